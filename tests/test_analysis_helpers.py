"""Shared small tables for the analysis tests (built once per session by grid search).

No tests here: the helpers build coarse scheduling tables for the small example configs with
:func:`coarse_table.coarse_table` (tests/coarse_table.py), so the analyses can be tested without a tuner.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from coarse_table import coarse_table
from adnmesh.config import load_config

EXAMPLES = Path(__file__).resolve().parent.parent / "configs" / "examples"


@lru_cache(maxsize=None)
def example(name: str):
    """The config ``configs/examples/<name>.yaml``."""
    return load_config(EXAMPLES / f"{name}.yaml")


@lru_cache(maxsize=None)
def small_table(name: str):
    """A coarse table (8 x 8 normalised grid, 8 x 8 static grid) for an example config."""
    return coarse_table(example(name), kp_n=np.geomspace(0.01, 3.0, 8),
                        ki_n=np.geomspace(0.001, 5.0, 8), static_grid=8)
