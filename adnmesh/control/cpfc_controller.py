"""The CPFC: gain-scheduled PI control of ``P_IP`` (docs/method.md#control-structure,
docs/method.md#runtime-behaviour), as a bus-free state machine.

Every ``pi_period_s`` the CPFC samples ``P_ref`` (from the scenario: the initial operating point
plus the steps so far) and the last ``P_IP`` delivered by the measurement, updates its PI
(:class:`~adnmesh.control.pi.SampledPI`) and sends ``P_Y`` to the DERs on ``cpfc/p_y``. When the
set of available DERs changes, it switches at its next sample to the table entry of the new set
without a bump and sends the entry's weights W with that ``P_Y``; it repeats W every ``weights_period_s`` so that a DER that missed them
recovers. Every ``P_Y`` carries the number of the entry in use (``entry``, counted from 0 per run):
a DER applies ``P_Y`` only with the weights of the same entry.

The output is limited to the range where at least one available DER is not saturated (its
setpoint ``P_Y w_d P_inst,d + P_sched,d`` inside ``[0, P_inst,d]``); the PI's anti-windup holds
the integrator beyond it.

**Which DERs are available**: those SI names, less those whose own latest acknowledgement (a
heartbeat, which the CPFC receives too) says they are in their watchdog fallback — so the CPFC
learns a fallback 0.1 s after it happened, before the availability monitor's SI follows.

**A stale SI** (docs/faults.md#what-the-system-does). The monitor repeats SI every
``heartbeat_period_s``. When no SI has arrived for ``heartbeat_timeout_s`` (plus the jitter of
``availability_to_cpfc``) — the monitor is dead, or its link is cut — the CPFC no longer trusts
the SI it has and derives availability from the heartbeats it receives itself, by the monitor's
own rule: a DER is available while its last heartbeat said ``available`` in a mode other than
``watchdog`` and is younger than ``heartbeat_timeout_s``. So the gains follow the DERs that
leave (or come back) while the monitor is gone, with the same switches the monitor's SI would
have caused, one heartbeat link delay earlier. It says so with a ``si_stale`` warning event and
``si_back`` when SI arrives again (SI then rules again). A restarted CPFC that hears no SI while
it waits to resume starts from the heartbeats the same way. The alternative, the table's static
controller on every DER, would keep commanding DERs that have left.

**Bumpless switching** keeps the DERs' total commanded power ``P_Y Σ w_d P_inst,d`` continuous
over the DERs that carry the output: before the switch those of the old entry that are still
available (a DER that left has already stopped following), after it those of the new entry.
So ``P_Y' = P_Y · Σ_before / Σ_after`` (``scale`` in the switch record). When DERs only leave and
the weights stay, the scale is 1 and ``P_Y`` itself is continuous
(docs/method.md#bumpless-switching); when DERs return,
the others hand them their share instead of all of them adding it at once; after a hold without
any DER (nothing carried the output), the held output continues unscaled. A DER whose setpoint
is at a limit counts with what it is commanded, limited. How fast the DERs move to their new
shares is the switch's **handover** time (``handover_s`` in the switch record; 0 when the switch
moves no DER's commanded power, or after a hold without DERs; docs/method.md#returning-ders-
handover): long enough for the slowest DER involved and for the loop to keep P_IP within
``HANDOVER_BOUND`` of the power handed over.

**Directional availability** (docs/method.md#directional-availability): of the available DERs
the CPFC uses those that can move in the direction the DERs move (up or down from their
schedules; a DER at ``p_sched_w: 0`` cannot go down). The direction is decided one sample before
each step of P_ref, from where the DERs' commanded power will be after it; a change of the DERs
in use is a switch then (``direction`` in its record), with the loop at rest.

**The grid guard** (docs/method.md#grid-guard): the measurement's ``grid_guard`` messages name
the DERs blocked per direction near a grid limit. Moving in a direction the CPFC leaves those
blocked that way out of the DERs it uses (a switch at the next sample); they keep the power
they were commanded (``keep`` in the switch record: a cap) and the others go on from their own
shares; released, they get their weights back with a handover. If every DER that can move
that way is blocked, its output stops moving that way (the integrator freezes as at a
limit). In guard mode ``block`` it holds (``hold: grid``)
against every error that would move the DERs further in their direction, and follows one
that moves them back.

**In a hierarchy of ADNs** (docs/hierarchy.md) the level above asks for an offset of P_ref from
the ADN's own schedule (``adn_offset`` from the ADN's site agent); the CPFC takes the offset it
last heard into P_ref at each sample, and keeps it when the level above falls silent. An offset
moves the DERs without a step of the schedule, so the direction of directional availability is
decided at the ADN's own steps only.

**Said when over**: the first P_Y of every entry with certified figures carries them
(``design``: docs/method.md#said-when-over), so a recording knows what each step's entry was
certified for.

**Undoing wind-up.** The CPFC keeps its PI state of the last seconds. When a DER's
acknowledgement says it fell back at ``t``, or measurements stop, the samples computed from
measurements that already showed the fault (after ``t + T_meas``; after the last measurement)
are undone: the PI goes back to its state then, so that an outage leaves no trace in the
integrator, whatever its length.

Gains come from a :class:`GainSchedule`: the table entry of the subset, else an entry tuned on
demand (:class:`adnmesh.tuning.ondemand.OnDemandTuner`, warm-started from the table's nearest
plant, when that module exists), else the table's static
controller with unit weights; if none exists the CPFC keeps its gains and says so in its stats.
While an on-demand tuning runs, the CPFC uses the static controller and switches to the tuned
entry (bumplessly, a second switch of the same set) at the first sample after it is ready.

**Holding** (no wind-up, no jump; docs/method.md#watchdog-and-holds). The CPFC holds its output and
its integrator —
``P_Y`` stays as it was and carries ``hold`` — while

- no measurement has arrived for ``measurement_timeout_s`` (``hold: measurement``); when
  measurements return, the integrator is re-initialised so that the output continues from the
  held value (:meth:`SampledPI.reenter <adnmesh.control.pi.SampledPI.reenter>`);
- no DER is available (``hold: actuators``), e.g. every DER in its watchdog fallback after an
  outage of the CPFC → DER link (the availability monitor counts a DER in fallback as
  unavailable); the switch back to an available set is bumpless;
- it has just been restarted (``hold: resuming``; it sends nothing then): it waits for SI and a
  heartbeat of every available DER (their acknowledgement of the last P_Y they applied), at
  most ``heartbeat_timeout_s``, and resumes from the latest acknowledged P_Y, so that the DERs
  return to the setpoints they had before it was lost.

Each start and end of a hold is an event on ``event/cpfc``.
"""

from __future__ import annotations

import functools
import math
import os
import threading
import time
from collections import deque

from msgspec import UNSET, to_builtins
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from adnmesh.config import Config
from adnmesh.control.base import Agent, Outgoing
from adnmesh.control.loop_quantity import P_LOOP, LoopQuantity
from adnmesh.control.operating_point import available_power_w, initial_p_ip_w
from adnmesh.control.pi import SampledPI, SwitchRecord
from adnmesh.names import der_id_of
from adnmesh.wire.keys import Keys
from adnmesh.wire.messages import ActuatorGroup, Design, Envelope, Switch
from adnmesh.wire.units import ns
from adnmesh.tuning.subset_selection import able_to_move
from adnmesh.tuning.table import SchedulingTable, TableEntry

__all__ = ["CPFC", "DIRECTION_BAND", "GainSchedule", "HANDOVER_BOUND", "HANDOVER_MAX_S",
           "HANDOVER_RESPONSE_TIMES", "HANDOVER_TOLERANCE", "REACH_TOLERANCE", "TUNING_DELAY_S",
           "SwitchEvent", "initial_p_ref_w", "output_limits"]


REACH_TOLERANCE = 1.0
"""A reference this close beyond its reachable range (W or var) is in it: the range comes from
power flows solved to their tolerance (an HV grid's lower end, with every ADN at its schedule,
lay 5 mW above the operating point it was computed from)."""


