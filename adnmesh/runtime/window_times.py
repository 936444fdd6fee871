"""When an agent's sim-clock windows ran, in wall time: the stage timeline of a run.

On the sim clock each agent runs the windows the clock grants it, and a window of one agent
often waits for another's (the measurement for the DERs', the CPFC for the measurement's).
Where a run's wall time goes -- the windows, or the hand-overs between them -- shows in when
each window's grant arrived, when it began and when it ended.

With the environment variable :data:`ENV` set to a directory, every agent process notes
these three times of each window (``time.monotonic_ns``: one clock for every process of the
machine) and the CPU time its thread spent in the window, and writes them when its run ends
(the goodbye said, or killed by an injected fault) to ``<directory>/<agent>.<pid>.json``
(``/`` in the agent's id as ``.``): ``{"agent": ..., "windows": [[until_ns, granted_ns,
began_ns, ended_ns, cpu_ns], ...]}``, ``until_ns`` the sim time the window was granted to,
``granted_ns`` null for a window whose grant was not seen. In scale mode a hosted agent's
grant arrives when its host hands it over, after the windows of the agents before it in the
same sample. ``benchmarks/bench_runtime.py --timeline`` reads them. Unset (the default),
nothing is noted.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

__all__ = ["ENV", "WindowTimes"]

ENV = "ADNMESH_WINDOW_TIMES"
"""The environment variable that names the directory the window times go to."""


class WindowTimes:
    """The windows of one agent process (see the module docstring); not thread-safe (the
    agent process calls it with its lock held)."""

    def __init__(self, agent: str, directory: Path) -> None:
        self.agent = agent
        self.directory = Path(directory)
        self.windows: list[tuple[int, int | None, int, int, int]] = []
        self._granted: dict[int, int] = {}    # until_ns -> when its grant arrived, ns

    @classmethod
    def from_env(cls, agent: str) -> WindowTimes | None:
        """The times of ``agent`` if :data:`ENV` names a directory, else None."""
        directory = os.environ.get(ENV)
        return cls(agent, Path(directory)) if directory else None

    def granted(self, until_ns: int) -> None:
        """The grant to ``until_ns`` arrived now."""
        self._granted.setdefault(until_ns, time.monotonic_ns())

    def ran(self, until_ns: int, began_ns: int, ended_ns: int, cpu_ns: int) -> None:
        """The window to ``until_ns`` ran from ``began_ns`` to ``ended_ns`` (monotonic ns),
        ``cpu_ns`` of its thread's CPU time."""
        self.windows.append((until_ns, self._granted.pop(until_ns, None), began_ns, ended_ns,
                             cpu_ns))

    def write(self) -> Path:
        """Write the windows noted so far (whole or not at all: a temporary file renamed);
        return the file."""
        path = self.directory / f"{self.agent.replace('/', '.')}.{os.getpid()}.json"
        partial = path.with_suffix(".part")
        partial.write_text(json.dumps({"agent": self.agent, "windows": self.windows}))
        os.replace(partial, path)
        return path
