"""covey benchmarks: `covey bench` / `python -m bench` (see bench/__main__.py).

Importing the package sets OMP_WAIT_POLICY=PASSIVE and one BLAS thread before any section
loads numpy or torch: on a shared 2-core machine spinning BLAS threads make small calls
100-1000x slower (shared/DESIGN.md). Values already set by the caller win.
"""

import os

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
