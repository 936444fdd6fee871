"""The grid guard: which DERs may not move which way, because a limit is at hand
(docs/method.md#grid-guard), as a bus-free state machine the measurement runs.

Every sample the guard looks at every reported bus voltage and every line and transformer
loading of the power flow (:class:`GuardValues`). A quantity **engages** when it comes within
the config's margin of its limit (``v_max_pu - v_margin_pu``, ``v_min_pu + v_margin_pu``,
``loading_max_pct - loading_margin_pct``) and is **released** once it has stayed inside its
release level (the engaging level moved inwards by ``v_release_pu`` / ``loading_release_pct``)
for ``release_s``: hysteresis in value and in time, so that a quantity hovering at the margin
does not toggle the control. Nor is it released while the loop presses the way it blocks
(every DER still in use held at its limit that way): the blocked DERs would be asked at once
to move that way again.

For an engaged quantity x with a bad direction σ (+1 for a voltage at its upper limit and for a
loading, −1 for a voltage at its lower limit) and the sensitivities ``s_d = ∂x/∂P_d`` of the
DERs (and ``∂x/∂Q_d``; :func:`adnmesh.grid.sensitivity.limit_sensitivities`), DER d is
**blocked up** in P when raising its P worsens x by at least ``share`` of the most sensitive
DER's effect, ``σ s_d ≥ share · max_e |s_e|``, and **blocked down** when lowering it does,
``−σ s_d ≥ share · max_e |s_e|``; the same for Q. The sensitivities are taken when a quantity
engages and refreshed every ``refresh_s`` while any is engaged; a DER once blocked for an
engaged quantity stays blocked until the quantity is released. The CPFC leaves a DER blocked in
the direction its DERs move out of the entry it uses (:mod:`adnmesh.control.cpfc_controller`).

In mode ``block`` no DER is blocked; instead ``hold`` is set while any quantity is beyond its
limit itself, released with the same hysteresis: the whole control waits, the practice of
letting the tap changer restore the band. In mode ``off`` the guard only watches.

Whatever the mode the guard keeps **episodes of violation** (any quantity beyond its limit):
their start, end, and worst excess with where it was, as events.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["DIRECTIONS", "GridGuard", "GuardValues", "Watched"]

#: the four ways a DER can be blocked: (quantity, direction)
DIRECTIONS = (("p", 1), ("p", -1), ("q", 1), ("q", -1))
_FIELDS = {("p", 1): "p_up", ("p", -1): "p_down", ("q", 1): "q_up", ("q", -1): "q_down"}
_WORDS = {("p", 1): "raising P", ("p", -1): "lowering P", ("q", 1): "raising Q",
          ("q", -1): "lowering Q"}


@dataclass(frozen=True)
class GuardValues:
    """The grid at one sample, per element (the power flow's, in the sensitivities' order).

    Attributes
    ----------
    vm_pu : ndarray
        Voltage of every reported bus, p.u.
    line_pct, trafo_pct : ndarray
        Loading of every line and transformer, %.
    bus_names, line_names, trafo_names : sequence of str
        Their names, for events.
    """

    vm_pu: np.ndarray
    line_pct: np.ndarray
    trafo_pct: np.ndarray
    bus_names: Sequence[str]
    line_names: Sequence[str]
    trafo_names: Sequence[str]


@dataclass
class Watched:
    """One engaged quantity: ``kind`` (``v_high``, ``v_low``, ``line``, ``trafo``), its
    element index, and the DERs it blocks per direction (``(quantity, ±1)`` -> set of ids)."""

    kind: str
    index: int
    blocked: dict
    inside_since_ns: int | None = None


class GridGuard:
    """Engages, blocks and releases (see the module docstring).

    Parameters
    ----------
    settings : adnmesh.config.Guard
    limits : adnmesh.config.GridLimits
    der_ids : sequence of str
        The DERs in the sensitivities' column order.
    reactive : bool
        Whether the DERs follow a Q loop (else Q is never blocked).
    """

    def __init__(self, settings, limits, der_ids: Sequence[str], reactive: bool) -> None:
        self.settings, self.limits = settings, limits
        self.der_ids = tuple(der_ids)
        self.reactive = reactive
        self.mode = settings.mode
        self.release_ns = int(round(settings.release_s * 1e9))
        self.refresh_ns = int(round(settings.refresh_s * 1e9))
        self.watched: dict[tuple[str, int], Watched] = {}
        self.hold = False
        self._hold_inside_since: int | None = None
        self._refreshed_ns: int | None = None
        self.violation: dict | None = None      # the episode under way: start, worst, where
        self._version = 0                       # counts the changes of the blocked sets
        self.counts = {"sensitivity_refreshes": 0, "engaged": 0, "violations": 0}
        self.levels = self._levels()

    # -- levels ----------------------------------------------------------------------------

    def _levels(self) -> dict[str, tuple[float, float, float, int]]:
        """kind -> (limit, engaging level, release level, bad direction σ): :attr:`levels`."""
        s, lim = self.settings, self.limits
        return {
            "v_high": (lim.v_max_pu, lim.v_max_pu - s.v_margin_pu,
                       lim.v_max_pu - s.v_margin_pu - s.v_release_pu, 1),
            "v_low": (lim.v_min_pu, lim.v_min_pu + s.v_margin_pu,
                      lim.v_min_pu + s.v_margin_pu + s.v_release_pu, -1),
            "line": (lim.loading_max_pct, lim.loading_max_pct - s.loading_margin_pct,
                     lim.loading_max_pct - s.loading_margin_pct - s.loading_release_pct, 1),
            "trafo": (lim.loading_max_pct, lim.loading_max_pct - s.loading_margin_pct,
                      lim.loading_max_pct - s.loading_margin_pct - s.loading_release_pct, 1),
        }

    @staticmethod
    def _values(values: GuardValues, kind: str) -> np.ndarray:
        return {"v_high": values.vm_pu, "v_low": values.vm_pu, "line": values.line_pct,
                "trafo": values.trafo_pct}[kind]

    @staticmethod
    def _name(values: GuardValues, kind: str, index: int) -> str:
        names = values.bus_names if kind in ("v_high", "v_low") else (
            values.line_names if kind == "line" else values.trafo_names)
        return names[index] if index < len(names) else f"{kind} {index}"

    # -- a sample ----------------------------------------------------------------------------

    def observe(self, t_ns: int, values: GuardValues,
                sensitivities: Callable[[], object],
                pressing: frozenset = frozenset()) -> tuple[bool, list[dict]]:
        """Fold one sample in. ``sensitivities()`` gives the current
        :class:`~adnmesh.grid.sensitivity.LimitSensitivities` (called only when needed);
        ``pressing`` holds the ways (``("p", 1)``, ...) in which every DER the loop still
        uses is held at its limit: a quantity that blocks DERs one of those ways is not
        released (they would be asked at once to move that way and worsen it again).

        Returns ``(changed, events)``: whether the blocked sets or ``hold`` changed, and the
        events to say (dicts with ``level``, ``kind``, ``text``, ``subject``).
        """
        before = (self._version, self.hold)
        worst = self._worst(values)
        events = self._violations(t_ns, values, worst)
        if self.mode == "directional":
            events += self._directional(t_ns, values, sensitivities, pressing)
        elif self.mode == "block":
            events += self._block(t_ns, values, worst)
        return (self._version, self.hold) != before, events

    def _directional(self, t_ns, values, sensitivities, pressing) -> list[dict]:
        levels, events = self.levels, []
        new = []
        for kind, (_, engage, release, sigma) in levels.items():
            x = self._values(values, kind)
            if x.size == 0:
                continue
            beyond = np.flatnonzero(sigma * (x - engage) > 0)
            for i in beyond.tolist():
                key = (kind, i)
                if key not in self.watched:
                    self.watched[key] = Watched(kind, i, {d: set() for d in DIRECTIONS})
                    self.counts["engaged"] += 1
                    new.append(key)
                else:
                    self.watched[key].inside_since_ns = None
            for key, w in list(self.watched.items()):
                if w.kind != kind or key in new:
                    continue
                value = float(x[w.index])
                pressed = any(w.blocked[way] for way in pressing)
                if sigma * (value - release) <= 0 and not pressed:   # inside the release
                    if w.inside_since_ns is None:
                        w.inside_since_ns = t_ns
                    elif t_ns - w.inside_since_ns >= self.release_ns:
                        del self.watched[key]
                        self._version += any(w.blocked.values())
                        released = self._blocked_sets()
                        events += self._release_events(w, released, values)
                else:                    # between release and engage, or pressed
                    w.inside_since_ns = None
        due = (self._refreshed_ns is None
               or t_ns - self._refreshed_ns >= self.refresh_ns)
        if self.watched and (new or due):
            events += self._block_by(sensitivities(), values, t_ns)
        elif not self.watched:
            self._refreshed_ns = None
        return events

    def _block_by(self, sens, values: GuardValues, t_ns: int) -> list[dict]:
        """Add to each engaged quantity's blocked DERs by the sensitivities ``sens``."""
        self._refreshed_ns = t_ns
        self.counts["sensitivity_refreshes"] += 1
        before = self._blocked_sets()
        rows = {"v_high": (sens.dv_dp, sens.dv_dq), "v_low": (sens.dv_dp, sens.dv_dq),
                "line": (sens.dline_dp, sens.dline_dq), "trafo": (sens.dtrafo_dp,
                                                                   sens.dtrafo_dq)}
        share = self.settings.share
        sigmas = {k: v[3] for k, v in self.levels.items()}
        cause: dict[tuple, tuple[str, int]] = {}
        for key, w in self.watched.items():
            sigma = sigmas[w.kind]
            for quantity, matrix in zip(("p", "q"), rows[w.kind]):
                if quantity == "q" and not self.reactive:
                    continue
                s = sigma * np.asarray(matrix[w.index], dtype=float)
                biggest = float(np.max(np.abs(s))) if s.size else 0.0
                if not biggest > 0 or not math.isfinite(biggest):
                    continue
                for d, value in enumerate(s.tolist()):
                    for direction in (1, -1):
                        if direction * value >= share * biggest:
                            w.blocked[(quantity, direction)].add(self.der_ids[d])
                            cause.setdefault((quantity, direction, self.der_ids[d]), key)
        after = self._blocked_sets()
        self._version += after != before
        events = []
        for way in DIRECTIONS:
            added = [d for d in self.der_ids if d in after[way] and d not in before[way]]
            if not added:
                continue
            kind, index = cause[(*way, added[0])]
            x = float(self._values(values, kind)[index])
            events.append({"level": "WARNING", "kind": "guard_block",
                           "subject": _FIELDS[way],
                           "text": f"grid guard: {', '.join(added)} blocked from "
                                   f"{_WORDS[way]}: {self._describe(values, kind, index, x)}"})
        return events

    def _release_events(self, w: Watched, after: dict, values: GuardValues) -> list[dict]:
        events = []
        for way in DIRECTIONS:
            freed = [d for d in self.der_ids if d in w.blocked[way] and d not in after[way]]
            if freed:
                x = float(self._values(values, w.kind)[w.index])
                events.append({"level": "INFO", "kind": "guard_release",
                               "subject": _FIELDS[way],
                               "text": f"grid guard: {', '.join(freed)} free again for "
                                       f"{_WORDS[way]}: "
                                       f"{self._describe(values, w.kind, w.index, x)}"})
        return events

    def _describe(self, values: GuardValues, kind: str, index: int, x: float) -> str:
        limit = self.levels[kind][0]
        name = self._name(values, kind, index)
        if kind in ("v_high", "v_low"):
            return f"{name} at {x:.4f} p.u. (limit {limit:g} p.u.)"
        return f"{kind} {name} at {x:.1f} % (limit {limit:g} %)"

    def _block(self, t_ns: int, values: GuardValues, worst) -> list[dict]:
        """Mode block: hold while anything is beyond its limit (``worst``:
        :meth:`_worst`), released with hysteresis."""
        if worst is not None and worst[0] > 0:
            self._hold_inside_since = None
            if not self.hold:
                self.hold = True
                return [{"level": "WARNING", "kind": "guard_hold", "subject": "grid",
                         "text": "grid guard: control held, "
                                 f"{self._describe(values, worst[1], worst[2], worst[3])}"}]
            return []
        if not self.hold:
            return []
        levels, inside = self.levels, True
        s = self.settings
        for kind, (limit, _, _, sigma) in levels.items():
            x = self._values(values, kind)
            back = s.v_release_pu if kind.startswith("v_") else s.loading_release_pct
            if x.size and np.any(sigma * (x - (limit - sigma * back)) > 0):
                inside = False
        if not inside:
            self._hold_inside_since = None
            return []
        if self._hold_inside_since is None:
            self._hold_inside_since = t_ns
        if t_ns - self._hold_inside_since < self.release_ns:
            return []
        self.hold = False
        self._hold_inside_since = None
        return [{"level": "INFO", "kind": "guard_resume", "subject": "grid",
                 "text": "grid guard: the band is restored, control resumes"}]

    # -- violations ------------------------------------------------------------------------

    def _worst(self, values: GuardValues):
        """(excess beyond the limit in the limit's unit per unit of limit, kind, index,
        value) of the quantity furthest beyond its limit (excess ≤ 0: none is)."""
        best = None
        for kind, (limit, _, _, sigma) in self.levels.items():
            x = self._values(values, kind)
            if x.size == 0:
                continue
            excess = np.nan_to_num(sigma * (x - limit) / abs(limit), nan=-np.inf)
            i = int(np.argmax(excess))
            if best is None or excess[i] > best[0]:
                best = (float(excess[i]), kind, i, float(x[i]))
        return best

    def _violations(self, t_ns: int, values: GuardValues, worst) -> list[dict]:
        beyond = worst is not None and worst[0] > 0
        episode = self.violation
        if beyond:
            where = self._describe(values, worst[1], worst[2], worst[3])
            if episode is None:
                self.counts["violations"] += 1
                self.violation = {"start_ns": t_ns, "excess": worst[0], "where": where}
                return [{"level": "WARNING", "kind": "limit_violated", "subject": "grid",
                         "text": f"grid limit violated: {where}"}]
            if worst[0] > episode["excess"]:
                episode["excess"], episode["where"] = worst[0], where
            return []
        if episode is None:
            return []
        self.violation = None
        seconds = (t_ns - episode["start_ns"]) / 1e9
        return [{"level": "INFO", "kind": "limit_restored", "subject": "grid",
                 "text": f"grid limits kept again after {seconds:g} s; worst: "
                         f"{episode['where']}"}]

    # -- the state ---------------------------------------------------------------------------

    def _blocked_sets(self) -> dict:
        out = {way: set() for way in DIRECTIONS}
        for w in self.watched.values():
            for way, ders in w.blocked.items():
                out[way] |= ders
        return out

    def state(self) -> dict:
        """The body of a ``grid_guard`` message: the blocked DERs per direction (in the
        DERs' order) and ``hold``."""
        sets = self._blocked_sets()
        body = {_FIELDS[way]: [d for d in self.der_ids if d in sets[way]]
                for way in DIRECTIONS}
        body["hold"] = self.hold
        return body
