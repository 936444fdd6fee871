"""Tuning of the gain-scheduling table CP: the paper's method, a global search that certifies
it, Find W, the static controller, and on-demand tuning of one subset
(docs/method.md#tuning-the-gain-table).

The names below are imported on first use (PEP 562): the CPFC agent needs only the table and
the subset selection, not the numerics behind tuning (numba, scipy), which load when a subset
is tuned.
"""
import importlib

__all__ = ["METHODS", "TuningProblem", "all_subsets", "paper_path", "tune_subset", "tune_table",
           "write_csv"]

_HOME = {"METHODS": "build", "paper_path": "build", "tune_table": "build", "write_csv": "build",
         "tune_subset": "ondemand", "TuningProblem": "problem", "all_subsets": "problem"}


def __getattr__(name: str):
    if name not in _HOME:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_HOME[name]}"), name)
