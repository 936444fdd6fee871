"""Solution space of one subset: feasibility and rise time over the (K_P, K_I) plane
(docs/method.md#solution-space).

The plane is that of the tuning problem (docs/method.md#the-papers-method, initial values and path
search): the subset's reference loop with
all weights 1. Every grid point is classified by the first constraint it fails — ``unstable``,
``disk margin`` (alpha below the minimum) or ``overshoot`` (at or above the maximum) — or as
feasible; rise time and overshoot come from full step responses of every point that meets the
disk-margin constraint.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from adnmesh.analysis.subset_loops import deployed_batch, subset_name
from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.tuning.build import paper_path as tuner_path

__all__ = ["REASONS", "SolutionSpace", "solution_space", "paper_path"]

#: classes of a grid point, in the order they are checked
REASONS = ("unstable", "disk margin", "overshoot", "")

#: default extent of the plane in normalised gains: kp_n = K_P sum P_inst, ki_n = K_I sum P_inst
KP_N_RANGE = (0.01, 3.0)
KI_N_RANGE = (0.001, 5.0)


@dataclass(frozen=True)
class SolutionSpace:
    """Grid over the (K_P, K_I) plane of one subset.

    Attributes
    ----------
    ders : tuple of str
        The subset.
    kp : ndarray, shape (NP,)
        Proportional gains of the grid, 1/W (log-spaced).
    ki : ndarray, shape (NI,)
        Integral gains, 1/(W s).
    reason : ndarray of str, shape (NI, NP)
        ``""`` where feasible, else the first constraint failed (:data:`REASONS`).
    rise_time_s, overshoot_pct, disk_margin : ndarray, shape (NI, NP)
        NaN where not computed (rise time and overshoot need the disk-margin constraint met).
    path : tuple of (kp, ki, feasible)
        The paper method's search path (1/W, 1/(W s)), empty if unavailable.
    table_point : (kp, ki) or None
        The table's gains for the subset.
    constraints : dict
        ``disk_margin_min``, ``overshoot_max_pct``.
    p_inst_w : float
        Installed power of the subset, W (``kp_n = K_P p_inst_w``).
    """

    ders: tuple[str, ...]
    kp: np.ndarray
    ki: np.ndarray
    reason: np.ndarray
    rise_time_s: np.ndarray
    overshoot_pct: np.ndarray
    disk_margin: np.ndarray
    path: tuple = ()
    table_point: tuple | None = None
    constraints: dict | None = None
    p_inst_w: float = 1.0

    @property
    def name(self) -> str:
        return subset_name(self.ders)

    @property
    def feasible(self) -> np.ndarray:
        return self.reason == ""

    def best(self) -> tuple[float, float, float] | None:
        """``(kp, ki, rise_time_s)`` of the grid's fastest feasible point, or None."""
        rise = np.where(self.feasible, self.rise_time_s, np.inf)
        if not np.isfinite(rise).any():
            return None
        i, j = np.unravel_index(np.argmin(rise), rise.shape)
        return float(self.kp[j]), float(self.ki[i]), float(rise[i, j])

    def counts(self) -> dict[str, int]:
        """Grid points per class (``"feasible"`` for ``""``)."""
        return {r or "feasible": int(np.sum(self.reason == r)) for r in REASONS}


def paper_path(config, ders: Sequence[str]) -> list[tuple[float, float, bool]]:
    """The paper method's search path for ``ders``
    (:func:`adnmesh.tuning.build.paper_path`) as ``(kp, ki, feasible)`` (1/W, 1/(W s))."""
    return [(float(kp), float(ki), bool(ok)) for kp, ki, ok in tuner_path(config, list(ders))]


def _span(lo: float, hi: float, points) -> tuple[float, float]:
    """``(lo, hi)`` widened to hold ``points`` with a margin of 25 %."""
    pts = [p for p in points if p > 0]
    if not pts:
        return lo, hi
    return min(lo, min(pts) / 1.25), max(hi, max(pts) * 1.25)


def solution_space(config, ders: Sequence[str], n: int = 60, path=None, table_point=None,
                   kp_range: tuple[float, float] | None = None,
                   ki_range: tuple[float, float] | None = None,
                   progress: Callable[[int], None] | None = None,
                   chunk: int = 400) -> SolutionSpace:
    """Classify an ``n x n`` log grid of the subset's (K_P, K_I) plane.

    Parameters
    ----------
    config : adnmesh.config.Config
    ders : sequence of str
        The subset's DER ids.
    n : int
        Grid points per axis.
    path : sequence of (kp, ki, feasible), optional
        Search path to show (the plane is widened to contain it).
    table_point : (kp, ki), optional
        The table's gains for the subset (the plane is widened to contain them).
    kp_range, ki_range : (float, float), optional
        Extent in 1/W and 1/(W s); default the normalised ranges ``kp_n`` in
        [0.01, 3] and ``ki_n`` in [0.001, 5] 1/s divided by the subset's installed power.
    progress : callable, optional
        Called with the number of grid points just evaluated.
    """
    c = config.constraints
    one = deployed_batch(config, [tuple(ders)], 1.0, 1.0)
    p_inst = float(one.gains_w.sum())
    path = tuple(path or ())
    extra_kp = [p[0] for p in path] + ([table_point[0]] if table_point else [])
    extra_ki = [p[1] for p in path] + ([table_point[1]] if table_point else [])
    if kp_range is None:
        kp_range = _span(KP_N_RANGE[0] / p_inst, KP_N_RANGE[1] / p_inst, extra_kp)
    if ki_range is None:
        ki_range = _span(KI_N_RANGE[0] / p_inst, KI_N_RANGE[1] / p_inst, extra_ki)
    kp = np.geomspace(*kp_range, n)
    ki = np.geomspace(*ki_range, n)
    kk, ii = (g.ravel() for g in np.meshgrid(kp, ki))
    plant = one.plant()
    out = {k: np.full(kk.size, np.nan) for k in ("rise", "os", "dm")}
    stable = np.zeros(kk.size, bool)
    for start in range(0, kk.size, chunk):
        sl = slice(start, min(kk.size, start + chunk))
        f = evaluate(plant, kk[sl], ii[sl], band_pct=c.settling_band_pct, classical=False,
                     disk_margin_min=c.disk_margin_min)
        stable[sl] = f.stable
        out["rise"][sl], out["os"][sl], out["dm"][sl] = (f.rise_time_s, f.overshoot_pct,
                                                         f.disk_margin)
        if progress is not None:
            progress(sl.stop - sl.start)
    dm_ok = stable & (out["dm"] >= c.disk_margin_min)
    os_ok = dm_ok & (out["os"] < c.overshoot_max_pct) & np.isfinite(out["rise"])
    reason = np.where(~stable, "unstable",
                      np.where(~dm_ok, "disk margin", np.where(~os_ok, "overshoot", "")))
    shape = (n, n)
    return SolutionSpace(tuple(one.subsets[0]), kp, ki, reason.reshape(shape),
                         out["rise"].reshape(shape), out["os"].reshape(shape),
                         out["dm"].reshape(shape), path,
                         None if table_point is None else tuple(map(float, table_point)),
                         {"disk_margin_min": c.disk_margin_min,
                          "overshoot_max_pct": c.overshoot_max_pct}, p_inst)
