"""A coarse scheduling table by grid search — for tests and examples, not for deployment.

:func:`coarse_table` picks, for every subset, the feasible pair with the lowest rise time on a
log grid of *normalised* gains ``kp_n = K_P sum P_inst`` (dimensionless) and
``ki_n = K_I sum P_inst`` (1/s), with all weights 1, and a static controller the same way on a
grid of absolute gains. It is what the analyses need to run without ``adnmesh tune`` (the
paper's method, :mod:`adnmesh.tuning`); its entries are feasible but not optimal.

:func:`example` and :func:`small_table` give the analysis tests the example configs and their
coarse tables, each built once per session.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Sequence

import numpy as np

from adnmesh.analysis.subset_loops import SubsetBatch, deployed_batch
from adnmesh.config import load_config
from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.tuning.design_key import design_document
from adnmesh.tuning.problem import all_subsets
from adnmesh.tuning.table import FIGURE_KEYS, SchedulingTable, TableEntry

__all__ = ["coarse_table", "feasibility", "example", "small_table", "EXAMPLES"]

EXAMPLES = Path(__file__).resolve().parent.parent / "configs" / "examples"

KP_N = np.geomspace(0.01, 3.0, 14)
KI_N = np.geomspace(0.001, 5.0, 14)


def feasibility(batch: SubsetBatch, constraints, time_mask=None, classical=False):
    """Figures of merit of the batch and its verdict per loop.

    Returns
    -------
    figures : LoopFigures
    reason : ndarray of str
        ``""`` (feasible), ``"unstable"``, ``"disk margin"`` or ``"overshoot"`` (the first
        constraint that fails, in that order).
    """
    f = evaluate(batch.plant(), batch.kp, batch.ki, band_pct=constraints.settling_band_pct,
                 classical=classical, time_mask=time_mask,
                 disk_margin_min=constraints.disk_margin_min)
    dm_ok = f.stable & (f.disk_margin >= constraints.disk_margin_min)
    os_ok = dm_ok & (f.overshoot_pct < constraints.overshoot_max_pct) & np.isfinite(f.rise_time_s)
    reason = np.where(~f.stable, "unstable",
                      np.where(~dm_ok, "disk margin", np.where(~os_ok, "overshoot", "")))
    return f, reason


def _figures(f, i: int) -> dict:
    row = f.row(i)
    return {k: row[k] for k in FIGURE_KEYS}


def coarse_table(config, subsets: Sequence[Sequence[str]] | None = None,
                 kp_n=KP_N, ki_n=KI_N, static_grid: int = 20) -> SchedulingTable:
    """Grid-search table for ``subsets`` (default: all) of ``config``, plus a static controller.

    Parameters
    ----------
    config : adnmesh.config.Config
    subsets : sequence of sequences of DER ids, optional
    kp_n, ki_n : array_like
        Grid of normalised gains (dimensionless and 1/s); ``K_P = kp_n / sum P_inst`` (1/W).
    static_grid : int
        Points per axis of the static controller's grid of absolute gains (spanning the
        normalised grid over the smallest and largest subset).
    """
    c = config.constraints
    subsets = all_subsets(config.der_ids()) if subsets is None else [tuple(s) for s in subsets]
    unit = deployed_batch(config, subsets, 1.0, 1.0)
    total = unit.gains_w.sum(axis=1)
    kpg, kig = (g.ravel() for g in np.meshgrid(np.asarray(kp_n, float), np.asarray(ki_n, float)))
    n = kpg.size
    rows = np.repeat(np.arange(len(subsets)), n)
    cand = SubsetBatch(tuple(unit.subsets[i] for i in rows), unit.actuators, unit.gains_w[rows],
                       np.tile(kpg, len(subsets)) / total[rows],
                       np.tile(kig, len(subsets)) / total[rows], unit.t_com_s, unit.t_meas_s)
    f, reason = feasibility(cand, c)
    rise = np.where(reason == "", f.rise_time_s, np.inf).reshape(len(subsets), n)
    best = np.argmin(rise, axis=1)
    table = SchedulingTable(config.sha256, {"disk_margin_min": c.disk_margin_min,
                                            "overshoot_max_pct": c.overshoot_max_pct,
                                            "settling_band_pct": c.settling_band_pct},
                            "coarse-grid", tuple(config.der_ids()),
                            design=design_document(config))
    kp = np.array([kpg[j] for j in best]) / total
    ki = np.array([kig[j] for j in best]) / total
    final = deployed_batch(config, subsets, kp, ki)
    ff, _ = feasibility(final, c, classical=True)
    for i, s in enumerate(final.subsets):
        ok = bool(np.isfinite(rise[i, best[i]]))
        table.add(TableEntry(s, float(kp[i]), float(ki[i]), {d: 1.0 for d in s}, ok,
                             None if ok else "no feasible grid point", _figures(ff, i)))
    # static controller: one absolute pair for every subset, best worst-case rise time
    kps = np.geomspace(kp_n[0] / total.max(), kp_n[-1] / total.min(), static_grid)
    kis = np.geomspace(ki_n[0] / total.max(), ki_n[-1] / total.min(), static_grid)
    kk, ii = (g.ravel() for g in np.meshgrid(kps, kis))
    m = len(subsets)
    rows = np.tile(np.arange(m), kk.size)
    cand = SubsetBatch(tuple(unit.subsets[i] for i in rows), unit.actuators, unit.gains_w[rows],
                       np.repeat(kk, m), np.repeat(ii, m), unit.t_com_s, unit.t_meas_s)
    freq = evaluate(cand.plant(), cand.kp, cand.ki, classical=False, time_domain=False)
    dm_all = np.all((freq.stable & (freq.disk_margin >= c.disk_margin_min)).reshape(-1, m), axis=1)
    f_s, r_s = feasibility(cand, c, time_mask=np.repeat(dm_all, m))
    ok = np.all((r_s == "").reshape(-1, m), axis=1)
    worst = np.where(ok, np.max(np.where(r_s == "", f_s.rise_time_s, np.inf).reshape(-1, m),
                                axis=1), np.inf).reshape(kis.size, kps.size)
    a, b = np.unravel_index(np.argmin(worst), worst.shape)
    sb = deployed_batch(config, [tuple(config.der_ids())], kps[b], kis[a])
    fs, _ = feasibility(sb, c, classical=True)
    ok = bool(np.isfinite(worst[a, b]))
    table.static = TableEntry(tuple(config.der_ids()), float(kps[b]), float(kis[a]),
                              {d: 1.0 for d in config.der_ids()}, ok,
                              None if ok else "no feasible grid point", _figures(fs, 0))
    table.complete = len(subsets) == 2 ** len(config.ders) - 1
    return table


@lru_cache(maxsize=None)
def example(name: str):
    """The config ``configs/examples/<name>.yaml``."""
    return load_config(EXAMPLES / f"{name}.yaml")


@lru_cache(maxsize=None)
def small_table(name: str):
    """A coarse table (8 x 8 normalised grid, 8 x 8 static grid) for an example config."""
    return coarse_table(example(name), kp_n=np.geomspace(0.01, 3.0, 8),
                        ki_n=np.geomspace(0.001, 5.0, 8), static_grid=8)
