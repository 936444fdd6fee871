"""``adnmesh up``'s progress bar: sim time reached, the speed factor, the events as they happen.

A rich progress bar on stderr in sim seconds, with the speed factor (sim s per wall s, over
the last few seconds), and above it one line per event of the run (gain switches, faults,
availability changes, DER modes; the texts ``replay`` and ``inspect`` use, from the live
view's :class:`~adnmesh.results.series.LiveCollector`). Only for a terminal, or when asked.
"""

from __future__ import annotations

import time
from collections import deque

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from adnmesh.results.rules import Event

__all__ = ["SHOWN_EVENTS", "RunProgress", "event_line", "speed_factor"]

SHOWN_EVENTS = frozenset({"gain_switch", "fault", "availability", "der_available", "der_mode"})
"""Event kinds printed above the bar (and agents' warnings and errors other than overruns,
which ``up`` reports itself)."""


def event_line(event: Event) -> str | None:
    """The line printed for ``event`` (``t = 12.000 s  text``), or None if it is not shown."""
    shown = event.kind in SHOWN_EVENTS or (
        event.kind == "event" and event.level in ("WARN", "ERROR")
        and event.data.get("kind") != "overrun")
    return f"t = {event.t_ns / 1e9:9.3f} s  {event.text}" if shown else None


def speed_factor(samples: deque) -> float | None:
    """Sim seconds per wall second over ``samples`` of (wall s, sim ns); None with too few."""
    if len(samples) < 2 or samples[-1][0] <= samples[0][0]:
        return None
    (w0, s0), (w1, s1) = samples[0], samples[-1]
    return (s1 - s0) / 1e9 / (w1 - w0)


class RunProgress:
    """The bar and the event lines (use as a context manager; thread-safe).

    Parameters
    ----------
    console : rich.console.Console
        Where to draw (stderr).
    end_ns : int
        The scenario's end, ns.
    window_s : float
        The speed factor is measured over this much wall time, s.
    """

    def __init__(self, console: Console, end_ns: int, window_s: float = 5.0) -> None:
        self.end_ns, self.window_s = end_ns, window_s
        self._samples: deque = deque()
        self._progress = Progress(TextColumn("sim"), BarColumn(),
                                  TextColumn("{task.fields[reached]}"),
                                  TextColumn("{task.fields[speed]}"), TimeElapsedColumn(),
                                  console=console, transient=False)
        self._task = self._progress.add_task("run", total=end_ns / 1e9, reached="",
                                             speed="")

    def __enter__(self) -> RunProgress:
        self._progress.start()
        return self

    def __exit__(self, *exc) -> None:
        self._progress.stop()

    def update(self, reached_ns: int) -> None:
        """The run reached ``reached_ns`` of sim time."""
        now = time.monotonic()
        self._samples.append((now, reached_ns))
        while self._samples and self._samples[0][0] < now - self.window_s:
            self._samples.popleft()
        factor = speed_factor(self._samples)
        self._progress.update(
            self._task, completed=reached_ns / 1e9,
            reached=f"{reached_ns / 1e9:.1f} / {self.end_ns / 1e9:g} s",
            speed="" if factor is None else f"x{factor:.3g} sim s per wall s")

    def events(self, events: list[Event]) -> None:
        """Print the shown ones of ``events`` above the bar."""
        for event in events:
            line = event_line(event)
            if line is not None:
                self._progress.console.print(line, markup=False, highlight=False)
