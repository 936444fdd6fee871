"""All figures of merit of the reference loop for M candidate PI pairs at once.

:func:`evaluate` is the one entry point used by tuning, analyses and the CLI: certified
stability, disk margin, classical margins (optional) and step info, vectorised over candidates
and processed in memory-bounded chunks.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from adnmesh.loopmodel.frequency_response import as_candidates, loop_response
from adnmesh.loopmodel.frequency_kernels import grid_pass
from adnmesh.loopmodel.margins import ClassicalMargins, DiskMargin, classical_margins, disk_margin_at
from adnmesh.loopmodel.plant import Plant
from adnmesh.loopmodel.stability import NyquistData, certified_omega, interval_bounds, winding_verdict
from adnmesh.loopmodel.step_response import StepInfo, step_info

__all__ = ["LoopFigures", "evaluate", "disk_margin_bound", "CHUNK"]

#: candidates per frequency-domain chunk (bounds memory to ~100 MB)
CHUNK = 2048


@dataclass(frozen=True)
class LoopFigures:
    """Figures of merit per candidate (arrays of shape (M,)). NaN where not applicable.

    Attributes
    ----------
    stable : ndarray of bool
    certified : ndarray of bool
        Stability verdict certified (see :mod:`adnmesh.loopmodel.stability`).
    unstable_poles : ndarray of int
    disk_margin : ndarray
        alpha, 0 if unstable.
    disk_omega : ndarray
        Critical frequency of the disk margin, rad/s.
    disk_gain_margin : ndarray, shape (M, 2)
        Absolute.
    disk_phase_margin_deg : ndarray
    gain_margin, phase_margin_deg, delay_margin_s : ndarray
        Classical margins (NaN unless requested).
    gain_margin_omega, phase_margin_omega : ndarray
        rad/s.
    overshoot_pct, rise_time_s, settling_time_s, settling_time_2pct_s, peak, peak_time_s : ndarray
        Step info of ``G_CL`` (NaN unless requested or where unstable).
    """

    stable: np.ndarray
    certified: np.ndarray
    unstable_poles: np.ndarray
    disk_margin: np.ndarray
    disk_omega: np.ndarray
    disk_gain_margin: np.ndarray
    disk_phase_margin_deg: np.ndarray
    gain_margin: np.ndarray
    gain_margin_omega: np.ndarray
    phase_margin_deg: np.ndarray
    phase_margin_omega: np.ndarray
    delay_margin_s: np.ndarray
    overshoot_pct: np.ndarray
    rise_time_s: np.ndarray
    settling_time_s: np.ndarray
    settling_time_2pct_s: np.ndarray
    peak: np.ndarray
    peak_time_s: np.ndarray

    def row(self, i: int) -> dict:
        """Figures of candidate ``i`` as plain Python values (None for not-applicable)."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)[i]
            if isinstance(v, np.ndarray):
                out[f.name] = [None if not np.isfinite(x) else float(x) for x in v]
            elif isinstance(v, (np.bool_, bool)):
                out[f.name] = bool(v)
            elif isinstance(v, (np.integer,)):
                out[f.name] = int(v)
            else:
                out[f.name] = float(v) if np.isfinite(v) else None
        return out


def disk_margin_bound(plant: Plant, kp, ki, per_decade: int = 100) -> np.ndarray:
    """Upper bound of the disk margin alpha per candidate, shape (M,); cheap.

    ``2 / max |1 - L| / |1 + L|`` sampled on :func:`~adnmesh.loopmodel.stability.certified_grid` (never
    below the disk margin: the peak of ``2 |S - 1/2|`` is at least its sampled maximum), without
    certification or refinement (in chunks of :data:`CHUNK` candidates): a candidate whose
    bound is below a limit violates that disk-margin constraint, stable or not (an unstable
    loop's disk margin is 0). Any grid gives a bound; with the default ``per_decade`` (the
    certified grid's) it is the kind :func:`evaluate`'s ``screen`` uses (the same values
    for the same batch and chunking), a coarser one is cheaper and looser.
    """
    kp, ki, gains = as_candidates(plant, kp, ki)
    out = np.empty(kp.size)
    for start in range(0, kp.size, CHUNK):
        sl = slice(start, min(kp.size, start + CHUNK))
        sub = plant.with_gains(gains[sl])
        out[sl] = 2.0 / _grid_pass(sub, kp[sl], ki[sl], np.inf, per_decade)[1][0]
    return out


