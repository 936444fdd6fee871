"""How a run went through its faults: detection, deviation and recovery, per fault.

For every injected fault (its window ``[start, end)``, from the run's ``fault`` messages) and the
run's events (what agents noticed, :mod:`adnmesh.wire.messages`):

- **detected**: the first event of an agent that reacted to a fault — a DER's watchdog
  fallback, the availability monitor marking a DER unavailable, the CPFC holding or finding SI
  stale, the measurement taking a silent DER at its schedule — at or after
  the start and before the end (a fault nobody noticed while it lasted is "not detected"); by
  whom and how long after the start;
- **largest deviation during** and **after**: ``max |P_IP - P_ref|`` over the P_IP samples in
  the window, and from the end until the next fault starts, the next scenario event (a step of
  P_ref, a change of availability: ``events_s``) or 60 s have passed (or the run ends), W;
- **recovery time**: from the end until ``|P_IP - P_ref|`` stays within ``band_w`` (interpolated
  like a settling time), s; 0 if it never leaves the band after the end, None if it is outside
  at the end of the after window.

Pure functions of arrays; used by ``adnmesh up``'s summary and by ``adnmesh inspect``, so both
give the same figures.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from adnmesh.names import der_agent_id

__all__ = ["DETECTION_KINDS", "FaultFigures", "fault_figures"]

DETECTION_KINDS = frozenset({"watchdog_fallback", "unavailable", "hold", "der_silent",
                             "si_stale"})
"""Event kinds that show an agent reacting to a fault."""

AFTER_WINDOW_S = 60.0
"""Longest look after a fault's end, s."""


@dataclass(frozen=True)
class FaultFigures:
    """One fault and what it did (times in s of sim time, powers in W)."""

    fault_id: int
    kind: str
    target: str
    start_s: float
    end_s: float | None
    detected_s: float | None
    detected_by: str | None
    detection_delay_s: float | None
    max_deviation_during_w: float | None
    max_deviation_after_w: float | None
    recovery_time_s: float | None


def _deviation(t_ip: np.ndarray, dev: np.ndarray, lo: float, hi: float) -> float | None:
    inside = (t_ip >= lo) & (t_ip < hi)
    return float(np.max(dev[inside])) if inside.any() else None


def _recovery(t_ip: np.ndarray, dev: np.ndarray, lo: float, hi: float,
              band_w: float) -> float | None:
    inside = (t_ip >= lo) & (t_ip < hi)
    t, d = t_ip[inside], dev[inside]
    if t.size == 0:
        return None
    out = np.flatnonzero(d > band_w)
    if out.size == 0:
        return 0.0
    i = int(out[-1])
    if i == t.size - 1:
        return None
    crossing = t[i] + (t[i + 1] - t[i]) * (d[i] - band_w) / (d[i] - d[i + 1])
    return float(crossing - lo)


def _first_reaction(reactions, start: float, stop: float, fault: dict):
    """``(t, who)`` of the first reaction in ``[start, stop)``; at equal times the fault's own
    DER's, else the first sender by name."""
    inside = [(t, who) for t, who, _ in reactions if start <= t < stop]
    if not inside:
        return None
    first = min(t for t, _ in inside)
    at_first = [who for t, who in inside if t == first]
    own = der_agent_id(str(fault.get('der')))
    return first, own if own in at_first else min(at_first)


def fault_figures(faults: Sequence[dict], events: Sequence[tuple[float, str, str]],
                  t_ip_s: Sequence[float], p_ip_w: Sequence[float],
                  p_ref_t_s: Sequence[float], p_ref_w: Sequence[float], *, end_s: float,
                  band_w: float, events_s: Sequence[float] = ()) -> list[FaultFigures]:
    """The figures of every fault (see the module docstring).

    Parameters
    ----------
    faults : sequence of dict
        ``fault`` message bodies (``fault_id``, ``kind``, ``start_ns``, ``end_ns``, target).
    events : sequence of (t_s, sender, kind)
        The run's events.
    t_ip_s, p_ip_w : sequence of float
        P_IP samples: sampling time, s, and value, W.
    p_ref_t_s, p_ref_w : sequence of float
        When P_ref took each value, s, and the value, W.
    end_s : float
        End of the run, s.
    band_w : float
        Recovery band, W.
    events_s : sequence of float
        Instants of the scenario's own events (they end a fault's after window), s.
    """
    t_ip = np.asarray(t_ip_s, dtype=float)
    p_ip = np.asarray(p_ip_w, dtype=float)
    ref_t, ref_v = np.asarray(p_ref_t_s, dtype=float), np.asarray(p_ref_w, dtype=float)
    if ref_v.size == 0:               # no P_ref recorded (a cut recording): no deviation
        ref_t, ref_v = np.zeros(1), np.full(1, np.nan)
    idx = np.searchsorted(ref_t, t_ip, side="right") - 1
    dev = np.where(idx >= 0, np.abs(p_ip - ref_v[np.maximum(idx, 0)]), 0.0)
    starts = sorted({f["start_ns"] * 1e-9 for f in faults})
    reactions = sorted(e for e in events if e[2] in DETECTION_KINDS)
    out = []
    for f in sorted(faults, key=lambda f: (f["start_ns"], f["fault_id"])):
        start = f["start_ns"] * 1e-9
        end = None if f.get("end_ns") is None else f["end_ns"] * 1e-9
        stop = end_s if end is None else end
        seen = _first_reaction(reactions, start, stop, f)
        later = [s for s in (*starts, *events_s) if s > start and (end is None or s > end)]
        after_hi = min([end_s, *later, *([] if end is None else [end + AFTER_WINDOW_S])])
        target = next((str(f[k]) for k in ("link", "der", "agent") if f.get(k)), "all ICT")
        out.append(FaultFigures(
            f["fault_id"], f["kind"], target, start, end,
            None if seen is None else seen[0], None if seen is None else seen[1],
            None if seen is None else seen[0] - start,
            _deviation(t_ip, dev, start, stop),
            None if end is None else _deviation(t_ip, dev, end, after_hi),
            None if end is None else _recovery(t_ip, dev, end, after_hi, band_w)))
    return out
