# covey developer entry points. Both targets build an idempotent .venv next to this file.
#   make demo   install the runtime and start `covey demo` (simulated fleet + browser ground station)
#   make test   install system packages, the runtime, torch and test tools, then run every test
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
# Debian packages the tests need: a browser for the ground-station tests, the Cortex-M7
# toolchain and emulator for the firmware tests, a C compiler for the host firmware build.
APT_PKGS := chromium gcc libc6-dev make gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm
export OMP_WAIT_POLICY ?= PASSIVE
export OPENBLAS_NUM_THREADS ?= 1
DEMO_ARGS ?=
PYTEST_ARGS ?=

.PHONY: demo test install install-test system-deps lint clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

$(VENV)/.runtime: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e .
	touch $@

$(VENV)/.test: pyproject.toml $(VENV)/.runtime
	$(BIN)/pip install -q -e '.[test,train]'
	touch $@

install: $(VENV)/.runtime
install-test: $(VENV)/.test

system-deps:
	@missing=""; for p in $(APT_PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" -eq 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -q && \
	  DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -q -o DPkg::Lock::Timeout=600 $$missing; \
	fi

demo: $(VENV)/.runtime
	$(BIN)/covey demo $(DEMO_ARGS)

test: system-deps $(VENV)/.test
	$(BIN)/ruff check .
	$(BIN)/python -m pytest $(PYTEST_ARGS)

lint: $(VENV)/.test
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) firmware/build .pytest_cache
