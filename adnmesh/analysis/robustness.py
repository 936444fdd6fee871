"""Robustness and performance over all subsets, adaptive vs static
(docs/method.md#robustness-and-performance).

Every subset of the table is evaluated as deployed: the adaptive controller with the subset's
own ``(K_P, K_I)`` and weights ``W`` (DER d contributes ``w_d P_inst,d``), the static controller
with its one pair and weights for every subset. Both use the reference model (PT1, nominal time
constants) with exact delays.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.analysis.subset_loops import SubsetBatch, deployed_batch, subset_name

__all__ = ["METRICS", "Metric", "RobustnessResult", "MetricSummary", "table_batches",
           "evaluate_batch", "analyze_robustness"]


@dataclass(frozen=True)
class Metric:
    """A figure of merit shown in the box plots.

    Attributes
    ----------
    key : str
        Field of :class:`adnmesh.loopmodel.evaluation.LoopFigures` (and CSV column suffix).
    label : str
        Axis label with unit.
    worse : str
        ``"high"`` if larger values are worse (times, overshoot), ``"low"`` for margins.
    """

    key: str
    label: str
    worse: str


METRICS = (
    Metric("rise_time_s", "rise time 10–90 % [s]", "high"),
    Metric("settling_time_s", "settling time (band) [s]", "high"),
    Metric("overshoot_pct", "overshoot [%]", "high"),
    Metric("disk_margin", "disk margin α", "low"),
    Metric("gain_margin", "gain margin (absolute)", "low"),
    Metric("phase_margin_deg", "phase margin [deg]", "low"),
    Metric("delay_margin_s", "delay margin [s]", "low"),
)

#: ``MetricSummary.worst_subset`` when every subset has the same value
ALL_EQUAL = "all equal"

#: further per-subset columns of the CSV
EXTRA_KEYS = ("settling_time_2pct_s", "peak_time_s", "stable")


@dataclass(frozen=True)
class MetricSummary:
    """Median and worst subset of one metric for one controller.

    ``worst_value`` is NaN and ``worst_subset`` empty when no subset has a finite value, and
    ``worst_subset`` is :data:`ALL_EQUAL` when every subset has the same value;
    ``unstable`` subsets are counted apart (their margins and step figures do not exist).
    """

    median: float
    worst_value: float
    worst_subset: str
    finite: int


@dataclass(frozen=True)
class RobustnessResult:
    """Figures of merit of every subset for the adaptive and the static controller.

    Attributes
    ----------
    subsets : tuple of tuple of str
    feasible : ndarray of bool, shape (M,)
        The table marks the entry feasible.
    adaptive, static : dict
        Metric key (``METRICS`` and ``EXTRA_KEYS``) -> ndarray of shape (M,); ``static`` is
        None when the table has no static controller.
    band_pct : float
        Settling band of ``settling_time_s``, percent.
    adaptive_batch, static_batch : SubsetBatch
        The loops evaluated (gains and weights as deployed).
    weights : tuple of dict
        Adaptive weights ``w_d`` per subset (dimensionless).
    """

    subsets: tuple[tuple[str, ...], ...]
    feasible: np.ndarray
    adaptive: dict
    static: dict | None
    band_pct: float
    adaptive_batch: SubsetBatch
    static_batch: SubsetBatch | None
    weights: tuple[dict, ...]

    @property
    def names(self) -> list[str]:
        return [subset_name(s) for s in self.subsets]

    @property
    def controllers(self) -> tuple[str, ...]:
        """``("adaptive", "static")``, or ``("adaptive",)`` without a static controller."""
        return ("adaptive",) if self.static is None else ("adaptive", "static")

    def unstable(self, controller: str) -> list[str]:
        """Names of the subsets whose closed loop is unstable with ``controller``."""
        stable = getattr(self, controller)["stable"]
        batch = getattr(self, f"{controller}_batch")
        return [n for n, ok, g in zip(self.names, stable, batch.has_gains) if g and not ok]

    def without_gains(self) -> list[str]:
        """Subsets whose table entry has no PI pair (not evaluated for the adaptive controller)."""
        return [n for n, g in zip(self.names, self.adaptive_batch.has_gains) if not g]

    def summary(self, controller: str) -> dict[str, MetricSummary]:
        """Per metric: median over subsets (finite values) and the worst subset."""
        values = getattr(self, controller)
        out = {}
        for m in METRICS:
            v = np.asarray(values[m.key], float)
            fin = np.isfinite(v)
            if m.key == "disk_margin":          # 0 for unstable loops: that is the worst
                fin = ~np.isnan(v)
            if not fin.any():
                out[m.key] = MetricSummary(float("nan"), float("nan"), "", 0)
                continue
            idx = np.nonzero(fin)[0]
            j = idx[np.argmax(v[idx])] if m.worse == "high" else idx[np.argmin(v[idx])]
            who = self.names[j] if np.ptp(v[idx]) > 0 else ALL_EQUAL
            out[m.key] = MetricSummary(float(np.median(v[idx])), float(v[j]), who,
                                       int(fin.sum()))
        return out

    def csv_rows(self) -> tuple[list[str], list[list]]:
        """Header and one row per subset, tidy (every cell one value; pandas reads it with
        its defaults): the subset's label, ``in_<der>`` (1 if the DER is in it, else 0) and
        ``w_<der>`` (its adaptive weight, empty if it is not in it) per DER, the gains
        (1/W, 1/(W s)), every figure of both controllers (empty: none)."""
        keys = [m.key for m in METRICS] + list(EXTRA_KEYS)
        ders = list(dict.fromkeys(d for s in self.subsets for d in s))
        header = (["subset", "n_ders", "feasible", "kp_per_w", "ki_per_w_s"]
                  + [f"in_{d}" for d in ders] + [f"w_{d}" for d in ders]
                  + [f"{c}_{k}" for c in self.controllers for k in keys])
        rows = []
        ab = self.adaptive_batch
        for i, s in enumerate(self.subsets):
            weights = self.weights[i]
            row = [subset_name(s), len(s), bool(self.feasible[i]), _cell(ab.kp[i]),
                   _cell(ab.ki[i])]
            row += [int(d in s) for d in ders]
            row += [_cell(weights[d]) if d in s and d in weights else "" for d in ders]
            for ctrl in self.controllers:
                row += [_cell(getattr(self, ctrl)[k][i]) for k in keys]
            rows.append(row)
        return header, rows


def _cell(v):
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    v = float(v)
    if np.isnan(v):
        return ""
    return "inf" if np.isinf(v) else f"{v:.6g}"


def table_batches(config, table) -> tuple[SubsetBatch, SubsetBatch | None, np.ndarray,
                                          list[dict]]:
    """The adaptive and static loops of every table entry, as deployed.

    Returns
    -------
    adaptive, static : SubsetBatch
        Same subsets (the table's entries by size, then config order); ``static`` is None
        when the table has no static controller.
    feasible : ndarray of bool
        The table's feasibility flag per entry.
    weights : list of dict
        Adaptive weights per entry.
    """
    order = {d: i for i, d in enumerate(config.der_ids())}
    entries = sorted(table.entries.values(),
                     key=lambda e: (len(e.ders), [order.get(d, len(order)) for d in e.ders]))
    subsets = [e.ders for e in entries]
    weights = [dict(e.w) for e in entries]
    adaptive = deployed_batch(config, subsets, [e.kp for e in entries],
                              [e.ki for e in entries], weights)
    st = table.static
    static = None if st is None else deployed_batch(config, subsets, st.kp, st.ki, dict(st.w))
    return adaptive, static, np.array([e.feasible for e in entries], bool), weights


def evaluate_batch(batch: SubsetBatch, band_pct: float, classical: bool = True,
                   chunk: int = 4096, progress: Callable[[int], None] | None = None,
                   model: str = "pt1", lag_scale: float = 1.0) -> dict:
    """Figures of merit (``METRICS`` and ``EXTRA_KEYS``) of every loop of the batch.

    :func:`adnmesh.loopmodel.evaluation.evaluate` in chunks (``progress(n)`` after each). Subsets without a PI
    pair (NaN gains) are not evaluated: NaN figures, ``stable`` False.
    """
    keys = [m.key for m in METRICS] + list(EXTRA_KEYS)
    out = {k: np.full(len(batch), np.nan) for k in keys}
    out["stable"] = np.zeros(len(batch), bool)
    valid = np.nonzero(batch.has_gains)[0]
    for start in range(0, valid.size, chunk):
        rows = valid[start:start + chunk]
        kp, ki = batch.gains(rows)
        f = evaluate(batch.plant(model, lag_scale, rows), kp, ki, band_pct=band_pct,
                     classical=classical)
        for k in keys:
            out[k][rows] = getattr(f, k)
        if progress is not None:
            progress(rows.size)
    if progress is not None and valid.size < len(batch):
        progress(len(batch) - valid.size)
    return out


def analyze_robustness(config, table, progress: Callable[[int], None] | None = None,
                       chunk: int = 4096) -> RobustnessResult:
    """Evaluate every table entry with the adaptive and the static controller.

    Parameters
    ----------
    config : adnmesh.config.Config
    table : adnmesh.tuning.table.SchedulingTable
        Its entries (all subsets, or those present) and its static controller (if any).
    progress : callable, optional
        Called with the number of loops just evaluated (M per controller).
    chunk : int
        Loops per :func:`adnmesh.loopmodel.evaluation.evaluate` call.
    """
    adaptive, static, feasible, weights = table_batches(config, table)
    band = config.constraints.settling_band_pct
    fa = evaluate_batch(adaptive, band, chunk=chunk, progress=progress)
    fs = None if static is None else evaluate_batch(static, band, chunk=chunk,
                                                    progress=progress)
    return RobustnessResult(adaptive.subsets, feasible, fa, fs, band, adaptive, static,
                            tuple(weights))
