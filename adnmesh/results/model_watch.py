"""The CPFC's model watch (``runtime.model_watch``, docs/method.md#model-watch): each step of
P_ref against what its table entry was certified for, as the run goes, and the data to fit
the DERs' dynamics to a step that was not.

It takes the messages the CPFC handles (``p_ip``, ``si``, ``heartbeat``) and sends (``p_ref``;
``p_y`` with a switch record or design figures) and finds the steps over their design by the
rule of ``adnmesh up``'s summary (:class:`~adnmesh.results.design_watch.OverDesignWatch`: the
entry's overshoot limit, its rise and settling time plus a tolerance), once a step's window has
closed or, at the latest, :data:`JUDGED_AFTER_SETTLINGS` of its entry's design settling
times after the step (so that a retuned entry can serve the next step); and the recoveries
after gain switches slower than the new entry predicts (:meth:`ModelWatch.observe`). For a
fit (``retune``) it also keeps the set-points the CPFC commanded, summed per DER type, at the
instant they reach the DERs (``t_com_s`` after the command); like the P_IP samples, only as
far back as a step still open needs them. A state machine without a network, times in ns of
sim time, powers in W.
"""
from __future__ import annotations

from array import array
from dataclasses import dataclass

import numpy as np

from adnmesh.results.design_check import FIGURE_TOLERANCE, ders_shown, entry_at
from adnmesh.results.design_watch import GRACE_NS, OverDesign, OverDesignWatch

__all__ = ["JUDGED_AFTER_SETTLINGS", "ModelWatch", "SlowRecovery", "StepData"]

#: a step is judged (and fitted) at the latest this many of its entry's design settling times
#: after it, or when its window ends if that is sooner
JUDGED_AFTER_SETTLINGS = 3


