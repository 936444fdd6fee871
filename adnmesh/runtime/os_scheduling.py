"""How an agent process of a realtime run asks the OS for timely wake-ups.

A realtime agent sleeps until its next event and must wake on time (its delivery error,
:mod:`adnmesh.sim.latency`). Three things of the process decide how late it wakes, beside the
machine's load:

- **priority** (:data:`PRIORITIES`): ``off`` leaves the process as it is; ``nice`` raises its
  CFS weight (``os.nice``, :data:`NICE`), so that on a shared machine the run's processes get a
  core before the other jobs' ones; ``fifo`` gives every thread the real-time policy
  ``SCHED_FIFO`` (priority :data:`FIFO_PRIORITY`): it preempts every ordinary process as soon as
  it wakes. Linux's real-time throttling (``kernel.sched_rt_runtime_us``, 95 % by default) keeps
  a share of each core for the others, so a run that cannot keep up does not freeze the
  machine. Both need privileges (root or ``CAP_SYS_NICE``); without them the process goes on
  as it is and :func:`raise_priority` says so in one line: never a failure.
- **timer slack** (``prctl(PR_SET_TIMERSLACK)``): Linux may delay a timed wait by up to 50 µs
  to batch wake-ups; a realtime agent asks for :data:`TIMER_SLACK_NS`. (Threads under
  ``SCHED_FIFO`` have no slack anyway.)
- **the GIL switch interval** (``sys.setswitchinterval``): a thread that wants the GIL while
  another runs Python waits up to this long (5 ms by default) -- the Zenoh callback that brings
  a message, or the main thread woken by it. A realtime agent sets :data:`SWITCH_INTERVAL_S`.

- **the garbage collector**: a full (generation 2) collection walks every object the process
  holds, about 70 ms for an agent's 60,000 objects after its imports on this machine, and in
  that time the process answers nothing. :func:`freeze_heap` moves what startup built into the
  collector's permanent generation (``gc.freeze``), so that a collection walks only what the run
  itself keeps (microseconds). Every agent process and ``up`` do it once startup is done.

:class:`SpinPlan` is the last part of a wake-up: sleep until ``spin`` before the event, then
poll the clock (the sleep's own error, the scheduler's wake-up latency, is then paid before
the event instead of after it).
"""

from __future__ import annotations

import ctypes
import gc
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["FIFO_PRIORITY", "NICE", "PRIORITIES", "PRIORITY_ENV", "SPIN_ENV", "SPIN_NS",
           "SWITCH_INTERVAL_S", "TIMER_SLACK_NS", "PriorityResult", "SpinPlan",
           "freeze_heap", "raise_priority", "spin_ns_from_env", "tighten_timers"]

PRIORITIES = ("off", "nice", "fifo")
"""The priorities a realtime run may ask for (``adnmesh up --rt-priority``)."""

PRIORITY_ENV = "ADNMESH_RT_PRIORITY"
"""Environment variable through which ``up`` hands the priority to its agent processes."""

SPIN_ENV = "ADNMESH_RT_SPIN_US"
"""Environment variable: the spin of :class:`SpinPlan`, µs (default :data:`SPIN_NS`)."""

NICE = -10
"""The nice value of priority ``nice`` (ordinary processes have 0: about 10x their weight)."""

FIFO_PRIORITY = 10
"""The ``SCHED_FIFO`` priority of priority ``fifo`` (1-99; low: kernel threads stay above)."""

TIMER_SLACK_NS = 1_000
"""The timer slack a realtime agent asks for, ns (Linux's default: 50 µs)."""

SWITCH_INTERVAL_S = 2e-4
"""The GIL switch interval of a realtime agent, s (Python's default: 5 ms)."""

SPIN_NS = 0
"""The default spin before an event, wall ns (see :class:`SpinPlan`; measured in
docs/performance.md#realtime-clock)."""

_PR_SET_TIMERSLACK = 29


