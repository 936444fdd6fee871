"""Tuning of the gain-scheduling table CP: the paper's method, a global search that certifies
it, Find W, the static controller, and on-demand tuning of one subset
(docs/method.md#tuning-the-gain-table)."""
from adnmesh.tuning.build import METHODS, paper_path, tune_table, write_csv
from adnmesh.tuning.ondemand import tune_subset
from adnmesh.tuning.problem import TuningProblem, all_subsets

__all__ = ["METHODS", "TuningProblem", "all_subsets", "paper_path", "tune_subset", "tune_table",
           "write_csv"]
