"""Several agents in one process, on one Zenoh session: the scale mode of ``adnmesh up``.

With ``runtime.ders_per_process`` above 1, ``up`` starts one DER program per group of that many
DERs (``python -m adnmesh.agents.der CONFIG --der A --der B ...``), and the program serves them
here. Each agent stays what it is in a process of its own -- an
:class:`~adnmesh.runtime.process.AgentProcess` with its node, its lock, its liveliness token
and its clock protocol -- so the messages of a run, and its recording, are the same; what the
agents share is the process, the session and the subscribers:

- the host declares **one subscriber per key** and hands every sample to each agent that takes
  that key (all the hosted DERs take the CPFC's ``P_Y``, the faults and the clock's start and
  stop: one subscriber, and one Zenoh delivery thread, instead of one per agent), and one
  liveliness subscriber for ``up``;
- the agents' gates share one decode (:class:`~adnmesh.wire.shared_decode.SharedDecode`): a
  sample every DER takes is parsed and validated once, and each gate applies its own accept
  rules to that message;
- each agent runs in a thread of its own until the end of the run, then says its goodbye;
- SIGTERM or SIGINT stops every agent of the process.

A process is a failure domain: an internal error in one agent's code ends the process, and
``up`` counts every agent in it as lost. An injected kill ends one agent only: it withdraws its
liveliness and takes nothing more, the others go on (its restart is a process of its own). The
secure profile gives every agent its own certificate, so hosting is for the open profile.
"""

from __future__ import annotations

import signal
import threading

import zenoh

from adnmesh.runtime.process import AgentProcess, die_with_parent
from adnmesh.sim.node import Node
from adnmesh.wire.envelope import split_frame
from adnmesh.wire.keys import Keys
from adnmesh.wire.shared_decode import SharedDecode

__all__ = ["serve_hosted"]


def _fan_out(callbacks: list):
    """One Zenoh callback that hands a sample to every callback of ``callbacks`` in turn."""
    if len(callbacks) == 1:
        return callbacks[0]

    def deliver(sample: zenoh.Sample) -> None:
        for callback in callbacks:
            callback(sample)
    return deliver


def _on_grants(agents: list[AgentProcess], keys: Keys):
    """The Zenoh callback of the process's grants, one sample from the sim clock per batch
    (:meth:`~adnmesh.wire.keys.Keys.host_grants`): each grant to its agent, as if it had come
    on the agent's own key; a sample whose names and grants do not pair up, or that names an
    agent the process does not host, is rejected and counted."""
    by_id = {agent.agent: agent for agent in agents}

    def deliver(sample: zenoh.Sample) -> None:
        names = [] if sample.attachment is None else \
            sample.attachment.to_bytes().decode("utf-8", "replace").split("\n")
        payloads = split_frame(sample.payload.to_bytes())
        if len(names) != len(payloads) or not set(names) <= by_id.keys():
            agents[0].samples["clock_in"] += 1
            agents[0].reject(keys.host_grants(agents[0].agent),
                             f"grant sample: {len(payloads)} grant(s) for the agents named "
                             f"({len(names)}), or an agent not hosted here")
            return
        for i, (name, payload) in enumerate(zip(names, payloads)):
            by_id[name].take_grant(payload, counted=i == 0)
    return agents[0].guarded(deliver)


def serve_hosted(session: zenoh.Session, nodes: list[Node], grid: str) -> int:
    """Run the agents of ``nodes`` on ``session`` until the run ends (see the module
    docstring); return the exit code (0)."""
    die_with_parent()
    agents = [AgentProcess(session, node, grid, hosted=True) for node in nodes]
    shared = SharedDecode()
    for node in nodes:
        node.gate.decoder = shared

    def on_signal(signum, frame) -> None:   # no lock in a handler: each wakes within 1 s
        for agent in agents:
            agent.stop = agent.stop or signal.Signals(signum).name

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    handles = []
    try:
        by_key: dict[str, list] = {}
        for agent in agents:
            for key, callback in agent.routes().items():
                by_key.setdefault(key, []).append(callback)
        handles = [session.declare_subscriber(key, _fan_out(callbacks))
                   for key, callbacks in by_key.items()]
        keys = Keys(grid)
        handles.append(session.declare_subscriber(keys.host_grants(agents[0].agent),
                                                  _on_grants(agents, keys)))
        for agent in agents:
            agent.startup(subscribe=False)
        handles.append(session.liveliness().declare_subscriber(
            Keys(grid).liveliness("up"), _fan_out([a.on_up_alive for a in agents]),
            history=True))
        threads = [threading.Thread(target=agent.run_to_end, name=agent.agent, daemon=True)
                   for agent in agents]
        for thread in threads:
            thread.start()
        for thread in threads:
            while thread.is_alive():      # in slices: the signal handler runs in between
                thread.join(1.0)
    finally:
        for handle in reversed(handles):
            handle.undeclare()
        for agent in agents:
            agent.close()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return 0
