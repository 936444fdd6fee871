"""adnmesh: adaptive cross-voltage-level power flow control of an active distribution network,
tuned offline and run as a mesh of communicating processes.

The foundation, which imports nothing heavy: :mod:`~adnmesh.config` (the YAML config, validated),
:mod:`~adnmesh.errors` (the one-line user errors), :mod:`~adnmesh.names` (the ids and names on
the bus), :mod:`~adnmesh.files` (atomic file writes) and :mod:`~adnmesh.cli` (the ``adnmesh``
command line, one module per subcommand in :mod:`~adnmesh.commands`). Then the subpackages:

- numerics, pure: :mod:`~adnmesh.loopmodel` (the reference loop: plant, frequency and step
  response, stability, margins, the compiled kernels), :mod:`~adnmesh.tuning` (the gain table:
  the paper's method, the global search, Find W, the static controller, on-demand tuning),
  :mod:`~adnmesh.analysis` (robustness, model uncertainty, solution space),
  :mod:`~adnmesh.grid` (the SimBench grid and its power flow) and :mod:`~adnmesh.dermodels`
  (detailed DER models for time-domain runs);
- the running system: :mod:`~adnmesh.wire` (messages and keys on the bus),
  :mod:`~adnmesh.control` (the controllers of the agents), :mod:`~adnmesh.sim` (time, links and
  faults), :mod:`~adnmesh.recording` (MCAP recordings), :mod:`~adnmesh.results` (what a run
  means: series, figures, summaries), :mod:`~adnmesh.runtime` (processes, bus, security) and
  :mod:`~adnmesh.agents` (the agent programs, ``python -m adnmesh.agents.<kind>``).

See ``README.md`` and ``docs/``.

**OpenBLAS threads.** Importing adnmesh changes nothing in the process. The ``adnmesh`` command
line calls :func:`one_blas_thread` before numpy loads, so that the tuning, its worker processes
and the agents ``adnmesh up`` starts (they inherit its environment) run numpy's OpenBLAS on one
thread. A program that uses adnmesh as a library and wants the same calls
:func:`one_blas_thread` before it first imports numpy (or sets ``OPENBLAS_NUM_THREADS=1`` in
its environment).
"""

import os
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("adnmesh")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.1.0"

__all__ = ["__version__", "one_blas_thread", "BLAS_THREADS_ENV"]

BLAS_THREADS_ENV = "OPENBLAS_NUM_THREADS"
"""The variable numpy's OpenBLAS reads its thread count from, once, when numpy loads."""


def one_blas_thread() -> None:
    """Set ``OPENBLAS_NUM_THREADS=1`` in this process's environment unless it is set.

    Our products are tiny (a few actuator groups times a frequency grid); OpenBLAS's extra
    threads do no useful work on them but busy-wait after every call, which on the 2-core
    machine took half the CPU from the other tuning worker: the SimBench table took 67 s wall
    / 133 CPU s with them and 37 s / 72 CPU s without, bit for bit the same entries
    (benchmarks/bench_tuning.py). It acts only if numpy has not been imported yet in this
    process; processes started afterwards inherit it.
    """
    os.environ.setdefault(BLAS_THREADS_ENV, "1")
