"""Summary figures of a recorded run: how P_IP followed each step of P_ref.

For every step of P_ref (a change of its value) the response of the measured P_IP is judged
in the window up to the next step (or the end of the recording), relative to the P_IP sampled
last before the step (``y0``) and the new reference (``target``):

- rise time: from 10 % to 90 % of ``target - y0``, s (None if 90 % is never reached),
- settling time: from the step until P_IP stays within ``band_pct`` % of ``|target - y0|``
  around the target, s (None if it is outside at the end of the window),
- overshoot: the largest excursion beyond the target, % of ``|target - y0|`` (0 if none).

Times are P_IP's send (sampling) times. These are the same conventions as the reference model's
step information (SPEC §2), applied to the recorded signals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from adnmesh.recording.series import RunData

__all__ = ["RunFigures", "StepFigures", "run_figures"]


@dataclass(frozen=True)
class StepFigures:
    """P_IP's response to one step of P_ref (times in s on the sim_time axis, powers in W)."""

    t_s: float
    delta_w: float
    target_w: float
    rise_time_s: float | None
    settling_time_s: float | None
    overshoot_pct: float
    window_s: float


@dataclass(frozen=True)
class RunFigures:
    """Summary of a run: step responses, tracking error and event counts.

    ``availability_changes`` does not count the initial state; ``faults`` counts fault events
    (a start and an end are two); ``mode_changes`` counts DER mode changes (e.g. to watchdog).

    ``rms_error_w`` and ``max_error_w`` are over every P_IP sample, against the P_ref in force
    at its send time (None without both series).
    """

    steps: tuple[StepFigures, ...]
    rms_error_w: float | None
    max_error_w: float | None
    gain_switches: int
    availability_changes: int
    faults: int
    mode_changes: int


def _step_figures(t_s: np.ndarray, y: np.ndarray, t_step: float, t_end: float, target: float,
                  band_pct: float) -> StepFigures | None:
    before = np.flatnonzero(t_s <= t_step)
    inside = (t_s > t_step) & (t_s <= t_end)
    if before.size == 0 or not inside.any():
        return None
    y0 = y[before[-1]]
    delta = target - y0
    ts, ys = t_s[inside], y[inside]
    if delta == 0:
        return StepFigures(t_step, 0.0, target, None, None, 0.0, t_end - t_step)
    fraction = (ys - y0) / delta
    t10 = ts[np.argmax(fraction >= 0.1)] if (fraction >= 0.1).any() else None
    t90 = ts[np.argmax(fraction >= 0.9)] if (fraction >= 0.9).any() else None
    rise = float(t90 - t10) if t10 is not None and t90 is not None else None
    outside = np.abs(ys - target) > band_pct / 100 * abs(delta)
    if outside[-1]:
        settling = None
    else:
        last_out = np.flatnonzero(outside)
        settling = float(ts[last_out[-1] + 1] - t_step) if last_out.size else float(ts[0] - t_step)
    overshoot = max(0.0, float(np.max(fraction) - 1.0) * 100.0)
    return StepFigures(float(t_step), float(delta), float(target), rise, settling, overshoot,
                       float(t_end - t_step))


def run_figures(run: RunData, *, band_pct: float = 5.0) -> RunFigures:
    """Compute the :class:`RunFigures` of ``run`` (settling band ``band_pct`` %)."""
    p_ref, p_ip = run.one("p_ref"), run.one("p_ip")
    steps: list[StepFigures] = []
    rms = worst = None
    if p_ref is not None and p_ip is not None and p_ip.values.size:
        t_ip, y = np.asarray(run.seconds(p_ip.t_ns)), p_ip.values
        t_ref = np.asarray(run.seconds(p_ref.t_ns))
        change = np.flatnonzero(np.diff(p_ref.values) != 0) + 1
        step_times = [float(t_ref[i]) for i in change] + [float(t_ip[-1])]
        for j, i in enumerate(change):
            found = _step_figures(t_ip, y, step_times[j], step_times[j + 1],
                                  float(p_ref.values[i]), band_pct)
            if found is not None:
                steps.append(found)
        index = np.searchsorted(t_ref, t_ip, side="right") - 1
        valid = index >= 0
        if valid.any():
            error = y[valid] - p_ref.values[index[valid]]
            rms, worst = float(np.sqrt(np.mean(error**2))), float(np.max(np.abs(error)))
    kinds = [e.kind for e in run.events]
    return RunFigures(steps=tuple(steps), rms_error_w=rms, max_error_w=worst,
                      gain_switches=kinds.count("gain_switch"),
                      availability_changes=max(0, kinds.count("availability") - 1),
                      faults=kinds.count("fault"), mode_changes=kinds.count("der_mode"))