def initial_p_ref_w(config: Config) -> float:
    """``P_ref`` before the first step: the operating point with ``P_Y = 0``, W (P_IP with every
    DER at its schedule: the power flow's with a grid model, else ``rest_of_grid_w`` plus the
    schedules)."""
    return initial_p_ip_w(config)


def output_limits(config: Config, weights: dict[str, float],
                  available: dict[str, float] | None = None) -> tuple[float, float]:
    """``(y_min, y_max)``: beyond them every weighted DER is saturated (dimensionless).

    A DER d saturates high at ``P_Y = (P_avail - P_sched) / (w_d P_inst)`` and low at
    ``P_Y = -P_sched / (w_d P_inst)`` (``available``: DER id -> P_avail, W; default P_inst).
    Without a weighted DER both limits are NaN.
    """
    highs, lows = [], []
    for der in config.ders:
        w = weights.get(der.id, 0.0)
        if w > 0:
            p_max = der.p_inst_w if available is None else available[der.id]
            highs.append((p_max - der.p_sched_w) / (w * der.p_inst_w))
            lows.append(-der.p_sched_w / (w * der.p_inst_w))
    if not highs:
        return math.nan, math.nan
    return min(lows), max(highs)


#: sim time an on-demand tuning is taken to last on the sim clock (see :class:`GainSchedule`), s
TUNING_DELAY_S = 1.0

#: a switch's handover lasts at least this many times the reaction plus 10-90 % rise time
#: (``t_delay_s + T_d ln 9``) of the slowest DER whose commanded power it moves, so that
#: every DER can follow it (docs/method.md#returning-ders-handover)
HANDOVER_RESPONSE_TIMES = 2.0

#: and at least ``1 / (HANDOVER_BOUND K_I Σ w_d P_inst,d)`` (the new entry's normalised
#: integral gain): then P_IP stays within about this fraction of the power handed over
HANDOVER_BOUND = 0.05

#: the longest handover, s
HANDOVER_MAX_S = 3600.0

#: a DER's commanded power moves at a switch if it changes by more than this fraction of
#: its installed power
HANDOVER_TOLERANCE = 1e-6

#: a step changes the direction the DERs move in when it takes their total commanded power
#: above their schedules beyond this fraction of the available DERs' installed power on the
#: other side (docs/method.md#directional-availability)
DIRECTION_BAND = 0.01


class GainSchedule:
    """Resolves a set of available DERs to its gains and weights.

    A subset the table lacks is tuned on demand. Until its entry is ready the CPFC runs the
    table's static controller (source ``static_tuning``) and switches (bumplessly) to the
    tuned entry at the first PI sample after it is ready (:meth:`ready`):

    - on the sim clock (``background`` False) the tuning is computed at once, so runs stay
      deterministic, but its result is released only ``tuning_delay_s`` of sim time later: the
      time it would take on a machine, as a fixed figure;
    - in realtime runs (``background`` True) it runs in a background thread and is ready when
      it is done.

    Without a static controller the CPFC waits for the tuning (computed at once).

    Parameters
    ----------
    config : Config
    table : SchedulingTable or None
        The gain-scheduling table (None: only on-demand tuning).
    tune : callable, optional
        ``tune(config, der_ids) -> TableEntry``; default: an
        :class:`adnmesh.tuning.ondemand.OnDemandTuner` warm-started from ``table`` (the global
        search of :func:`adnmesh.tuning.tune_subset` without a table), if importable.
    on_demand : bool
        Tune missing subsets at all (False: table, then static controller).
    tuning_delay_s : float
        Sim time an on-demand tuning takes on the sim clock, s (0: ready at the next sample).
    background : bool
        Tune in a background thread (realtime runs); ``tuning_delay_s`` is then not used.
    """

    def __init__(self, config: Config, table: SchedulingTable | None,
                 tune: Callable[[Config, list[str]], TableEntry] | None = None,
                 on_demand: bool = True, tuning_delay_s: float = TUNING_DELAY_S,
                 background: bool = False) -> None:
        self.config = config
        self.table = table
        self._tune = tune
        self.on_demand = on_demand
        self.tuning_delay_ns = ns(tuning_delay_s)
        self.background = background
        self._tuned: dict[frozenset, TableEntry] = {}
        self._jobs: dict[frozenset, tuple] = {}     # set -> (ready at ns, entry) or (future,)
        self._retuned: dict[frozenset, TableEntry] = {}   # entries that replace the table's
        self._retunes: dict[frozenset, tuple] = {}  # set -> as _jobs, of (entry, words)
        self._pool = None
        self._processes = None           # the retunes' process (realtime runs)
        self.sources: dict[str, int] = {}

    def lookup(self, available: frozenset[str], t_ns: int | None = None
               ) -> tuple[TableEntry | None, str]:
        """Return ``(entry, source)``; source is ``retuned`` (an entry of :meth:`retune`),
        ``table``, ``tuned``, ``static``,
        ``static_tuning`` (an on-demand tuning started at ``t_ns`` is not ready yet) or
        ``none``. Without ``t_ns`` a missing subset is tuned at once."""
        if available in self._retuned:
            return self._count(self._retuned[available], "retuned")
        if self.table is not None:
            entry = self.table.lookup(available)
            if entry is not None and entry.feasible:
                return self._count(entry, "table")
        if available in self._tuned:
            return self._count(self._tuned[available], "tuned")
        tune = None
        if self.on_demand:
            if self._tune is None:
                self._tune = _tuner(self.config, self.table)
            tune = self._tune
        static = self._static(available)
        if tune is not None and available:
            ids = [d for d in self.config.der_ids() if d in available]
            if t_ns is None or static is None:
                self._tuned[available] = tune(self.config, ids)
                return self._count(self._tuned[available], "tuned")
            if available not in self._jobs:
                self._jobs[available] = self._start(tune, ids, t_ns)
            return self._count(static, "static_tuning")
        if static is not None:
            return self._count(static, "static")
        return self._count(None, "none")

    def ready(self, available: frozenset[str], t_ns: int) -> bool:
        """Whether the on-demand tuning of ``available`` is done by ``t_ns`` (its entry is then
        what :meth:`lookup` returns)."""
        job = self._jobs.get(available)
        if job is None:
            return available in self._tuned
        if not _done(job, t_ns):
            return False
        entry = job[0].result() if len(job) == 1 else job[1]
        self._tuned[available] = entry
        del self._jobs[available]
        return True

    def retune(self, available: frozenset[str], job: Callable[[], tuple], t_ns: int,
               again: bool = False, at_once: bool = False) -> None:
        """Tune ``available`` again by ``job() -> (entry or None, words)`` (the model watch's,
        docs/method.md#model-watch): on the sim clock at once, released ``tuning_delay_s``
        later (deterministic, as an on-demand tuning); in realtime runs in a process of its
        own at a lower priority (``job`` picklable), so that the fit's seconds of CPU do not
        hold up the control loop's interpreter. Its entry, once :meth:`retuned` has handed it
        over, replaces the table's. A retune of the same set still pending stays, unless
        ``again`` (the cascade rule's newer verdict replaces it). ``at_once``: ``job`` is
        quick and its entry is ready at once, on either clock (the cascade rule's)."""
        if available in self._retunes and not (again and (at_once or not self.background)):
            return
        if at_once or not self.background:
            self._retunes[available] = (t_ns + (0 if at_once else self.tuning_delay_ns), job())
            return
        if self._processes is None:     # not a thread: the fit would hold up the PI's samples
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor
            self._processes = ProcessPoolExecutor(
                1, mp_context=multiprocessing.get_context("spawn"),
                initializer=_retune_worker, initargs=(os.getpid(),))
        self._retunes[available] = (self._processes.submit(job),)

    def retuned(self, available: frozenset[str], t_ns: int) -> tuple | None:
        """``(entry or None, words)`` of the retune of ``available`` once it is done by
        ``t_ns`` (once; None before); a feasible entry is then what :meth:`lookup` returns
        for ``available``."""
        job = self._retunes.get(available)
        if job is None or not _done(job, t_ns):
            return None
        del self._retunes[available]
        try:
            entry, words = job[0].result() if len(job) == 1 else job[1]
        except Exception as exc:           # noqa: BLE001 - the retune's process died: said
            return None, f"the retune's process failed: {exc!r}"
        if entry is not None and entry.feasible:
            self._retuned[available] = entry
        return entry, words

    def _start(self, tune, ids: list[str], t_ns: int) -> tuple:
        if self.background:
            if self._pool is None:
                from concurrent.futures import ThreadPoolExecutor
                self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tuning")
            return (self._pool.submit(tune, self.config, ids),)
        return (t_ns + self.tuning_delay_ns, tune(self.config, ids))

    def _static(self, available: frozenset[str]) -> TableEntry | None:
        if self.table is None or self.table.static is None or not available:
            return None
        static = self.table.static
        ids = tuple(d for d in self.config.der_ids() if d in available)
        return TableEntry(ids, static.kp, static.ki, dict.fromkeys(ids, 1.0))

    def _count(self, entry, source):
        self.sources[source] = self.sources.get(source, 0) + 1
        return entry, source


