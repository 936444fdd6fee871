"""adnmesh: adaptive cross-voltage-level power flow control of active distribution networks.

The package holds the pure numerics (reference model, margins, step information, tuning,
analyses), the configuration loader and the command-line interface. See ``README.md``.
"""

import os
from importlib.metadata import PackageNotFoundError, version

# OpenBLAS on one thread unless the user says otherwise (read when numpy loads, so this must
# run before it: the package imports nothing else first). Our products are tiny (a few
# actuator groups times a frequency grid); OpenBLAS's extra threads do no useful work on them
# but busy-wait after every call, which on the 2-core machine took half the CPU from the
# other tuning worker: the SimBench table took 67 s wall / 133 CPU s with them and 37 s /
# 72 CPU s without, bit for bit the same entries (benchmarks/bench_tuning.py). Processes
# started from here (tuning workers, agents) inherit it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

try:
    __version__ = version("adnmesh")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.1.0"

__all__ = ["__version__"]
