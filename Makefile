# covey developer entry points. Both targets build an idempotent .venv next to this file, from
# the locked versions in requirements.lock (pip) and .ci/apt.lock (Debian).
#   make demo   install the runtime and start `covey demo` (simulated fleet + browser ground station)
#   make test   install system packages, the runtime, torch and test tools, then run every test
#   make lock   re-resolve pyproject.toml's ranges to today's newest versions and rewrite both locks
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
LOCK := requirements.lock
# PIP_CONSTRAINT (not -c) also reaches pip's isolated build environments, so setuptools is locked.
PIP := PIP_CONSTRAINT=$(CURDIR)/$(LOCK) PIP_DISABLE_PIP_VERSION_CHECK=1 $(BIN)/pip install -q
# Debian packages the tests need: a browser for the ground-station tests, the Cortex-M7
# toolchain and emulator for the firmware tests, a C compiler for the host firmware build.
APT_PKGS := chromium gcc libc6-dev make gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm
export OMP_WAIT_POLICY ?= PASSIVE
export OPENBLAS_NUM_THREADS ?= 1
DEMO_ARGS ?=
PYTEST_ARGS ?=

.PHONY: demo test install install-test system-deps lint lock clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(PIP) pip setuptools

$(VENV)/.runtime: pyproject.toml $(LOCK) | $(BIN)/python
	$(PIP) -e .
	touch $@

$(VENV)/.test: pyproject.toml $(LOCK) $(VENV)/.runtime
	$(PIP) -e '.[test,train]'
	touch $@

install: $(VENV)/.runtime
install-test: $(VENV)/.test

system-deps:
	bash .ci/apt-install

demo: $(VENV)/.runtime
	$(BIN)/covey demo $(DEMO_ARGS)

test: system-deps $(VENV)/.test
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/python -m pytest $(PYTEST_ARGS)

lint: $(VENV)/.test
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

# Fresh resolution in a throw-away venv: newest versions within pyproject.toml's ranges.
lock:
	rm -rf .lock-venv
	$(PY) -m venv .lock-venv
	.lock-venv/bin/pip install -q --upgrade pip setuptools
	.lock-venv/bin/pip install -q -e '.[test,train]'
	{ echo "# pip versions covey's suite passed with (Python 3.11, Linux x86-64). Installed as"; \
	  echo "# constraints by 'make demo' / 'make test'; refresh with 'make lock', then run 'make test'."; \
	  .lock-venv/bin/pip freeze --all --exclude-editable | LC_ALL=C sort -f; } > $(LOCK)
	rm -rf .lock-venv
	{ sed -n '1,2p' .ci/apt.lock; \
	  for p in $(APT_PKGS); do echo "$$p=$$(dpkg-query -W -f='$${Version}' $$p)"; done; } > .ci/apt.lock.new
	mv .ci/apt.lock.new .ci/apt.lock

clean:
	rm -rf $(VENV) firmware/build .pytest_cache .mypy_cache