def _done(job: tuple, t_ns: int) -> bool:
    """Whether a tuning job is done by ``t_ns``: ``(future,)`` (background) once the future
    is, ``(ready at ns, result)`` (sim clock) from that instant on."""
    return job[0].done() if len(job) == 1 else t_ns >= job[0]


def _retune_job(config: Config, table: SchedulingTable | None, ders: tuple[str, ...], data):
    """``job() -> (entry or None, words)``: fit each moving DER type of ``data`` (a
    :class:`~adnmesh.results.model_watch.StepData`) and tune ``ders`` over the set it implies
    (:func:`adnmesh.tuning.retune.retune`). Picklable: a realtime run's CPFC runs it in a
    process of its own."""
    return functools.partial(_retune, config, table, ders, data)


def _retune(config: Config, table: SchedulingTable | None, ders: tuple[str, ...],
            data) -> tuple:
    from adnmesh.identify.type_fit import fit_types       # scipy, numba: when asked
    from adnmesh.tuning.problem import nominal_by_type
    from adnmesh.tuning.retune import retune

    try:
        fits = fit_types(data.period_s, data.setpoints_w, data.p_ip_w,
                         {t: a for t, a in nominal_by_type(config, ders).items()
                          if t in data.setpoints_w})
        entry, robust = retune(config, table, ders, fits)
    except Exception as exc:       # noqa: BLE001 - a worker's end: said, the entry stays
        return None, f"the fit or the tuning failed: {exc}"
    fitted = "; ".join(f"{t} dead time {f.delay_s:.4g} s, T_rise {f.rise_s:.4g} s "
                       f"(R² {f.r2:.3f})" for t, f in fits.items())
    if not entry.feasible:
        return entry, f"fitted {fitted}; no entry certified over the set ({entry.reason})"
    fig = entry.figures
    box = ", ".join(f"{t} b {u.lag_scale[0]:g}-{u.lag_scale[1]:g}, dead time "
                    f"{u.delay_add_s[0]:+g} to {u.delay_add_s[1]:+g} s"
                    for t, u in robust.types.items() if t in fits)
    return entry, (f"fitted {fitted}; tuned {len(ders)} DERs over {box}: K_P "
                   f"{entry.kp:.4g} 1/W, K_I {entry.ki:.4g} 1/(W s), designed rise "
                   f"{fig['rise_time_s']:.4g} s, settling {fig['settling_time_s']:.4g} s, "
                   f"overshoot {fig['overshoot_pct']:.3g} %")


def _retune_worker(parent_pid: int) -> None:
    """A retune process: below the control loop's priority, and gone with its CPFC."""
    os.nice(10)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="parent", daemon=True).start()


def _tuner(config: Config, table: SchedulingTable | None):
    """The on-demand tuner, warm-started from ``table``'s nearest plant (cached)."""
    from adnmesh.tuning.ondemand import OnDemandTuner   # numba: only when a subset is missing

    return OnDemandTuner(config, table)


@dataclass(frozen=True)
class SwitchEvent:
    """A gain switch: when, to which set (the DERs of the new entry), how, the output before
    and after (equal), the DERs' handover time (s, 0: at once) and, for a switch of direction,
    the direction (``up``, ``down``; else empty)."""

    t_ns: int
    available: tuple[str, ...]
    source: str
    record: SwitchRecord
    handover_s: float = 0.0
    direction: str = ""


