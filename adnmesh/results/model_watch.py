"""The CPFC's model watch (``runtime.model_watch``, docs/method.md#model-watch): each step of
P_ref against what its table entry was certified for, as the run goes, and the data to fit
the DERs' dynamics to a step that was not.

It takes the messages the CPFC handles (``p_ip``, ``si``, ``heartbeat``) and sends (``p_ref``;
``p_y`` with a switch record or design figures) and finds the steps over their design by the
rule of ``adnmesh up``'s summary (:class:`~adnmesh.results.design_watch.OverDesignWatch`: the
entry's overshoot limit, its rise and settling time plus a tolerance), once a step's window has
closed or, at the latest, :data:`JUDGED_AFTER_SETTLINGS` of its entry's design settling
times after the step (so that a retuned entry can serve the next step). For a fit (``retune``) it also keeps the set-points the CPFC commanded, summed per DER
type, at the instant they reach the DERs (``t_com_s`` after the command); like the P_IP
samples, only as far back as a step still open needs them. A state machine without a
network, times in ns of sim time, powers in W.
"""
from __future__ import annotations

from array import array
from dataclasses import dataclass

import numpy as np

from adnmesh.results.design_watch import GRACE_NS, OverDesign, OverDesignWatch

__all__ = ["JUDGED_AFTER_SETTLINGS", "ModelWatch", "StepData"]

#: a step is judged (and fitted) at the latest this many of its entry's design settling times
#: after it, or when its window ends if that is sooner
JUDGED_AFTER_SETTLINGS = 3


@dataclass(frozen=True)
class StepData:
    """A step's window on a uniform grid: ``period_s``, P_IP (W) and per DER type the summed
    set-points of the entry's DERs (W), from the last P_IP sample before the step on."""

    period_s: float
    p_ip_w: np.ndarray
    setpoints_w: dict[str, np.ndarray]


class ModelWatch:
    """Finds the steps over their design and keeps what a fit needs.

    Parameters
    ----------
    config : Config
    keep_setpoints : bool
        Keep the commanded set-points (for a fit, ``retune``).
    """

    def __init__(self, config, keep_setpoints: bool) -> None:
        self.watch = OverDesignWatch(config.constraints.settling_band_pct,
                                     early_settlings=JUDGED_AFTER_SETTLINGS)
        self._type_of = {d.id: d.type for d in config.ders}
        self._types = tuple(dict.fromkeys(self._type_of.values()))
        self._t_com_ns = int(round(config.t_com_s * 1e9))
        self._keep = keep_setpoints
        self._t_ns = array("q")
        self._setpoints = {t: array("d") for t in self._types}

    def observe(self, message_type: str, body: dict) -> list[OverDesign]:
        """The steps over their design that one message (envelope fields and body, plain
        data) closes."""
        found = self.watch.observe_body(message_type, body)
        if message_type == "p_ip":
            self._forget()
        return found

    def commanded(self, t_ns: int, setpoints_w: dict[str, float]) -> None:
        """The set-points (DER id -> W) of the DERs the CPFC commands, sent at ``t_ns``."""
        if not self._keep:
            return
        sums = dict.fromkeys(self._types, 0.0)
        for der, value in setpoints_w.items():
            sums[self._type_of[der]] += value
        self._t_ns.append(t_ns + self._t_com_ns)
        for t, value in sums.items():
            self._setpoints[t].append(value)

    def step_data(self, found: OverDesign) -> StepData:
        """The window of step ``found`` (see :class:`StepData`); ValueError if too little of
        it is kept (fewer than 10 samples)."""
        series = self.watch.series
        # copies: the watch's arrays grow on while a fit (in a realtime run's thread) runs
        t = np.array(series.p_ip_t_ns, dtype=np.int64)
        y = np.array(series.p_ip_w, dtype=float)
        start = int(round(found.check.t_s * 1e9))
        end = found.closed_ns
        first = max(int(np.searchsorted(t, start, side="left")) - 1, 0)
        last = int(np.searchsorted(t, end, side="left"))
        if last - first < 10 or not len(self._t_ns):
            raise ValueError("fewer than 10 samples of the step are kept")
        grid = t[first:last]
        period_s = float(np.median(np.diff(grid))) * 1e-9
        sent = np.array(self._t_ns, dtype=np.int64)
        at = np.clip(np.searchsorted(sent, grid, side="right") - 1, 0, len(sent) - 1)
        setpoints = {ty: np.array(v, dtype=float)[at] for ty, v in self._setpoints.items()}
        moving = {ty: v for ty, v in setpoints.items() if np.ptp(v) > 0}
        return StepData(period_s, y[first:last], moving)

    def _forget(self) -> None:
        """Drop the set-points before the oldest P_IP sample the watch still holds (less a
        grace), every time they outnumber it twice."""
        held = self.watch.series.p_ip_t_ns
        if not self._keep or len(self._t_ns) < 2 * len(held) + 1000 or not held:
            return
        sent = np.asarray(self._t_ns, dtype=np.int64)
        cut = max(int(np.searchsorted(sent, held[0] - GRACE_NS, side="right")) - 1, 0)
        self._t_ns = array("q", sent[cut:].tobytes())
        for t, values in self._setpoints.items():
            self._setpoints[t] = array("d", np.asarray(values)[cut:].tobytes())
