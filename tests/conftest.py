"""Shared fixtures of the adnmesh test suite."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from adnmesh.config import Config, load_config

REPO_ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="session")
def configs_dir() -> Path:
    """The repository's ``configs/`` directory."""
    return REPO_ROOT / "configs"


@pytest.fixture(scope="session")
def simbench_config(configs_dir: Path) -> Config:
    """The reference case of SPEC §6, loaded from ``configs/simbench.yaml``."""
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
