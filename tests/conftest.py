"""Shared fixtures of the adnmesh test suite."""

from __future__ import annotations

import fcntl
import os
import signal
from pathlib import Path

import adnmesh

# first: OpenBLAS on one thread, read when numpy loads, as the command line does (so a test that
# runs adnmesh.cli.main in this process leaves the environment as it found it)
adnmesh.one_blas_thread()
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from adnmesh.config import Config, load_config  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="session")
def configs_dir() -> Path:
    """The repository's ``configs/`` directory."""
    return REPO_ROOT / "configs"


@pytest.fixture(scope="session")
def simbench_config(configs_dir: Path) -> Config:
    """The reference case (docs/method.md#reference-case), loaded from ``configs/simbench.yaml``."""
    return load_config(configs_dir / "simbench.yaml")


# Variables that are not a test's doing: pytest updates the first in every phase, and importing
# pandapower (through pandera) sets the other two once.
_NOT_A_TESTS_DOING = {"PYTEST_CURRENT_TEST", "SPARK_LOCAL_IP", "PYARROW_IGNORE_TIMEZONE"}


def _environ() -> dict[str, str]:
    """``os.environ`` less :data:`_NOT_A_TESTS_DOING`."""
    return {k: v for k, v in os.environ.items() if k not in _NOT_A_TESTS_DOING}


@pytest.fixture(autouse=True)
def _no_global_state_changed():
    """Fail a test that leaves the working directory, the environment or numpy's RNG changed."""
    cwd, environ, rng_state = os.getcwd(), _environ(), np.random.get_state()
    yield
    assert os.getcwd() == cwd, "test changed the working directory"
    assert _environ() == environ, "test changed os.environ"
    after = np.random.get_state()
    assert all(np.array_equal(a, b) for a, b in zip(rng_state, after)), (
        "test changed numpy's global random state"
    )


#: modules whose tests bound the processes, sessions or threads they start by wall-clock time
#: tightly (test_wheel's and test_reference_case's bounds, 120-900 s, hold beside the 100-DER
#: run at nice 19: waiting for it cost the suite's other worker 30-54 s of every CI run)
_TIMED_MODULES = {"test_acl", "test_cli", "test_inspect", "test_margins_cli", "test_recording",
                  "test_runtime_faults", "test_runtime_secure", "test_runtime_up",
                  "test_tuning_fallback"}
#: longest wait for the machine lock, s (the test holding it is bounded by its own timeouts)
_LOCK_WAIT_S = 3600


def _flock(fd: int, operation: int, what: str) -> None:
    """``flock`` bounded by :data:`_LOCK_WAIT_S` (an alarm interrupts the blocking call)."""
    def expired(signum, frame):
        raise TimeoutError
    previous = signal.signal(signal.SIGALRM, expired)
    signal.alarm(_LOCK_WAIT_S)
    try:
        fcntl.flock(fd, operation)
    except TimeoutError:
        pytest.fail(f"waited {_LOCK_WAIT_S} s for the machine lock ({what})")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.fixture(autouse=True)
def _machine_share(request, tmp_path_factory):
    """A test marked ``machine_alone`` (the 100-DER run: 104 processes on 2 cores) has the
    machine to itself with respect to the timed tests: it holds an exclusive lock on a file
    that every xdist worker of the session sees, and the tests of :data:`_TIMED_MODULES` hold
    it shared. Beside the 100-DER run their wall-clock bounds were missed (CI, load ~58); the
    other tests run beside it (they are only slower)."""
    alone = request.node.get_closest_marker("machine_alone") is not None
    if not alone and Path(request.node.path).stem not in _TIMED_MODULES:
        yield
        return
    path = tmp_path_factory.getbasetemp().parent / "adnmesh-machine.lock"
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        _flock(fd, fcntl.LOCK_EX if alone else fcntl.LOCK_SH, request.node.nodeid)
        yield
    finally:
        os.close(fd)                           # releases the lock
