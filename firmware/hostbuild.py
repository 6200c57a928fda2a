"""Builds the policy core for the host with the system C compiler, on demand.

Outputs go to firmware/build/ (gitignored), named by a hash of the sources, the
weights header and the flags, so a stale build is never reused and parallel
test runs never clobber each other (each writes a temp file, then renames).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from firmware.export_c import export_c_header

FIRMWARE_DIR = Path(__file__).resolve().parent
BUILD_DIR = FIRMWARE_DIR / "build"
CORE_C = tuple(
    FIRMWARE_DIR / f"covey_{m}.c"
    for m in ("policy", "traffic", "safety", "guidance", "zones", "fence")
)
CORE_H = tuple(
    FIRMWARE_DIR / f"covey_{m}.h"
    for m in ("policy", "traffic", "safety", "guidance", "zones", "fence")
)
DRIVER_SOURCE = FIRMWARE_DIR / "host" / "covey_driver.c"
BENCH_SOURCE = FIRMWARE_DIR / "host" / "covey_bench.c"
UNIT_SOURCE = FIRMWARE_DIR / "host" / "covey_unit.c"
ZONES_DRIVER_SOURCE = FIRMWARE_DIR / "host" / "covey_zones_driver.c"
FENCE_DRIVER_SOURCE = FIRMWARE_DIR / "host" / "covey_fence_driver.c"
SHIPPED_NPZ = FIRMWARE_DIR.parent / "policy" / "weights" / "policy.npz"
COMMITTED_HEADER = FIRMWARE_DIR / "covey_weights.h"

WARN_FLAGS = (
    "-std=c99",
    "-Wall",
    "-Wextra",
    "-Wpedantic",
    "-Wshadow",
    "-Wdouble-promotion",  # the core is float32: any silent double is a bug
    "-Wfloat-conversion",
    "-Werror",
)
# -O3 vectorises the transposed matvecs and the activation loops; -fno-trapping-math lets
# the clamps inside exp_f become selects (no value changes: no reassociation, no contraction
# under -std=c99); -march=native uses this host's vector width (AVX2: 183 -> 26 us at N = 20).
# COVEY_PORTABLE=1 drops -march=native (a baseline x86-64 / arm64 build, about 60 us).
OPT_FLAGS = (
    "-O3",
    "-fno-trapping-math",
    *(() if os.environ.get("COVEY_PORTABLE") == "1" else ("-march=native",)),
)
SANITIZE_FLAGS = (
    "-O1",
    "-g",
    "-fsanitize=address,undefined",
    "-fno-omit-frame-pointer",
    "-fno-sanitize-recover=all",
)


def compiler() -> str:
    """The C compiler: $CC or `cc`; raises if neither is on PATH."""
    cc = os.environ.get("CC", "cc")
    if shutil.which(cc) is None:
        raise FileNotFoundError(f"no C compiler {cc!r} on PATH (set CC)")
    return cc


def header_for(npz_path, out_dir: Path = BUILD_DIR) -> Path:
    """A freshly generated weights header for `npz_path`, inside the build dir."""
    digest = hashlib.sha256(Path(npz_path).read_bytes()).hexdigest()[:16]
    return export_c_header(npz_path, out_dir / "headers" / f"covey_weights_{digest}.h")


def _build(
    kind: str,
    header: Path,
    extra: tuple[str, ...],
    sources: tuple[Path, ...],
    suffix: str,
    defines: tuple[str, ...] = (),
) -> Path:
    cc = compiler()
    header = Path(header).resolve()
    flags = (
        *WARN_FLAGS,
        *extra,
        *defines,
        f'-DCOVEY_WEIGHTS_HEADER="{header}"',
        f"-I{FIRMWARE_DIR}",
    )
    h = hashlib.sha256()
    for p in (*CORE_C, *CORE_H, *sources, header):
        h.update(p.read_bytes())
    h.update(" ".join((cc, *flags)).encode())
    out = BUILD_DIR / f"{kind}-{h.hexdigest()[:16]}{suffix}"
    if out.exists():
        return out
    BUILD_DIR.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=BUILD_DIR, suffix=suffix + ".tmp")
    os.close(fd)
    cmd = [cc, *flags, "-o", tmp, *map(str, CORE_C), *map(str, sources), "-lm"]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        os.unlink(tmp)
        raise RuntimeError(f"C build failed:\n{' '.join(cmd)}\n{res.stderr[-3000:]}")
    os.replace(tmp, out)
    return out


def build_library(header: Path, defines: tuple[str, ...] = ()) -> Path:
    """Shared library of the core (for ctypes)."""
    suffix = ".dylib" if sys.platform == "darwin" else ".so"
    return _build("libcovey", header, (*OPT_FLAGS, "-shared", "-fPIC"), (), suffix, defines)


def build_driver(header: Path, sanitize: bool = False, defines: tuple[str, ...] = ()) -> Path:
    """The stdin/stdout test driver (firmware/host/covey_driver.c), optionally sanitized."""
    extra = SANITIZE_FLAGS if sanitize else OPT_FLAGS
    kind = "driver-asan" if sanitize else "driver"
    return _build(kind, header, extra, (DRIVER_SOURCE,), "", defines)


def build_unit(header: Path) -> Path:
    """The C unit tests (firmware/host/covey_unit.c), with ASan and UBSan."""
    return _build("unit-asan", header, SANITIZE_FLAGS, (UNIT_SOURCE,), "")


def build_zones_driver(header: Path) -> Path:
    """The keep-out zones' stdin/stdout driver (firmware/host/covey_zones_driver.c), with ASan
    and UBSan."""
    return _build("zones-driver-asan", header, SANITIZE_FLAGS, (ZONES_DRIVER_SOURCE,), "")


def build_fence_driver(header: Path) -> Path:
    """The geofence conversion's stdin/stdout driver (firmware/host/covey_fence_driver.c), with
    ASan and UBSan."""
    return _build("fence-driver-asan", header, SANITIZE_FLAGS, (FENCE_DRIVER_SOURCE,), "")


def build_bench(header: Path) -> Path:
    """The host timing program (firmware/host/covey_bench.c), -O2."""
    return _build("bench", header, OPT_FLAGS, (BENCH_SOURCE,), "")


def run_driver(driver: Path, text: str) -> tuple[list[str], str]:
    """Feeds cases to a driver; returns (stdout lines, stderr). Raises on a non-zero exit."""
    env = dict(
        os.environ,
        ASAN_OPTIONS="detect_leaks=1:abort_on_error=0",
        UBSAN_OPTIONS="print_stacktrace=1:halt_on_error=1",
    )
    res = subprocess.run([str(driver)], input=text, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        raise RuntimeError(f"{driver.name} exited {res.returncode}:\n{res.stderr[-4000:]}")
    return res.stdout.splitlines(), res.stderr