@dataclass(frozen=True)
class SlowRecovery:
    """A gain switch after which P_IP took longer to come back to P_ref than the new entry
    predicts (see :meth:`ModelWatch.observe`): the switch (s of the run), the new entry and
    its DERs, when after the switch the error was largest (s) and how large (W), the time it
    then took to stay within the band (s; None: not within the window), what it may take (s)
    and the window (s)."""

    t_s: float
    entry: int | None
    ders: tuple[str, ...]
    peak_after_s: float
    largest_w: float
    recovered_s: float | None
    limit_s: float
    window_s: float

    @property
    def text(self) -> str:
        took = (f"took {self.recovered_s:.3f} s" if self.recovered_s is not None
                else "was not back by the end of the window")
        return (f"recovery after the gain switch at {self.t_s:g} s to entry {self.entry}"
                f"{ders_shown(self.ders)} SLOWER THAN DESIGNED: P_IP - P_ref, largest "
                f"{self.largest_w / 1e3:+.3f} kW {self.peak_after_s:.3f} s after the switch, "
                f"{took} from there to stay within the band, against {self.limit_s:.3f} s at "
                f"most (the entry's design settling time +{100 * FIGURE_TOLERANCE:g} %, and "
                f"the handover)")


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
        self._band = config.constraints.settling_band_pct / 100.0
        self._switches: list[tuple[int, float]] = []    # (t_ns, handover s) to be judged
        self._due_ns = 0                # the first switch's window cannot close before this
        self._known = (0, 0, 0)         # P_ref values, window ends, entries seen at _due_ns
        self._held = array("q")         # P_IP samples that say the DERs are held, while judging
        self._t_ns = array("q")
        self._setpoints = {t: array("d") for t in self._types}

    def observe(self, message_type: str, body: dict) -> list[OverDesign | SlowRecovery]:
        """The steps over their design and the slow recoveries after gain switches that one
        message (envelope fields and body, plain data) closes.

        **After a gain switch** (not one made because the DERs move the other way, which
        belongs to its step) the new entry predicts how the error the lost DERs leave dies
        out: an output disturbance ``e`` decays as ``e (1 - y(t))``, ``y`` the entry's step
        response, so within its design settling time. The window runs to the next step or
        window-ending event, at most :data:`JUDGED_AFTER_SETTLINGS` design settling times. If
        the largest error in it, ``e``, exceeds the settling band of the last step of P_ref
        (nothing to recover otherwise) and no P_IP sample from then on says the DERs are held
        at their limits (a lack of power, not of speed), the error must stay within
        ``max(band of e, band of that step)`` from ``(1 +``
        :data:`~adnmesh.results.design_check.FIGURE_TOLERANCE` ``)`` design settling times
        plus the switch's handover after that largest error on.
        """
        found = list(self.watch.observe_body(message_type, body))
        if message_type == "p_y" and isinstance(body.get("switch"), dict) \
                and not body["switch"].get("direction"):
            self._switches.append((body["t_send_ns"], float(body["switch"].get("handover_s", 0))))
            self.watch.keep_from_ns = self._switches[0][0]
            self._due_ns = 0
        if message_type == "p_ip":
            if body.get("held") and self._switches:
                self._held.append(body["t_send_ns"])
            found += self._recoveries()
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

    def _recoveries(self) -> list[SlowRecovery]:
        """Judge the gain switches whose window has closed (see :meth:`observe`)."""
        if not self._switches:
            return []
        series = self.watch.series
        now = series.p_ip_t_ns[-1]
        known = (len(series.p_ref_t_ns), len(series.windows.instants), len(series.entries))
        if now < self._due_ns and known == self._known:
            return []                   # nothing that could close a window came since
        out = []
        while self._switches:
            t_sw, handover_s = self._switches[0]
            announced = entry_at(series.entries, t_sw)
            design = None if announced is None else announced.get("design")
            ends = [t for t in (*series.step_times_ns(), *series.windows.instants) if t > t_sw]
            if design:
                ends.append(t_sw + int(JUDGED_AFTER_SETTLINGS
                                       * float(design["settling_time_s"]) * 1e9))
            end = min(ends) if ends else None
            if end is None or now < end + GRACE_NS:
                self._due_ns = 2**63 if end is None else end + GRACE_NS
                self._known = known
                break
            self._switches.pop(0)
            if design:
                found = self._recovery(t_sw, end, announced, float(design["settling_time_s"]),
                                       handover_s)
                if found is not None:
                    out.append(found)
        self.watch.keep_from_ns = self._switches[0][0] if self._switches else None
        if not self._switches:
            self._held = array("q")
        return out

    def _recovery(self, t_sw: int, end: int, announced: dict, settling_s: float,
                  handover_s: float) -> SlowRecovery | None:
        series = self.watch.series
        t = np.array(series.p_ip_t_ns, dtype=np.int64)
        inside = (t >= t_sw) & (t < end)
        if inside.sum() < 2:
            return None
        t, y = t[inside], np.array(series.p_ip_w, dtype=float)[inside]
        ref_t = np.array(series.p_ref_t_ns, dtype=np.int64)
        ref = np.array(series.p_ref_w, dtype=float)
        steps = [k for k in series.step_records() if ref_t[k] <= t_sw]
        if not steps:
            return None                  # no step yet: no band to measure against
        at = steps[-1]
        # P_ref at each sample (an offset from a level above moves it between steps)
        error = y - ref[np.searchsorted(ref_t, t, side="right") - 1]
        peak = int(np.argmax(np.abs(error)))
        floor = self._band * abs(ref[at] - ref[at - 1])
        held = np.array(self._held, dtype=np.int64)
        if abs(error[peak]) <= floor or np.any((held >= t[peak]) & (held < end)):
            return None        # nothing to recover, or the DERs at their limits: no dynamics
        band = max(self._band * abs(error[peak]), floor)
        outside = np.flatnonzero(np.abs(error) > band)
        window_s = (end - t_sw) * 1e-9
        limit_s = (1 + FIGURE_TOLERANCE) * settling_s + handover_s
        settled = outside[-1] + 1 < len(t)
        recovered = (t[outside[-1] + 1] - t[peak]) * 1e-9 if settled else None
        if (recovered is not None and recovered <= limit_s) or (
                recovered is None and (end - t[peak]) * 1e-9 <= limit_s):
            return None
        return SlowRecovery(t_sw * 1e-9, announced.get("entry"), tuple(announced.get("ders", ())),
                            (t[peak] - t_sw) * 1e-9, float(error[peak]), recovered, limit_s,
                            window_s)

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
