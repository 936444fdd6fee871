"""A year of intervals: the power flow, the guard and the entry of each (docs/study.md).

:func:`study_year` takes the config, the grid's :class:`~adnmesh.grid.profiles.YearProfiles`
and the grid model at the profiles' first interval, and for every interval:

1. each DER's **available power** is its sgen's profile power (at most ``p_inst_w``), its
   **availability** :func:`adnmesh.study.availability.availability`'s, its **schedule**
   ``study.schedule``'s (``share``: the share of its available power its ``p_sched_w`` is at
   the config's operating point; ``config``: its ``p_sched_w``, at most what it can deliver);
2. the **power flow** with every load and generator at its profile and each DER at what it
   feeds in (its reactive power: ``q_sched_var`` with a Q loop, else its sgen's): its schedule when available or cut off by ICT (a DER without its CPFC falls back
   to its schedule), its available power when below the minimum output (not an actuator,
   still producing), nothing in maintenance: P_IP, Q_IP, the extreme voltages and loadings;
3. where a voltage or a loading is within the guard's margin of its limit, the **guard**
   (:class:`adnmesh.control.grid_guard.GridGuard`, fresh for each interval: a quarter hour
   is longer than any hysteresis) with the exact sensitivities at that point tells which DERs
   may not move up or down; in mode ``block`` a limit beyond itself blocks every DER;
4. the **headroom** of each available DER (up: available power less schedule; down: the
   schedule), the **entry** of the DERs each direction may use
   (:class:`adnmesh.study.entries.EntryFigures`) and the ranges and service of
   :mod:`adnmesh.study.ranges`; and for every DER the same without it (its contribution).

Deterministic: the same config, profiles and interval range give the same result.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from adnmesh.study.availability import AVAILABLE, ICT, LOW_OUTPUT, availability
from adnmesh.study.entries import EntryFigures
from adnmesh.study.ranges import direction
from adnmesh.tuning.subset_selection import DIRECTION_HEADROOM

__all__ = ["StudyResult", "study_year", "schedules"]


@dataclass
class StudyResult:
    """What :func:`study_year` found.

    Attributes
    ----------
    columns : dict of str -> ndarray
        One value per interval (docs/study.md#files names and units them).
    der_ids : tuple of str
    p_avail_w, p_sched_w : ndarray, shape (T, n)
        Each DER's available power and schedule per interval, W.
    reason : ndarray of int8, shape (T, n)
        Availability reason codes (:data:`adnmesh.study.availability.REASONS`).
    contribution : dict of str -> ndarray, shape (n,)
        Per DER, summed over the intervals: range and linear range lost up and down without
        it (W·intervals), service intervals lost, settling time added (s·intervals).
    subsets, tuned : int
        Distinct subsets the year went through; of them tuned on demand.
    step_s : float
        Length of an interval, s.
    service_w : float
        The service size the ranges were checked against, W.
    """

    columns: dict
    der_ids: tuple
    p_avail_w: np.ndarray
    p_sched_w: np.ndarray
    reason: np.ndarray
    contribution: dict
    subsets: int
    tuned: int
    step_s: float
    service_w: float = 0.0

    def __len__(self) -> int:
        return int(self.p_avail_w.shape[0])


def schedules(config, p_avail_w: np.ndarray, p_avail_op_w: np.ndarray) -> np.ndarray:
    """Each DER's schedule per interval, W (``study.schedule``; module docstring)."""
    p_sched = np.array([d.p_sched_w for d in config.ders], dtype=float)
    if config.study.schedule == "config":
        return np.minimum(p_sched[None, :], p_avail_w)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(p_avail_op_w > 0, p_sched / p_avail_op_w, 0.0)
    return np.clip(share, 0.0, 1.0)[None, :] * p_avail_w


def study_year(config, profiles, data, p_avail_op_w: np.ndarray, table=None,
               first_interval: int = 0,
               progress: Callable[[int, int], None] | None = None) -> StudyResult:
    """Study every interval of ``profiles`` (see the module docstring).

    Parameters
    ----------
    config : adnmesh.config.Config
        With a grid model whose net ``profiles`` and ``data`` are of.
    profiles : adnmesh.grid.profiles.YearProfiles
        The intervals to study.
    data : adnmesh.grid.GridData
        The grid model (at any operating point of the same net and load model).
    p_avail_op_w : ndarray, shape (n,)
        Each DER's available power at the config's operating point, W (for the ``share``
        schedule).
    table : SchedulingTable, optional
        The gain table; subsets it lacks are tuned on demand.
    first_interval : int
        Index of ``profiles``' first interval in the year (for the ICT draws).
    progress : callable, optional
        ``progress(done, total)`` every few hundred intervals.
    """
    from adnmesh.grid import GridSolver

    ders = config.ders
    ids = config.der_ids()
    n, total = len(ders), len(profiles)
    solver = GridSolver(data, [d.sgen for d in ders])
    index = data.sgen_index([d.sgen for d in ders])
    p_inst = np.array([d.p_inst_w for d in ders], dtype=float)
    p_avail = np.minimum(profiles.sgen_p[:, index] * 1e6, p_inst[None, :])
    p_avail = np.maximum(p_avail, 0.0)
    rules = config.study
    min_share = np.array([getattr(rules.min_output_share, d.type) for d in ders])
    reason = availability(p_avail, p_inst, min_share, profiles.times, rules.maintenance, ids,
                          rules.ict_availability, config.runtime.seed, first_interval)
    sched = schedules(config, p_avail, p_avail_op_w)
    available = reason == AVAILABLE
    infeed = np.where((reason == AVAILABLE) | (reason == ICT), sched,
                      np.where(reason == LOW_OUTPUT, p_avail, 0.0))
    q_der = (np.array([d.q_sched_var for d in ders], dtype=float) if config.reactive is not None
             else data.sgen_q_mvar[index] * 1e6)       # the Q schedules with a Q loop

    grid = _grid_columns(total)
    blocked_up = np.zeros((total, n), dtype=bool)
    blocked_down = np.zeros((total, n), dtype=bool)
    model = config.grid_model
    guard_levels = _engage_levels(model)
    for k in range(total):
        solver.set_injections(profiles.injections(k))
        sample = solver.solve(infeed[k], q_der)
        _store(grid, k, sample)
        if sample.converged and model.guard.mode != "off":
            up, down, engaged = _guard(solver, sample, model, ids, infeed[k], q_der,
                                       guard_levels)
            grid["limited"][k] = engaged
            blocked_up[k], blocked_down[k] = up, down
        if progress is not None and (k % 500 == 499 or k == total - 1):
            progress(k + 1, total)

    limits = model.limits
    with np.errstate(invalid="ignore"):             # NaN where not converged: not violated
        grid["violated"] = ((grid["vm_min_pu"] < limits.v_min_pu)
                            | (grid["vm_max_pu"] > limits.v_max_pu)
                            | (np.fmax(grid["line_max_pct"], grid["trafo_max_pct"])
                               > limits.loading_max_pct))
    entries = EntryFigures(config, table)
    margin = DIRECTION_HEADROOM * p_inst[None, :]
    use_up = available & ~blocked_up & (p_avail - sched >= margin)
    use_down = available & ~blocked_down & (sched >= margin)
    columns, contribution = _ranges(config, entries, available, use_up, use_down,
                                    p_avail - sched, sched)
    for name in ("service", "service_up", "service_down"):   # no grid, no service
        columns[name] &= grid["converged"]
    columns.update(grid)
    columns["interval"] = np.arange(first_interval, first_interval + total)
    columns["time"] = profiles.times
    columns["n_available"] = available.sum(axis=1)
    columns["available"] = _id_lists(available, ids)
    columns["blocked_up"] = _id_lists(blocked_up & available, ids)
    columns["blocked_down"] = _id_lists(blocked_down & available, ids)
    return StudyResult(columns=columns, der_ids=ids, p_avail_w=p_avail, p_sched_w=sched,
                       reason=reason, contribution=contribution,
                       subsets=entries.subsets, tuned=entries.tuned,
                       step_s=profiles.step_s, service_w=config.study.service_w)


_GRID_FLOAT = ("p_ip_w", "q_ip_var", "vm_min_pu", "vm_max_pu", "line_max_pct",
               "trafo_max_pct")
_GRID_TEXT = ("vm_min_at", "vm_max_at", "line_max_at", "trafo_max_at")


def _grid_columns(total: int) -> dict:
    out = {name: np.full(total, np.nan) for name in _GRID_FLOAT}
    out.update({name: np.empty(total, dtype=object) for name in _GRID_TEXT})
    out["converged"] = np.zeros(total, dtype=bool)
    out["limited"] = np.zeros(total, dtype=bool)
    return out


def _store(grid: dict, k: int, s) -> None:
    grid["p_ip_w"][k], grid["q_ip_var"][k] = s.p_ip_w, s.q_ip_var
    grid["vm_min_pu"][k], grid["vm_max_pu"][k] = s.vm_min_pu, s.vm_max_pu
    grid["line_max_pct"][k] = s.line_loading_max_pct
    grid["trafo_max_pct"][k] = s.trafo_loading_max_pct
    grid["vm_min_at"][k], grid["vm_max_at"][k] = s.vm_min_at, s.vm_max_at
    grid["line_max_at"][k], grid["trafo_max_at"][k] = s.line_max_at, s.trafo_max_at
    grid["converged"][k] = s.converged


def _engage_levels(model) -> tuple[float, float, float]:
    """The guard's engaging levels: (low voltage, high voltage, loading), p.u. and %."""
    lim, g = model.limits, model.guard
    return (lim.v_min_pu + g.v_margin_pu, lim.v_max_pu - g.v_margin_pu,
            lim.loading_max_pct - g.loading_margin_pct)


def _guard(solver, sample, model, ids, p_w, q_var, levels):
    """``(blocked up, blocked down, engaged)`` at the solver's last solution (``sample``, whose
    extremes tell whether any quantity is within its margin)."""
    v_low, v_high, loading = levels
    line, trafo = sample.line_loading_max_pct, sample.trafo_loading_max_pct
    top = max(line if line == line else 0.0, trafo if trafo == trafo else 0.0)  # NaN: none
    engaged = bool(sample.vm_min_pu < v_low or sample.vm_max_pu > v_high or top > loading)
    n = len(ids)
    none = np.zeros(n, dtype=bool)
    if not engaged:
        return none, none, False
    from adnmesh.control.grid_guard import GridGuard, GuardValues
    from adnmesh.grid.sensitivity import limit_sensitivities

    guard = GridGuard(model.guard, model.limits, ids, reactive=False)
    values = GuardValues(solver.bus_vm_pu(), solver.line_loading_pct(),
                         solver.trafo_loading_pct(), solver.bus_names, solver.line_names,
                         solver.trafo_names)
    guard.observe(0, values, lambda: limit_sensitivities(solver, p_w, q_var))
    state = guard.state()
    if state["hold"]:
        every = np.ones(n, dtype=bool)
        return every, every, True
    return (np.isin(ids, state["p_up"]), np.isin(ids, state["p_down"]), True)


def _id_lists(mask: np.ndarray, ids) -> np.ndarray:
    """Each row's ids where ``mask`` holds, space-separated (a text per interval)."""
    names = np.array(ids, dtype=object)
    keys, inverse = np.unique(np.packbits(mask, axis=1), axis=0, return_inverse=True)
    texts = [" ".join(names[np.unpackbits(key)[:mask.shape[1]].astype(bool)]) for key in keys]
    return np.array(texts, dtype=object)[inverse.ravel()]


def _ranges(config, entries: EntryFigures, available, use_up, use_down, head_up, head_down):
    """Per-interval range, entry and service columns and per-DER contributions, one
    vectorised pass per distinct triple of subsets (available, usable up, usable down)."""
    study = config.study
    s_w, s_s = study.service_w, study.service_s
    total, n = available.shape
    head_up = np.where(available, np.maximum(head_up, 0.0), 0.0)
    head_down = np.where(available, np.maximum(head_down, 0.0), 0.0)
    cols = {name: np.full(total, np.nan) for name in (
        "range_up_w", "range_down_w", "linear_up_w", "linear_down_w", "rise_s", "settling_s",
        "overshoot_pct", "disk_margin", "settling_up_s", "settling_down_s", "rise_up_s",
        "overshoot_up_pct")}
    for name in ("feasible", "service_up", "service_down", "service", "tuned_on_demand"):
        cols[name] = np.zeros(total, dtype=bool)
    contribution = {name: np.zeros(n) for name in (
        "range_up_lost_w", "range_down_lost_w", "linear_up_lost_w", "linear_down_lost_w",
        "service_lost", "settling_added_s", "intervals_available")}
    key = np.concatenate([np.packbits(available, axis=1), np.packbits(use_up, axis=1),
                          np.packbits(use_down, axis=1)], axis=1)
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    bounds = np.flatnonzero(np.diff(inverse[order])) + 1
    for rows in np.split(order, bounds):
        k = rows[0]
        mask_all, mask_up, mask_down = available[k], use_up[k], use_down[k]
        f_all, f_up, f_down = entries(mask_all), entries(mask_up), entries(mask_down)
        hu, hd = head_up[rows], head_down[rows]
        r_up, l_up, ok_up = direction(hu, mask_up, f_up, s_w, s_s)
        r_dn, l_dn, ok_dn = direction(hd, mask_down, f_down, s_w, s_s)
        cols["range_up_w"][rows], cols["linear_up_w"][rows] = r_up, l_up
        cols["range_down_w"][rows], cols["linear_down_w"][rows] = r_dn, l_dn
        cols["service_up"][rows], cols["service_down"][rows] = ok_up, ok_dn
        service = ok_up & ok_dn
        cols["service"][rows] = service
        cols["rise_s"][rows], cols["settling_s"][rows] = f_all.rise_s, f_all.settling_s
        cols["overshoot_pct"][rows], cols["disk_margin"][rows] = (f_all.overshoot_pct,
                                                                 f_all.disk_margin)
        cols["feasible"][rows] = f_all.feasible
        cols["tuned_on_demand"][rows] = f_all.tuned or f_up.tuned or f_down.tuned
        cols["settling_up_s"][rows], cols["settling_down_s"][rows] = (f_up.settling_s,
                                                                     f_down.settling_s)
        cols["rise_up_s"][rows], cols["overshoot_up_pct"][rows] = (f_up.rise_s,
                                                                 f_up.overshoot_pct)
        for d in np.flatnonzero(mask_all):
            without = [m.copy() for m in (mask_all, mask_up, mask_down)]
            for m in without:
                m[d] = False
            g_all, g_up, g_down = (entries(m) for m in without)
            r_up2, l_up2, ok_up2 = direction(hu, without[1], g_up, s_w, s_s)
            r_dn2, l_dn2, ok_dn2 = direction(hd, without[2], g_down, s_w, s_s)
            c = contribution
            c["range_up_lost_w"][d] += (r_up - r_up2).sum()
            c["range_down_lost_w"][d] += (r_dn - r_dn2).sum()
            c["linear_up_lost_w"][d] += (l_up - l_up2).sum()
            c["linear_down_lost_w"][d] += (l_dn - l_dn2).sum()
            c["service_lost"][d] += (service & ~(ok_up2 & ok_dn2)).sum()
            slower = _added(g_all.settling_s, f_all.settling_s)
            c["settling_added_s"][d] += slower * rows.size
            c["intervals_available"][d] += rows.size
    return cols, contribution


def _added(without: float, with_: float) -> float:
    """Settling time added by losing a DER, s (0 where either is not a number)."""
    if without == without and with_ == with_:
        return without - with_
    return 0.0