@dataclass(frozen=True)
class PriorityResult:
    """What :func:`raise_priority` did.

    Attributes
    ----------
    granted : bool
        The priority asked for is in force (always true for ``off``).
    text : str
        One line saying what was done or why not ("" for ``off``).
    """

    granted: bool
    text: str


def raise_priority(priority: str, threads: Callable[[], list[int]] | None = None,
                   setscheduler=None, setpriority=None) -> PriorityResult:
    """Give this process the ``priority`` of :data:`PRIORITIES` (see the module docstring).

    Linux keeps both the nice value and the policy per thread: every thread listed by
    ``threads`` is changed (default: those of this process, from ``/proc/self/task``); a
    thread started later inherits them from its creator. ``setscheduler`` and ``setpriority``
    stand in for :func:`os.sched_setscheduler` and :func:`os.setpriority` in tests. Never
    raises for want of privileges: the result says so.
    """
    if priority not in PRIORITIES:
        raise ValueError(f"unknown realtime priority {priority!r} (one of "
                         f"{', '.join(PRIORITIES)})")
    if priority == "off":
        return PriorityResult(True, "")
    try:
        tids = (threads or _own_threads)()
        if priority == "nice":
            setpriority = setpriority or os.setpriority
            for tid in tids:
                setpriority(os.PRIO_PROCESS, tid, NICE)
            return PriorityResult(True, f"nice {NICE}")
        setscheduler = setscheduler or os.sched_setscheduler
        param = os.sched_param(FIFO_PRIORITY)
        for tid in tids:
            setscheduler(tid, os.SCHED_FIFO, param)
        return PriorityResult(True, f"SCHED_FIFO priority {FIFO_PRIORITY}")
    except (OSError, AttributeError) as exc:   # EPERM; no such call on this OS
        why = getattr(exc, "strerror", None) or str(exc)
        return PriorityResult(False, f"realtime priority {priority!r} not granted ({why}); "
                                     "running at the ordinary priority")


def _own_threads() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [0]     # the calling thread


def tighten_timers() -> None:
    """Timer slack :data:`TIMER_SLACK_NS` (Linux) and GIL switch interval
    :data:`SWITCH_INTERVAL_S` for this process (best effort: nothing on another OS)."""
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_TIMERSLACK, TIMER_SLACK_NS, 0, 0, 0)
        except (OSError, AttributeError):
            pass


def spin_ns_from_env(environ=os.environ) -> int:
    """The spin of :class:`SpinPlan` from :data:`SPIN_ENV` (µs), else :data:`SPIN_NS`; a bad
    value is ignored."""
    try:
        return max(0, int(float(environ[SPIN_ENV]) * 1e3))
    except (KeyError, ValueError):
        return SPIN_NS


@dataclass(frozen=True)
class SpinPlan:
    """Sleep, then spin, until a wall-clock instant.

    Parameters
    ----------
    spin_ns : int
        How long before the instant the sleep ends and polling begins, wall ns (0: sleep all
        the way).
    now_ns : callable
        The monotonic clock, ns (:func:`time.monotonic_ns`; a fake one in tests).
    """

    spin_ns: int
    now_ns: Callable[[], int]

    def sleep_s(self, target_ns: int) -> float:
        """How long to sleep before spinning toward ``target_ns`` (monotonic ns), s (<= 0:
        spin, or the instant has come)."""
        return (target_ns - self.spin_ns - self.now_ns()) * 1e-9

    def spin(self, target_ns: int, interrupted: Callable[[], bool] = lambda: False) -> bool:
        """Poll the clock until ``target_ns`` (at most ``spin_ns`` plus one poll); return
        whether the instant was reached (False: ``interrupted`` turned true first)."""
        now = self.now_ns
        if target_ns - now() > self.spin_ns:     # not within the spin: the caller sleeps
            return False
        while now() < target_ns:
            if interrupted():
                return False
        return True


def freeze_heap() -> int:
    """Collect once, then exclude every object alive now from later collections
    (``gc.freeze``): the modules, the config, the agent and its tables live until the process
    ends, and walking them in every full collection would stall the process for tens of ms.
    Returns how many objects were frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()