def _grid_pass(plant: Plant, kp, ki, screen_min: float, per_decade: int = 100):
    """The certified grid (rad/s) and :func:`adnmesh.loopmodel.frequency_kernels.grid_pass` on it (the
    winding only for candidates whose sampled disk margin reaches ``screen_min``)."""
    kp, ki, gains = as_candidates(plant, kp, ki)
    omega = certified_omega(plant, kp, ki, per_decade)
    resp = np.ascontiguousarray(plant.group_responses(omega))
    winding_too = screen_min != np.inf
    if winding_too:
        rho, drho = interval_bounds(plant, omega)
    else:
        rho = drho = np.zeros((len(plant.actuators), 0))
    out = grid_pass(np.ascontiguousarray(kp, dtype=float), np.ascontiguousarray(ki, dtype=float),
                    np.ascontiguousarray(gains, dtype=float), resp, omega, float(screen_min),
                    rho, drho, winding_too)
    return omega, out


def _frequency_part(plant: Plant, kp, ki, classical: bool, screen_min: float | None = None):
    """Nyquist verdict, disk margin and (optionally) classical margins of candidates.

    With ``screen_min``, candidates whose disk margin sampled on the certified grid is below
    it are neither certified nor refined: the sampled ``2 |S - 1/2|`` is never above its
    refined peak, so their disk margin is below ``screen_min`` whatever their stability.
    They are reported not stable with the sampled value (an upper bound) as disk margin.
    The verdicts and disk margins come from one compiled pass over the grid
    (:func:`_screened_part`); ``L`` on the grid is built only for the classical margins.
    """
    nyq, dm, _ = _screened_part(plant, kp, ki, -np.inf if screen_min is None else screen_min)
    if not classical:
        return nyq, dm, None
    kp, ki, gains = as_candidates(plant, kp, ki)
    loop = loop_response(plant.with_gains(gains), kp, ki,
                         nyq.omega)
    nyq = NyquistData(nyq.omega, loop, nyq.stable, nyq.unstable_poles, nyq.certified)
    return nyq, dm, classical_margins(plant, kp, ki, nyq)


def _screened_part(plant: Plant, kp, ki, screen_min: float):
    """:func:`_frequency_part` without classical margins (``screen_min`` -inf: every
    candidate certified), from one compiled pass over the certified grid
    (:func:`_grid_pass`): the verdicts and disk margins of
    :func:`~adnmesh.loopmodel.stability.nyquist_stability` and :func:`~adnmesh.loopmodel.margins.disk_margin`
    to rounding (``tests/test_freq_kernels.py``). Its :class:`NyquistData` has no ``loop``
    (None)."""
    kp, ki, gains = as_candidates(plant, kp, ki)
    omega, (q_peak, q_prev, q_next, k_peak, keep, winding, bad) = _grid_pass(
        plant, kp, ki, screen_min)
    upper = 2.0 / q_peak
    m = kp.size
    stable, certified = np.zeros(m, bool), np.zeros(m, bool)
    poles = np.full(m, -1)
    alpha, w_disk = upper.copy(), np.full(m, np.nan)
    if keep.any():
        sub = plant.with_gains(gains[keep])
        st, po, ce = winding_verdict(sub, kp[keep], ki[keep], gains[keep], omega,
                                     winding[keep], bad[keep])
        stable[keep], poles[keep], certified[keep] = st, po, ce
        d = disk_margin_at(sub, kp[keep], ki[keep], omega, k_peak[keep], q_prev[keep],
                           q_peak[keep], q_next[keep], st)
        alpha[keep], w_disk[keep] = d.alpha, d.omega
    return (NyquistData(omega, None, stable, poles, certified), DiskMargin(alpha, w_disk),
            None)