class CPFC(Agent):
    """The CPFC state machine (agent id ``cpfc``; see the module docstring).

    Parameters
    ----------
    config : Config
        For the Q loop its reactive view (:func:`adnmesh.reactive.reactive_view`).
    schedule : GainSchedule
        Must resolve the set of all DERs (available at t = 0).
    loop : LoopQuantity
        The quantity it controls (:data:`~adnmesh.control.loop_quantity.P_LOOP` or
        ``Q_LOOP``): the keys and fields it reads and writes. Values named ``p_...`` below are
        in the loop's unit (W or var).
    start_ref : float, optional
        The reference before the first step (default :func:`initial_p_ref_w`).
    available : dict, optional
        DER id -> the top of its range (default
        :func:`~adnmesh.control.operating_point.available_power_w`); the bottom is 0.
    steps : list, optional
        ``(t_ns, change)`` of the reference (default the scenario's P_ref steps).
    known_ids : iterable of str, optional
        Every DER an SI may name (default the config's); the loop uses those of the config.
    reachable : (float, float), optional
        The range of the controlled quantity the DERs can reach within the grid limits and
        their capability (:func:`adnmesh.analysis.pq_region.reference_bounds`); a reference
        beyond it is clipped to it and said (default: none, nothing is clipped).
    reachable_note : str, optional
        Why there is no range although clipping is on (said as a warning at the first sample).
    guard_mode : str, optional
        The grid guard's mode whose messages it follows (default the config's; ``off`` without
        a grid model): ``directional`` takes the blocked DERs, ``block`` the hold, ``off``
        neither.
    """

    agent_id = "cpfc"

    def __init__(self, config: Config, schedule: GainSchedule, loop: LoopQuantity = P_LOOP,
                 start_ref: float | None = None, available: dict[str, float] | None = None,
                 steps: list[tuple[int, float]] | None = None, known_ids=None,
                 reachable: tuple[float, float] | None = None,
                 reachable_note: str = "", guard_mode: str | None = None,
                 model_watch=None) -> None:
        self.config = config
        self.loop = loop
        self.keys = Keys(config.grid)
        rt = config.runtime
        self.schedule = schedule
        self._ids = config.der_ids()
        self._p_inst = {d.id: d.p_inst_w for d in config.ders}
        self._p_sched = {d.id: d.p_sched_w for d in config.ders}
        self._response_s = {d.id: d.t_delay_s + config.t_lag_s(d) * math.log(9.0)
                            for d in config.ders}
        self._available = available_power_w(config) if available is None else available
        self._able = able_to_move(config, self._available)   # directional availability
        self.direction = 0                    # +1 up, -1 down, 0 not moved yet
        # the grid guard: DERs blocked per direction (docs/method.md#grid-guard), its hold
        self._blocked: dict[int, frozenset[str]] = {1: frozenset(), -1: frozenset()}
        self._kept: dict[str, float] = {}     # DERs left out by the guard -> their power, W
        self._stop_said = 0                   # the guard's stop last said (+1 / -1 / 0)
        guard = config.grid_model.guard if config.grid_model is not None else None
        self._guard_mode = guard_mode or ("off" if guard is None else guard.mode)
        self.guard_hold = False
        self._redirected = False              # the pending switch is one of direction
        self.period_ns = ns(rt.pi_period_s)
        self.weights_period_ns = ns(rt.weights_period_s)
        self.p_ref_w = initial_p_ref_w(config) if start_ref is None else start_ref
        self.p_meas_w = self.p_ref_w          # the run starts in the operating point
        self.reachable = reachable
        self._note = reachable_note
        self.target_w = self._p_ref_before_clip = self.p_ref_w   # P_ref within reach
        self.meas_timeout_ns = ns(rt.measurement_timeout_s)
        self.ack_timeout_ns = ns(rt.heartbeat_timeout_s)
        self.si_timeout_ns = ns(rt.heartbeat_timeout_s + rt.links.availability_to_cpfc.jitter_s)
        self.last_si_ns = 0                    # when the last SI was delivered
        self.si_stale = False                  # availability from the heartbeats (no SI)
        self.last_meas_ns = 0
        self.actuators_held = 0                  # +1 / -1: every following DER held back
        self.hold: str | None = None          # measurement, actuators, resuming
        self._resume_ns: int | None = None
        self._si_seen = False
        # DER -> (t, mode, p_y applied, available) of its last heartbeat
        self.acks: dict[str, tuple[int, str, float, bool]] = {}
        self._watchdog: set[str] = set()     # the DERs whose last acknowledgement says fallback
        self.si_available = frozenset(self._ids)            # as SI last said
        self._t_meas_ns = ns(config.t_meas_s)
        self._history: deque = deque(maxlen=max(2, int(5 * ns(1.0) // self.period_ns)))
        self._rollback_to: int | None = None    # undo the samples after this time
        self._steps = ([(ns(s.t_s), s.delta_w) for s in config.scenario.p_ref_steps]
                       if steps is None else list(steps))
        self._known = frozenset(self._ids if known_ids is None else known_ids)
        self._next_step = 0
        # the level above's share (a hierarchy of ADNs): the offset of P_ref it asks for, W,
        # and the part of it already in p_ref_w
        self.offset_w = self._offset_in_ref_w = 0.0
        self._own_ref_w = self.p_ref_w      # P_ref without the offset: its steps only
        # heard from a level above: announce the ADN again every weights_period_s too (a
        # restarted upper CPFC learns the loops it runs on)
        self._below_a_level = False
        self._next_announce_ns = 0
        # the upper CPFC of a hierarchy: the rule for the ADNs' own gain switches
        # (adnmesh.cascade.switches.LowerSwitchRule; None elsewhere), the factor applied per set
        self.lower_switch_rule = None
        self._cascade_factor: dict[frozenset[str], float] = {}
        self._rule_set = frozenset(self._ids)   # the set the rule last saw (certified: all)
        self._retune_kind = "model"             # what the pending retune is: model or cascade
        self.available = self.in_use = frozenset(self._ids)
        self._pending: frozenset[str] | None = None
        self._awaiting: frozenset[str] | None = None     # set whose tuning is running
        entry, source = schedule.lookup(self.available)
        if entry is None:
            raise ValueError("no gains for the set of all DERs (table and tuning unavailable)")
        self.entry = entry
        self.entry_index = 0
        self.weights = self._weights(entry, self.in_use)
        self.pi = SampledPI(entry.kp, entry.ki, rt.pi_period_s)
        self.pi.set_limits(*self._limits())
        self.next_sample_ns = 0
        self._next_weights_ns = 0
        self._p_ref_sent: float | None = None
        self._p_y_sent = 0.0                    # the P_Y of the last p_y message (DERs hold it)
        self._announced: int | None = None      # the entry whose design figures were sent
        self._as_actuator: tuple | None = None  # what the last adn_actuator said: entry, DERs
        self._reannounce = True                 # weights set since the last look at them
        self._event_key = self.keys.of("event", self.agent_id)
        self.switches: list[SwitchEvent] = []
        self.counts: dict[str, int] = {"samples": 0, "no_gains": 0, "rejected_si": 0,
                                       "held_samples": 0, "rollbacks": 0}
        # the model watch (docs/method.md#model-watch): steps over their design, retunes
        self.model_watch = model_watch
        self._retune = config.runtime.model_watch == "retune" and model_watch is not None
        self._retuning: frozenset[str] | None = None     # set whose retune runs
        self._retuned_sets: set[frozenset[str]] = set()  # retuned once: not again
        if model_watch is not None:
            self.counts.update(model_mismatches=0, retunes=0)

    # -- agent interface -----------------------------------------------------------------------

    def next_timer_ns(self) -> int:
        return self.next_sample_ns

    def stats(self) -> dict[str, float]:
        prefix = self.loop.stats_prefix
        return {**{f"{prefix}{k}": float(v) for k, v in self.counts.items()},
                **{f"{prefix}gains_{k}": float(v) for k, v in self.schedule.sources.items()}}

    def on_clock(self, mode: str) -> None:
        """In realtime runs a subset the table lacks is tuned in a background thread (the
        static controller meanwhile); on the sim clock its tuning takes ``tuning_delay_s``."""
        self.schedule.background = mode == "realtime"

    def resume(self, t_ns: int) -> None:
        """A restarted CPFC at ``t_ns``: hold until the DERs' acknowledgements are in."""
        self.next_sample_ns = self._next_weights_ns = -(-t_ns // self.period_ns) * self.period_ns
        self.last_meas_ns = self._resume_ns = self.last_si_ns = t_ns
        self.hold = "resuming"

    def on_message(self, t_ns: int, message: Envelope) -> list[Outgoing]:
        if self.model_watch is not None and message.type in ("p_ip", "si", "heartbeat"):
            found = self.model_watch.observe(message.type, to_builtins(message))
            out = self._mismatches(t_ns, found) if found else []
            return out + self._handle(t_ns, message)
        return self._handle(t_ns, message)

    def _handle(self, t_ns: int, message: Envelope) -> list[Outgoing]:
        loop = self.loop
        if message.type == "p_ip":
            measured = getattr(message, loop.measured_field)
            if measured is UNSET:
                return []
            self.p_meas_w = measured
            self.last_meas_ns = t_ns
            held = getattr(message, loop.held_field)
            self.actuators_held = 0 if held is UNSET else (1 if held == "up" else -1)
        elif message.type == "heartbeat":
            self._ack(t_ns, message)
        elif message.type == "adn_offset" and loop is P_LOOP:
            self.offset_w = message.offset_w    # taken into P_ref at the next sample
            self._below_a_level = True
        elif message.type == "adn_actuator" and self.lower_switch_rule is not None:
            return self._lower_switched(t_ns, message)
        elif message.type == "grid_guard":
            return self._guard(message)
        elif message.type == "si":
            si = message.si
            if not set(si) <= self._known:
                self.counts["rejected_si"] += 1
                return []
            self._si_seen = True
            self.last_si_ns = t_ns
            self.si_available = frozenset(d for d in self._ids if si.get(d, False))
            out = []
            if self.si_stale:
                self.si_stale = False
                out.append(self._event("INFO", "si_back", "SI from the availability monitor "
                                       "arrives again: availability from SI"))
            self._update_available(t_ns)
            return out
        return []

    def _guard(self, message) -> list[Outgoing]:
        """The grid guard's state: the DERs blocked per direction for this loop's quantity
        and the guard's hold. A change of the DERs the CPFC can use in its direction is a
        switch at the next sample (bumpless, with handover), said by an event."""
        q = self.loop.name.lower()
        mode = self._guard_mode
        blocked = {1: frozenset(), -1: frozenset()} if mode != "directional" else {
            1: frozenset(getattr(message, f"{q}_up")).intersection(self._p_inst),
            -1: frozenset(getattr(message, f"{q}_down")).intersection(self._p_inst)}
        self.guard_hold = mode == "block" and bool(message.hold)   # what the config's mode does
        if blocked == self._blocked:
            return []
        self._blocked = blocked
        if self.hold == "resuming":
            return []                   # _try_resume takes the blocks in
        return self._redirect_by_guard()

    def _stand(self) -> None:
        """Not moved by a step yet (direction 0) while the guard blocks DERs: the direction is
        the way the DERs stand from their schedules at the last output."""
        if self.direction == 0 and (self._blocked[1] or self._blocked[-1]):
            standing = sum(self._share_w(d, w, self._p_y_sent) for d, w in self.weights.items())
            self.direction = 1 if standing > 0 else -1 if standing < 0 else 0

    def _redirect_by_guard(self) -> list[Outgoing]:
        """A switch at the next sample if the guard changes the DERs the CPFC can use, said by
        an event; an event when it blocks every DER that can move the DERs' way."""
        self._stand()
        stop = self._guard_stop()
        said, self._stop_said = self._stop_said, stop
        if self._pending is not None:
            return []
        in_use = self._in_use(self.available)
        way = "up" if self.direction > 0 else "down"
        if in_use == self.in_use:
            if stop and not said:
                return [self._event("WARNING", "guard", f"grid guard: every DER that can move "
                                    f"{way} is blocked: the output no longer moves {way}")]
            return []
        self._pending = self.available
        left = [d for d in self._ids if d in self._blocked.get(self.direction, ())
                and d in self.available]
        text = (f"grid guard: {', '.join(left)} left out moving {way}; the entry of "
                f"{len(in_use)} DER(s) takes over" if left else
                "grid guard: every DER usable again moving " + way)
        if self._guard_stop():
            text = (f"grid guard: every DER that can move {way} is blocked: the output no "
                    f"longer moves {way}")
        return [self._event("WARNING" if left else "INFO", "guard", text)]

    def _guard_stop(self) -> int:
        """+1 / -1 when every available DER that can move in the DERs' direction is blocked
        that way by the grid guard (the output then does not move further that way; the PI's
        integrator freezes as at a limit), else 0."""
        if self.direction == 0:
            return 0
        able = self.available & self._able[self.direction]
        return self.direction if able and not able - self._blocked[self.direction] else 0

    def _ack(self, t_ns: int, message) -> None:
        """A DER's acknowledgement; a new fallback undoes the samples it disturbed."""
        der = der_id_of(message.src)
        if der not in self._p_inst:         # a DER without reactive range: not in the Q loop
            return
        before = self.acks.get(der)
        acked = getattr(message, self.loop.output_field)
        self.acks[der] = (t_ns, message.mode, 0.0 if acked is UNSET else acked,
                          message.available)
        if message.mode == "watchdog":
            self._watchdog.add(der)
        else:
            self._watchdog.discard(der)
        fell_back = message.mode == "watchdog" and (before is None or before[1] != "watchdog")
        if fell_back and der in self.weights and self.hold is None:
            self._undo_after(message.t_send_ns + self._t_meas_ns)
        self._update_available(t_ns)

    def _update_available(self, t_ns: int) -> None:
        """The available set: SI (while stale: the heartbeats, see the module docstring) less
        the DERs whose own acknowledgement says fallback."""
        base = self._heard(t_ns) if self.si_stale else self.si_available
        available = base - self._watchdog if self._watchdog else base   # every acknowledgement
        self._pending = None if available is self.available or available == self.available \
            else available                                             # comes here: no loop

    def _heard(self, t_ns: int) -> frozenset[str]:
        """The DERs the heartbeats say are available at ``t_ns``: the monitor's rule."""
        timeout = self.ack_timeout_ns
        return frozenset(d for d, (t, mode, _, available) in self.acks.items()
                         if available and mode != "watchdog" and t_ns < t + timeout)

    def _watch_si(self, t_ns: int, out: list) -> None:
        """No SI for the SI timeout: availability from the heartbeats, said once; while
        stale, follow them (a heartbeat's age changes the set with time)."""
        if not self.si_stale and t_ns - self.last_si_ns > self.si_timeout_ns:
            self.si_stale = True
            out.append(self._event("WARNING", "si_stale", "no SI from the availability monitor "
                                   f"for {self.si_timeout_ns / 1e9:g} s: availability taken "
                                   "from the DERs' heartbeats"))
        if self.si_stale:
            self._update_available(t_ns)

    def _undo_after(self, t_ns: int) -> None:
        """Ask the next sample to take the PI back to its state at ``t_ns`` (see above)."""
        if self._rollback_to is None or t_ns < self._rollback_to:
            self._rollback_to = t_ns

    def on_timer(self, t_ns: int) -> list[Outgoing]:
        out = self._reference()
        if self._note:
            out.append(self._event("WARNING", "reference_clipping_off", self._note))
            self._note = ""
        self.next_sample_ns += self.period_ns
        self._watch_si(t_ns, out)
        if self.hold == "resuming" and not self._try_resume(t_ns, out):
            return out
        error_w = self.target_w - self.p_meas_w
        if self.direction == 0 and self.hold is None and (self._blocked[1] or self._blocked[-1]):
            out += self._redirect_by_guard()  # moved without a step: blocks apply now
        self._watch_measurement(t_ns, error_w, out)
        rolled_back = self._rollback_to is not None and self._roll_back()
        self._watch_guard_hold(error_w, out)
        if self.hold in (None, "grid") and not rolled_back:
            # the grid guard stops the output that way (all blocked, or its hold: every way
            # before the DERs first moved), K_P's part too; the DERs' limits stop the integrator
            held_by_grid = (self._guard_stop() * error_w > 0 or self.hold == "grid"
                            and (self.direction * error_w > 0 or not self.direction))
            stop = held_by_grid or self.actuators_held * error_w > 0
            p_y = self.pi.update(error_w, freeze=stop)
            if held_by_grid or (stop and self.hold == "grid"):
                self.pi.output = self._p_y_sent
                self.pi.reenter(error_w)
                p_y = self.pi.output
                self.counts["held_samples"] += 1
            self._watch_direction(t_ns, p_y)
        else:
            p_y = self.pi.output
            self.counts["held_samples"] += 1
        loop = self.loop
        body = {loop.output_field: p_y, loop.reference_field: self.p_ref_w, "kp": self.pi.kp,
                "ki": self.pi.ki}
        if (self._pending is None and self._awaiting is not None
                and self.schedule.ready(self._awaiting, t_ns)):
            self._pending, self._awaiting = self.available, None    # the tuned gains are in
        if self._retuning is not None:
            self._take_retune(t_ns, out)
        if self._pending is not None:
            self._apply_switch(t_ns, body, out)
        body["entry"] = self.entry_index
        announce = self.entry_index != self._announced
        if announce:
            self._announced = self.entry_index
            design = self._design(self.entry)
            if design is not None:
                body["design"] = design
        if t_ns >= self._next_weights_ns:
            body["w"] = dict(self.weights)
            self._next_weights_ns = t_ns + self.weights_period_ns
        if self.hold is not None:
            body["hold"] = self.hold
        out.append(Outgoing(self.keys.of(loop.output_kind), body))
        if loop is P_LOOP and self._reannounce:
            # a new entry, or the same gains on other DERs (no entry for the set: held on)
            self._reannounce = False
            acting = (self.entry_index, tuple(d for d in self._ids if self.weights.get(d, 0) > 0))
            if acting[1] and acting != self._as_actuator:
                self._as_actuator = acting
                self._next_announce_ns = t_ns + self.weights_period_ns
                out.append(Outgoing(self.keys.of("adn_actuator"), self._actuator()))
        elif (loop is P_LOOP and self._below_a_level and t_ns >= self._next_announce_ns
              and any(w > 0 for w in self.weights.values())):
            self._next_announce_ns = t_ns + self.weights_period_ns
            out.append(Outgoing(self.keys.of("adn_actuator"), self._actuator()))
        self._p_y_sent = body[loop.output_field]
        if self.model_watch is not None:
            self._watch_sent(t_ns, out)
        self.counts["samples"] += 1
        self._history.append((t_ns, self.pi.snapshot()))
        return out

    def _roll_back(self) -> bool:
        """Take the PI back to its state after the last sample at or before the rollback
        time (the samples after it were computed from disturbed measurements)."""
        t_back, self._rollback_to = self._rollback_to, None
        while self._history and self._history[-1][0] > t_back:
            self._history.pop()
        if not self._history:
            return False
        self.pi.restore(self._history[-1][1])
        self.counts["rollbacks"] += 1
        return True

    # -- the steps of a sample -----------------------------------------------------------------

    def _reference(self) -> list[Outgoing]:
        """Apply the P_ref steps due and the level above's offset as it last said it; the
        p_ref message when P_ref changed."""
        t_ns = self.next_sample_ns
        while self._next_step < len(self._steps) and self._steps[self._next_step][0] <= t_ns:
            self._own_ref_w += self._steps[self._next_step][1]
            self._next_step += 1
        self._offset_in_ref_w = self.offset_w
        # the reference is its own part plus the offset, each kept as it is (a running sum of
        # the offset's changes would drift by rounding)
        self.p_ref_w = self._own_ref_w + self._offset_in_ref_w
        if self.p_ref_w == self._p_ref_sent:
            return []
        self._p_ref_sent = self.p_ref_w
        loop = self.loop
        body = {loop.reference_field: self.p_ref_w}
        if self._below_a_level:           # the offset is an input, not a step of the reference
            body["offset_w"] = self._offset_in_ref_w
        return [Outgoing(self.keys.of(loop.reference_kind), body), *self._clip()]

    def _clip(self) -> list[Outgoing]:
        """The reference the loop controls to: P_ref within the reachable range; a change of
        whether it is clipped is said (the recorded P_ref stays the one asked for)."""
        was = self.target_w != self._p_ref_before_clip
        low, high = self.reachable or (-math.inf, math.inf)
        self._p_ref_before_clip = ref = self.p_ref_w
        inside = low - REACH_TOLERANCE <= ref <= high + REACH_TOLERANCE
        self.target_w = ref if inside else min(max(ref, low), high)
        unit = "var" if self.loop.name == "Q" else "W"
        name = f"{self.loop.name}_ref"
        if self.target_w != self.p_ref_w:
            return [self._event("WARNING", "reference_clipped", (
                f"{name} {self.p_ref_w / 1e6:.4f} M{unit} lies outside what the DERs can "
                f"reach within the grid limits and their capability ({low / 1e6:.4f} to "
                f"{high / 1e6:.4f} M{unit}): controlled to {self.target_w / 1e6:.4f} M{unit} "
                "instead of winding up"))]
        if was:
            return [self._event("INFO", "reference_reachable",
                                f"{name} {self.p_ref_w / 1e6:.4f} M{unit} is reachable again")]
        return []

    def _watch_direction(self, t_ns: int, p_y: float) -> None:
        """Directional availability (docs/method.md#directional-availability): at the sample
        before a step of P_ref, the direction the DERs will move in is where their total
        commanded power above their schedules will be once the step is done, that of now plus
        the step, when it is more than :data:`DIRECTION_BAND` of the available DERs'
        installed power away from their schedules (else the direction stays). If the DERs
        that can move in it are others than those in use, switch to their entry now
        (bumplessly, with the loop at rest), so that the step meets the gains designed for
        them."""
        steps, upcoming = self._steps, self._next_step
        step_w = 0.0
        while upcoming < len(steps) and steps[upcoming][0] <= t_ns + self.period_ns:
            step_w += steps[upcoming][1]
            upcoming += 1
        if step_w == 0.0:
            return
        commanded_w = sum(self._share_w(d, w, p_y) for d, w in self.weights.items()) + step_w
        band_w = DIRECTION_BAND * sum(self._p_inst[d] for d in self.available)
        direction = 1 if commanded_w > band_w else -1 if commanded_w < -band_w else \
            self.direction
        if direction == self.direction:
            return
        self.direction = direction
        if self._pending is None and self._in_use(self.available) != self.in_use:
            self._pending, self._redirected = self.available, True

    def _in_use(self, available: frozenset[str]) -> frozenset[str]:
        """The DERs whose entry the CPFC uses: the available ones that can move in the
        direction the DERs move and that the grid guard does not block that way (all
        available ones before they first moved; the set in use if the guard blocks every one
        that can move: the output then stops in that direction; all available ones if none
        can)."""
        if self.direction == 0:
            return available
        able = available & self._able[self.direction]
        usable = able - self._blocked[self.direction]
        if not usable and able:              # all blocked: keep the set (and caps) in use
            return (self.in_use & available) or able
        return usable or able or available

    def _watch_measurement(self, t_ns: int, error_w: float, out: list) -> None:
        """Hold while measurements are missing; re-enter without a jump when they return."""
        stale = t_ns - self.last_meas_ns > self.meas_timeout_ns
        if stale and self.hold in (None, "grid"):      # a grid hold needs measurements too
            self.hold = "measurement"
            self._undo_after(self.last_meas_ns)
            out.append(self._event("WARNING", "hold", "no measurement for "
                                   f"{self.meas_timeout_ns / 1e9:g} s: output and integrator "
                                   "held"))
        elif not stale and self.hold == "measurement":
            self.hold = None if self.weights else "actuators"
            self.pi.reenter(error_w)
            out.append(self._event("INFO", "resume", "measurements back: control resumed "
                                   f"from P_Y {self.pi.output:.6g} without a jump"))

    def _watch_guard_hold(self, error_w: float, out: list) -> None:
        """Guard mode ``block``: while the guard holds, output and integrator hold against
        every error that would move the DERs further in their direction (all errors before
        they first moved); the other way, back towards their schedules, they follow (a step
        back relieves the limit). Resume without a jump when the guard lets go."""
        if self.guard_hold and self.hold is None:
            self.hold = "grid"
            out.append(self._event("WARNING", "hold", "grid limit violated: output and "
                                   "integrator held until the band is restored (a move back "
                                   "towards the schedules is still followed)"))
        elif not self.guard_hold and self.hold == "grid":
            self.hold = None if self.weights else "actuators"
            self.pi.reenter(error_w)
            out.append(self._event("INFO", "resume", "grid band restored: control resumed "
                                   f"from P_Y {self.pi.output:.6g} without a jump"))

    def _apply_switch(self, t_ns: int, body: dict, out: list) -> None:
        record = self._switch(t_ns, self._pending)
        self._pending = None
        if not self.weights and self.hold is None:
            self.hold = "actuators"
            out.append(self._event("WARNING", "hold", "no DER available: output and "
                                   "integrator held"))
        if record is None:
            return
        if self.hold == "actuators":
            self.hold = None
            out.append(self._event("INFO", "resume", "DERs available again: control resumed"))
        handover_s = self.switches[-1].handover_s
        direction = self.switches[-1].direction
        body.update({self.loop.output_field: record.p_y_after}, kp=self.pi.kp, ki=self.pi.ki,
                    switch=Switch(record.p_y_before, record.p_y_limited, record.kp_before,
                                  record.ki_before, record.scale,
                                  handover_s if handover_s > 0 else UNSET,
                                  direction or UNSET,
                                  [d for d in self._ids if d in self._kept] or UNSET))
        self._next_weights_ns = t_ns
        if self.lower_switch_rule is not None and self.in_use != self._rule_set:
            out += self._cascade_rule(t_ns, "the ADNs in use changed")   # a hierarchy's top

    def _try_resume(self, t_ns: int, out: list) -> bool:
        """A restarted CPFC: resume once SI and every available DER's acknowledgement are in
        (or the heartbeat timeout passed); the output continues from the acknowledged P_Y."""
        since = self._resume_ns
        available = self._pending if self._pending is not None else self.available
        fresh = {d: a for d, a in self.acks.items() if a[0] >= since}
        waiting = not self._si_seen or not set(available) <= set(fresh)
        if waiting and t_ns - since < self.ack_timeout_ns:
            return False
        acked = max(fresh.values())[2] if fresh else 0.0     # the most recent acknowledgement
        if not self._si_seen and not self.si_stale:      # no SI: start from the heartbeats
            self.last_si_ns = t_ns - self.si_timeout_ns - 1
            self._watch_si(t_ns, out)
            available = self._pending if self._pending is not None else self.available
        self._pending = None
        self.available = frozenset()      # the switch below sets gains, weights and limits
        self.pi.output = self._p_y_sent = acked
        self._stand()                         # the guard's blocks apply from the DERs' side
        record = self._switch(t_ns, available)
        self.hold = None if record is not None else "actuators"
        self.pi.reenter(self.target_w - self.p_meas_w)
        self._next_weights_ns = t_ns
        out.append(self._event("INFO", "resume", f"restarted: resumed from the P_Y {acked:.6g} "
                               f"the DERs acknowledged ({len(fresh)} heartbeat(s))"))
        return True

    # -- the model watch (docs/method.md#model-watch) ------------------------------------------

    def _watch_sent(self, t_ns: int, out: list[Outgoing]) -> None:
        """Show the model watch this sample's reference and entry, and the set-points its
        P_Y commands."""
        watch = self.model_watch
        for message in list(out):
            kind = message.key.rsplit("/", 1)[-1]
            if kind in ("p_ref", "p_y") and (kind == "p_ref" or "switch" in message.body
                                             or "design" in message.body):
                body = to_builtins(message.body)
                body.update(t_send_ns=t_ns, src=self.agent_id)
                for found in watch.observe(kind, body):
                    out += self._mismatches(t_ns, [found])
        if self._retune:
            p_y = self._p_y_sent
            watch.commanded(t_ns, {d: self._p_sched[d] + self._share_w(d, w, p_y)
                                   for d, w in self.weights.items()})

    def _mismatches(self, t_ns: int, found) -> list[Outgoing]:
        """The events of steps over their design; with ``retune``, the fit and tuning of
        the subset in use if it is the step's and has not been retuned yet."""
        out = []
        for over in found:
            self.counts["model_mismatches"] += 1
            out.append(self._event("WARNING", "model_mismatch", over.text))
            step = getattr(over, "check", None)      # None: a slow recovery after a switch
            ders = frozenset(step.ders) if step is not None else frozenset()
            if (not self._retune or step is None or ders != self.in_use
                    or ders in self._retuned_sets or self._retuning is not None):
                continue
            try:
                data = self.model_watch.step_data(over)
            except ValueError as exc:
                out.append(self._event("WARNING", "model_retune", f"not tuned again: {exc}"))
                continue
            self._retuning, self._retune_kind = ders, "model"
            self._retuned_sets.add(ders)
            self.schedule.retune(ders, _retune_job(self.config, self.schedule.table,
                                                   tuple(d for d in self._ids if d in ders),
                                                   data), t_ns)
            out.append(self._event("INFO", "model_retune",
                                   f"fitting the DER types of entry {step.entry} to the "
                                   f"step at {step.t_s:g} s and tuning "
                                   f"{len(ders)} DERs again over the set the fit implies"))
        return out

    def _take_retune(self, t_ns: int, out: list[Outgoing]) -> None:
        """Switch to the retuned entry once it is ready (if its set is still in use)."""
        done = self.schedule.retuned(self._retuning, t_ns)
        if done is None:
            return
        ders, self._retuning = self._retuning, None
        entry, words = done
        kind = self._retune_kind
        if entry is None or not entry.feasible:
            out.append(self._event("WARNING", f"{kind}_retune", f"the entry stays: {words}"))
            return
        self.counts["retunes"] = self.counts.get("retunes", 0) + 1
        if kind == "cascade":                  # the factor now in use for that set
            factor = self._cascade_factor[ders] = entry.figures.get("cascade_back_off", 1.0)
            named = ", ".join(d for d in self._ids if d in ders)    # in the config's order
            words = f"the upper gains x{factor:.3g} in use for {named}"
        out.append(self._event("INFO", f"{kind}_retuned", words))
        if ders == self.in_use and self._pending is None:
            self._pending = self.available

    def _lower_switched(self, t_ns: int, message) -> list[Outgoing]:
        """An ADN below announced another closed loop (docs/hierarchy.md#lower-switches): the
        rule for the set in use, if the ADN is in it (:meth:`_cascade_rule`)."""
        try:
            adn = self.lower_switch_rule.take(message)
        except ValueError as exc:       # a loop the cascade's numerics cannot take: said
            return [self._rejected_announcement(exc)]
        if adn is None or adn not in self.in_use:
            return []
        return self._cascade_rule(t_ns, f"{adn} switched its gains", say_stay=True)

    def _cascade_rule(self, t_ns: int, why: str, say_stay: bool = False) -> list[Outgoing]:
        """The cascade of the set in use with the ADNs' loops as last announced; its table
        entry's gains backed off by the factor that certifies it (1: the table's), switched to
        as a retune is, bumplessly, at the next sample. The factor counts as in use for the set
        once switched to (a verdict left pending when the set changed is evaluated again on
        return). The evaluation runs in the sample's time (about 35 ms per factor tried):
        hierarchies run on the sim clock only. A loop the numerics cannot take is counted and
        said; the gains stay."""
        rule, table, ders = self.lower_switch_rule, self.schedule.table, self.in_use
        self._rule_set = ders
        base = None if table is None else table.lookup(sorted(ders))
        if base is None or not base.feasible:
            return []
        try:
            factor, fig = rule.back_off(base.ders, base.w, base.kp, base.ki)
        except ValueError as exc:
            return [self._rejected_announcement(exc)]
        if factor is None:
            c = rule.constraints
            return [self._event("WARNING", "cascade_rule", f"{why}: no back-off certifies the "
                                f"cascade ({fig.problem(c.disk_margin_min, c.overshoot_max_pct)})"
                                "; the upper gains stay")]
        if factor == self._cascade_factor.get(ders, 1.0):
            return [self._event("INFO", "cascade_rule", f"{why}: the upper gains stay "
                                f"(x{factor:.3g} certifies the cascade)")] if say_stay else []
        figures = {**base.figures, "rise_time_s": fig.rise_time_s, "overshoot_pct":
                   fig.overshoot_pct, "settling_time_s": fig.settling_time_s,
                   "disk_margin": fig.disk_margin, "cascade_back_off": factor}
        entry = replace(base, kp=base.kp * factor, ki=base.ki * factor, figures=figures)
        words = (f"{why}: the upper gains x{factor:.3g} certify the cascade "
                 f"(disk margin {fig.disk_margin:.3g}, overshoot {fig.overshoot_pct:.3g} %)")
        self._retuning, self._retune_kind = ders, "cascade"
        self.schedule.retune(ders, lambda: (entry, words), t_ns, again=True, at_once=True)
        return [self._event("INFO", "cascade_rule", words)]

    def _rejected_announcement(self, exc: Exception) -> Outgoing:
        self.counts["rejected_announcements"] = self.counts.get("rejected_announcements", 0) + 1
        return self._event("WARNING", "cascade_rule", f"an ADN's announcement is not evaluated, "
                           f"the upper gains stay: {exc}"[:500])

    def _event(self, level: str, kind: str, text: str) -> Outgoing:
        if self.loop is not P_LOOP:
            text = f"{self.loop.name} loop: {text}"
        return Outgoing(self._event_key, {"level": level, "kind": kind, "text": text,
                                          "subject": self.agent_id})

    # -- internals -----------------------------------------------------------------------------

    def _switch(self, t_ns: int, available: frozenset[str]) -> SwitchRecord | None:
        redirected, self._redirected = self._redirected, False
        self._reannounce = True
        self.available = available
        in_use = self.in_use = self._in_use(available)
        entry, source = self.schedule.lookup(in_use, t_ns) if in_use else (None, "none")
        self._awaiting = in_use if source == "static_tuning" else None
        if entry is None:
            # no actuators or no gains: keep the gains, hold the output where it is
            self.counts["no_gains"] += 1
            self.weights = self._weights(self.entry, in_use)
            if not self.weights:
                self.pi.set_limits(self.pi.output, self.pi.output)
            return None
        weights_before = self.weights
        kept_before, kept = self._kept, self._keep(weights_before, available, in_use)
        self._kept = kept
        carried = self._commanded_gain({d: w for d, w in weights_before.items()
                                        if d not in kept}, available)
        released_w = sum(w for d, w in kept_before.items() if d in available and d not in kept)
        self.entry = entry
        self.entry_index += 1
        self.weights = self._weights(entry, in_use)
        self.pi.set_limits(*self._limits())
        after = self._commanded_gain(self.weights, in_use)
        scale = carried / after if carried > 0 and after > 0 else 1.0
        scale = self._continuing_scale(weights_before, available, scale, kept, released_w)
        record = self.pi.switch(entry.kp, entry.ki, scale)
        handover_s = self._handover_s(weights_before, scale, kept_before, kept)
        direction = ("up" if self.direction > 0 else "down") if redirected else ""
        self.switches.append(SwitchEvent(t_ns, tuple(d for d in self._ids if d in in_use),
                                         source, record, handover_s, direction))
        return record

    def _keep(self, weights_before: dict[str, float], available: frozenset[str],
              in_use: frozenset[str]) -> dict[str, float]:
        """The DERs the grid guard leaves out that keep their commanded power (a cap, not a
        return to their schedules: docs/method.md#grid-guard) -> that power above their
        schedules, W: those of the old weights or already kept that are still available,
        blocked in the DERs' direction and not in the new set."""
        blocked = self._blocked.get(self.direction, frozenset())
        found = dict(self._kept)
        for d, w in weights_before.items():
            if d not in found:
                found[d] = self._share_w(d, w, self.pi.output)
        return {d: power for d, power in found.items()
                if d in available and d in blocked and d not in in_use}

    def _handover_s(self, weights_before: dict[str, float], scale: float,
                    kept_before: dict[str, float] | None = None,
                    kept: dict[str, float] | None = None) -> float:
        """How long the DERs take to hand over the power the switch moves between them, s
        (docs/method.md#returning-ders-handover): 0 after a hold without DERs (nothing
        carried the output; the DERs take their shares at once) and if it moves none (every
        DER's commanded power at the P_Y the DERs hold, by Eq. 1 and limited, is the same with
        the old weights as with the new ones and the scaled P_Y); else the longer of
        :data:`HANDOVER_RESPONSE_TIMES` times the response time of the slowest DER whose
        commanded power it moves and ``1 / (HANDOVER_BOUND ki_n)``, ``ki_n = K_I Σ w_d
        P_inst,d`` of the new entry (1/s), at most :data:`HANDOVER_MAX_S`."""
        if not any(d in self.available for d in weights_before):
            return 0.0          # nothing carried the output (a hold without DERs): at once
        held = self._p_y_sent
        slowest = None
        kept_before, kept = kept_before or {}, kept or {}
        for d in self.available & (set(weights_before) | set(self.weights) | set(kept_before)):
            if d in kept:
                continue                     # it keeps its power: nothing moves
            before = (kept_before[d] if d in kept_before else
                      self._share_w(d, weights_before.get(d, 0.0), held))
            jump = self._share_w(d, self.weights.get(d, 0.0), held * scale) - before
            if abs(jump) > HANDOVER_TOLERANCE * self._p_inst[d]:
                slowest = max(slowest or 0.0, self._response_s[d])
        if slowest is None:
            return 0.0
        ki_n = self.pi.ki * self._commanded_gain(self.weights, self.in_use)
        return min(max(HANDOVER_RESPONSE_TIMES * slowest, 1.0 / (HANDOVER_BOUND * ki_n)),
                   HANDOVER_MAX_S)

    def _continuing_scale(self, weights_before: dict[str, float], available: frozenset[str],
                          scale: float, kept=(), released_w: float = 0.0) -> float:
        """The factor on P_Y that keeps the DERs' total commanded power above their schedules
        continuous (docs/method.md#bumpless-switching), their limits included: ``scale``
        (the ratio of ``Σ w_d P_inst,d`` before and after) unless a DER's setpoint is at a
        limit (0 or its available power) before or after the switch; then the P_Y at which
        the new weights command the total the old ones command (over the DERs still
        available) at the output of this sample, found on the piecewise-linear sum. DERs the
        guard keeps at their power (``kept``) carry their share on; those it releases bring
        theirs (``released_w``) to the new weights."""
        p_y = self.pi.output
        if p_y == 0.0 or not self.weights or not any(d in available for d in weights_before):
            return scale            # nothing carried the output (a hold without DERs)
        total_w = released_w + sum(self._share_w(d, w, p_y) for d, w in weights_before.items()
                                   if d in available and d not in kept)
        tolerance_w = HANDOVER_TOLERANCE * sum(self._p_inst[d] for d in available)
        if abs(self._total_share_w(scale * p_y) - total_w) <= tolerance_w:
            return scale
        y = self._p_y_commanding(total_w)
        return scale if y is None else max(y / p_y, 0.0)

    def _total_share_w(self, p_y: float) -> float:
        """``Σ`` of the DERs' commanded power above their schedules at ``p_y`` by the
        current weights (Eq. 1, limited), W."""
        return sum(self._share_w(d, w, p_y) for d, w in self.weights.items())

    def _p_y_commanding(self, total_w: float) -> float | None:
        """The P_Y at which the current weights command ``total_w`` in all (W above the
        schedules), on the piecewise-linear, non-decreasing sum (bisection over its corners,
        then the line between the two around it); None if no P_Y does."""
        ids = [d for d, w in self.weights.items() if w > 0]
        gain = np.array([self.weights[d] * self._p_inst[d] for d in ids])
        sched = np.array([self._p_sched[d] for d in ids])
        most = np.array([self._available[d] for d in ids])

        def total(p_y: float) -> float:
            return float(np.sum(np.clip(p_y * gain + sched, 0.0, most) - sched))

        corners = np.unique(np.concatenate([-sched / gain, (most - sched) / gain]))
        if corners.size < 2 or not total(corners[0]) <= total_w <= total(corners[-1]):
            return None
        lo, hi = 0, corners.size - 1
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if total(corners[mid]) <= total_w:
                lo = mid
            else:
                hi = mid
        f0, f1 = total(corners[lo]), total(corners[hi])
        if f1 <= f0:
            return float(corners[lo])
        return float(corners[lo] + (total_w - f0) * (corners[hi] - corners[lo]) / (f1 - f0))

    def _design(self, entry: TableEntry) -> Design | None:
        """What ``entry`` was certified for (docs/method.md#said-when-over): the figures of
        its as-deployed loop and the overshoot limit; None for an entry without them (the
        static controller)."""
        figures = entry.figures
        values = [figures.get(k) for k in ("rise_time_s", "settling_time_s", "overshoot_pct")]
        if not all(isinstance(v, int | float) and math.isfinite(v) and v >= 0 for v in values):
            return None
        constraints = self.config.constraints
        return Design(*(float(v) for v in values), constraints.overshoot_max_pct,
                      constraints.settling_band_pct)

    def _actuator(self) -> dict:
        """What the ADN offers the level above under its entry now (docs/hierarchy.md): the
        body of an ``adn_actuator`` message, with the entry's exact closed loop."""
        from adnmesh.loopmodel.plant import plant_from_ders

        config = self.config
        ders = config.ders_by_id([d for d in self._ids if self.weights.get(d, 0.0) > 0])
        plant = plant_from_ders(ders, config.design_t_com_s, config.t_meas_s, self.weights,
                                rise_per_lag=config.rise_per_lag)
        groups = [ActuatorGroup(a.t_delay_s, a.t_lag_s, a.model, float(g))
                  for a, g in zip(plant.actuators, plant.gains_w)]
        return {"entry": self.entry_index, "ders": [d.id for d in ders],
                "capacity_w": float(sum(d.p_inst_w for d in ders)),
                "range_up_w": float(sum(d.p_inst_w - d.p_sched_w for d in ders)),
                "range_down_w": float(sum(d.p_sched_w for d in ders)),
                "kp": self.pi.kp, "ki": self.pi.ki, "t_com_s": plant.t_com_s,
                "t_meas_s": plant.t_meas_s, "groups": groups, "grid": config.grid}

    def _share_w(self, der_id: str, weight: float, p_y: float) -> float:
        """DER ``der_id``'s setpoint above its schedule by Eq. 1 with ``weight``, limited, W."""
        p_sched = self._p_sched[der_id]
        wanted = p_y * weight * self._p_inst[der_id] + p_sched
        return min(max(wanted, 0.0), self._available[der_id]) - p_sched

    def _commanded_gain(self, weights: dict[str, float], available: frozenset[str]) -> float:
        """``Σ w_d P_inst,d`` over the weighted DERs in ``available``, W per unit P_Y."""
        return sum(w * self._p_inst[d] for d, w in weights.items() if w > 0 and d in available)

    def _weights(self, entry: TableEntry, available: frozenset[str]) -> dict[str, float]:
        return {d: float(entry.w.get(d, 1.0)) for d in self._ids
                if d in available and d in entry.ders}

    def _limits(self) -> tuple[float, float]:
        low, high = output_limits(self.config, self.weights, self._available)
        if math.isnan(low):  # no weighted DER: hold the output
            return self.pi.output, self.pi.output
        return low, high
