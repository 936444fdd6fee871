"""The device simulators ``adnmesh up`` starts itself (a DER's ``plant.simulator: true``).

Each is ``python -m adnmesh device <protocol> CONFIG --der ID`` with the DER's available power
and model parameters (as the DER agent gets them), its own process and session, told to die
with ``up`` (:data:`~adnmesh.runtime.children.PARENT_ENV`). ``up`` starts them before the
agents and waits, bounded, until each accepts TCP connections on its address; it ends them by
PID after the agents (SIGTERM, then SIGKILL).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

from adnmesh.config import Config
from adnmesh.runtime.children import PARENT_ENV

__all__ = ["DeviceSimulators", "simulated_devices"]

_STOP_GRACE_S = 3.0
"""How long a simulator may take to end after SIGTERM before it is killed, s."""


def simulated_devices(config: Config) -> list:
    """The DERs whose device ``up`` simulates, in config order."""
    return [d for d in config.ders if d.plant is not None and d.plant.simulator]


class DeviceSimulators:
    """The simulator processes of one run (see the module docstring)."""

    def __init__(self, config: Config, log) -> None:
        self.config = config
        self.log = log
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, available_w: dict[str, float], model_params, timeout_s: float) -> str | None:
        """Start every simulator and wait until each listens; return why not, or None.
        ``model_params(der_id, p_avail_w)`` gives a DER's model parameters as JSON (or None)."""
        ders = simulated_devices(self.config)
        env = dict(os.environ, **{PARENT_ENV: str(os.getpid())})
        for der in ders:
            argv = [sys.executable, "-m", "adnmesh", "device", der.plant.protocol,
                    str(self.config.path), "--der", der.id]
            p_avail_w = available_w.get(der.id)
            if p_avail_w is not None:
                argv += ["--p-avail-w", repr(float(p_avail_w))]
                params = model_params(der.id, p_avail_w)
                if params is not None:
                    argv += ["--model-params", params]
            self.procs[der.id] = subprocess.Popen(argv, env=env, start_new_session=True,
                                                  stdin=subprocess.DEVNULL,
                                                  stdout=subprocess.DEVNULL)
        deadline = time.monotonic() + timeout_s
        for der in ders:
            why = self._wait_listening(der, deadline)
            if why is not None:
                return why
        if ders:
            where = ", ".join(f"{d.id} {d.plant.protocol} on {d.plant.host}:{d.plant.port}"
                              for d in ders)
            self.log(f"device simulators: {len(ders)} started ({where})")
        return None

    def _wait_listening(self, der, deadline: float) -> str | None:
        proc, plant = self.procs[der.id], der.plant
        while True:
            if proc.poll() is not None:
                return (f"the device simulator of {der.id} ended (exit code "
                        f"{proc.returncode}) before it listened on {plant.host}:{plant.port}")
            try:
                with socket.create_connection((plant.host, plant.port), timeout=0.2):
                    return None
            except OSError:
                pass
            if time.monotonic() > deadline:
                return (f"the device simulator of {der.id} did not listen on "
                        f"{plant.host}:{plant.port} within the startup timeout")
            time.sleep(0.05)

    def stop(self) -> None:
        """End every simulator by PID (SIGTERM, then SIGKILL after a grace)."""
        for proc in self.procs.values():
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + _STOP_GRACE_S
        for proc in self.procs.values():
            try:
                proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait()