def evaluate(plant: Plant, kp, ki, *, band_pct: float = 5.0, classical: bool = True,
             time_domain: bool = True, time_mask=None,
             overshoot_stop_pct: float | None = None,
             disk_margin_min: float | None = None,
             t_max_s: float = 20000.0, screen: bool = False) -> LoopFigures:
    """Evaluate the loop for M candidates.

    Parameters
    ----------
    plant : Plant
        Gains of shape (G,) (one plant) or (M, G) (one plant per candidate).
    kp, ki : float or array_like, shape (M,)
        PI gains, 1/W and 1/(W s), > 0.
    band_pct : float
        Settling band for ``settling_time_s``, percent.
    classical : bool
        Compute gain, phase and delay margins at all crossovers.
    time_domain : bool
        Compute step info (for the stable candidates in ``time_mask``).
    time_mask : array_like of bool, optional
        Restrict the (costly) step responses to these candidates, e.g. those meeting the
        disk-margin constraint.
    overshoot_stop_pct : float, optional
        Stop a candidate's simulation once its overshoot exceeds this (percent): enough to
        know it violates an overshoot constraint (its overshoot is then a lower bound).
    disk_margin_min : float, optional
        Simulate only candidates whose disk margin reaches this (the others already violate
        a disk-margin constraint).
    t_max_s : float
        Longest simulated step response, s; a response not settled by then has infinite
        settling times (and NaN rise time if it has not reached 90 %).
    screen : bool
        With ``disk_margin_min``: candidates whose disk margin sampled on the certified grid
        is already below it are not certified or refined (a constraint check needs no more);
        they are reported not stable, not certified, with that sampled value (an upper bound
        of their disk margin) as ``disk_margin``.
    """
    kp, ki, gains = as_candidates(plant, kp, ki)
    m = kp.size
    nan = lambda: np.full(m, np.nan)  # noqa: E731
    stable = np.zeros(m, bool)
    certified = np.zeros(m, bool)
    poles = np.zeros(m, int)
    alpha, w_disk = np.zeros(m), nan()
    gm, gmw, pm, pmw, dmar = nan(), nan(), nan(), nan(), nan()
    for start in range(0, m, CHUNK):
        sl = slice(start, min(m, start + CHUNK))
        sub = plant.with_gains(gains[sl])
        nyq, dm, cm = _frequency_part(sub, kp[sl], ki[sl], classical,
                                      disk_margin_min if screen else None)
        stable[sl], certified[sl], poles[sl] = nyq.stable, nyq.certified, nyq.unstable_poles
        alpha[sl], w_disk[sl] = dm.alpha, dm.omega
        if cm is not None:
            gm[sl], gmw[sl], pm[sl] = cm.gain_margin, cm.gain_margin_omega, cm.phase_margin_deg
            pmw[sl], dmar[sl] = cm.phase_margin_omega, cm.delay_margin_s
    dmo = DiskMargin(alpha, w_disk)
    for arr in (gm, gmw, pm, pmw, dmar):
        arr[~stable] = np.nan
    if time_domain:
        mask = stable if time_mask is None else stable & np.asarray(time_mask, bool)
        if disk_margin_min is not None:
            mask = mask & (alpha >= disk_margin_min)
        info = step_info(plant.with_gains(gains), kp, ki,
                         band_pct=band_pct, bandwidth_rad_s=w_disk, mask=mask,
                         overshoot_stop_pct=overshoot_stop_pct, t_max_s=t_max_s)
    else:
        info = StepInfo(*(nan() for _ in range(6)), np.nan, nan())
    return LoopFigures(stable, certified, poles, alpha, w_disk, dmo.gain_margin,
                       dmo.phase_margin_deg, gm, gmw, pm, pmw, dmar, info.overshoot_pct,
                       info.rise_time_s, info.settling_time_s, info.settling_time_2pct_s,
                       info.peak, info.peak_time_s)
