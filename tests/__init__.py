"""The test suite. BLAS runs on one thread, as `rig` runs it (rig.cli): on two cores a second
BLAS thread only spins against the other process or test."""

import os

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")  # before anything imports numpy
