"""Tests of adnmesh.sim (bus-free): ICT links, topology, the sim clock's coordinator, the node
(event order, validation before counting, rejections per key and reason) and the in-process
runner (determinism, agreement with the numerics, bumpless switching)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from adnmesh.config import Config, LinkSettings, Outage, load_config
from adnmesh.control.base import Agent, Outgoing
from adnmesh.control.cpfc_controller import GainSchedule
from adnmesh.control.registry import build_agent
from adnmesh.loopmodel.plant import plant_from_ders
from adnmesh.sim.clock import ClockError, Coordinator, Report
from adnmesh.sim.links import Impairment, Link, LinkParams, stream_seed
from adnmesh.sim.local import run_local
from adnmesh.sim.node import Node
from adnmesh.sim.topology import Topology
from adnmesh.loopmodel.step_response import simulate_step
from adnmesh.tuning.table import SchedulingTable, TableEntry
from adnmesh.wire.envelope import decode, encode
from adnmesh.wire.messages import DERState
from adnmesh.wire.units import ns

from lookahead_reference import coordinator_sources_reference, lookahead_reference

KP2, KI2 = 5e-8, 1.92e-7      # two WTs: stable, disk margin 1.51, overshoot 0 % (checked below)
KP1, KI1 = 1e-7, 3.84e-7      # one WT: the same loop (gains scale with 1 / P_inst)


@pytest.fixture(scope="module")
def config(configs_dir: Path) -> Config:
    return load_config(configs_dir / "examples" / "runtime-step.yaml")


@pytest.fixture(scope="module")
def schedule(config: Config) -> GainSchedule:
    table = SchedulingTable(config.sha256, {}, "test", config.der_ids())
    table.add(TableEntry(("SGen1", "SGen2"), KP2, KI2, {"SGen1": 1.0, "SGen2": 1.0}))
    table.add(TableEntry(("SGen1",), KP1, KI1, {"SGen1": 1.0}))
    return GainSchedule(config, table, on_demand=False)


def with_runtime(config: Config, **changes) -> Config:
    return config.model_copy(update={"runtime": config.runtime.model_copy(update=changes)})


# --- ICT links ----------------------------------------------------------------------------------


def test_link_delay_and_outage() -> None:
    link = Link(LinkParams("l", delay_ns=100, outages_ns=((1000, 2000),)), seed=1, sender="a")
    assert [link.transmit(t) for t in (0, 999, 1000, 1999, 2000)] == [100, 1099, None, None, 2100]
    assert link.lost == 2


def test_link_jitter_is_bounded_fifo_and_seeded() -> None:
    params = LinkParams("l", delay_ns=1_000, jitter_ns=5_000)
    a, b = Link(params, 3, "x"), Link(params, 3, "x")
    times = [a.transmit(t * 100) for t in range(2000)]
    assert times == [b.transmit(t * 100) for t in range(2000)]
    # FIFO holds a message back to the one before it, which was sent earlier with the same
    # bound: every delivery stays within the sender's delay + jitter
    assert all(t * 100 + 1_000 <= d <= t * 100 + 6_000 for t, d in enumerate(times))
    assert times == sorted(times)                                     # FIFO
    unordered = Link(dataclasses.replace(params, fifo=False), 3, "x")
    free = [unordered.transmit(t * 100) for t in range(2000)]
    assert free != sorted(free)
    assert all(t * 100 + 1_000 <= d < t * 100 + 6_000 for t, d in enumerate(free))
    three, four = Link(params, 3, "x"), Link(params, 4, "x")
    assert [three.transmit(t * 10_000) for t in range(20)] != \
        [four.transmit(t * 10_000) for t in range(20)]                # another seed, other draws
    assert stream_seed(3, "l", "x") != stream_seed(3, "l", "y")


def test_link_loss_rate_matches_its_probability() -> None:
    link = Link(LinkParams("l", delay_ns=0, loss=0.2), seed=11, sender="x")
    lost = sum(link.transmit(t) is None for t in range(20_000))
    assert lost == link.lost
    assert abs(lost / 20_000 - 0.2) < 4 * math.sqrt(0.2 * 0.8 / 20_000)


def test_link_params_from_settings() -> None:
    params = LinkParams.from_settings("x", LinkSettings(jitter_s=0.001, loss=0.1,
                                                        outages=(Outage(t_s=1.0,
                                                                        duration_s=0.5),)), 0.1)
    assert params == LinkParams("x", 100_000_000, 1_000_000, 0.1, True,
                                ((1_000_000_000, 1_500_000_000),))
    with pytest.raises(ValueError, match="no delay"):
        LinkParams.from_settings("x", LinkSettings())


# --- topology and clock ------------------------------------------------------------------------


def test_topology_routes_and_lookahead(config: Config) -> None:
    topo = Topology.from_config(config)
    keys = topo.keys
    assert topo.agents == ("cpfc", "measurement", "availability", "der/SGen1", "der/SGen2")
    assert topo.receivers[keys.of("p_y")] == ("der/SGen1", "der/SGen2")
    assert topo.subscriptions["measurement"] == (
        keys.of("der_state", "SGen1"), keys.of("der_state", "SGen2"), keys.of("fault"))
    assert topo.receivers[keys.of("heartbeat", "SGen1")] == ("availability", "cpfc")
    assert topo.link("cpfc", keys.of("p_y")).delay_ns == ns(config.t_com_s)
    look = topo.lookahead_ns
    assert look[("der/SGen1", "measurement")] == 0
    assert look[("cpfc", "measurement")] == ns(0.1)                    # via a DER
    assert look[("cpfc", "cpfc")] == ns(0.2)                            # the control loop
    assert look[("der/SGen1", "der/SGen2")] == ns(0.2)
    assert look[("measurement", "availability")] == ns(0.3)         # via CPFC and a DER


def _every_config(configs_dir: Path) -> list[Path]:
    return sorted(configs_dir.glob("*.yaml")) + sorted(configs_dir.glob("examples/*.yaml"))


def test_lookahead_is_the_floyd_warshall_dict_on_every_config(configs_dir: Path) -> None:
    for path in _every_config(configs_dir):
        topo = Topology.from_config(load_config(path))
        want = lookahead_reference(topo.agents, topo.links, topo.receivers)
        assert list(topo.lookahead_ns.items()) == list(want.items()), path  # order too
        assert all(type(d) is int for d in topo.lookahead_ns.values())
        assert Coordinator(topo, ns(1.0))._sources == \
            coordinator_sources_reference(topo.agents, topo.lookahead_ns), path
        assert topo.subscriptions == {a: tuple(k for k, to in topo.receivers.items() if a in to)
                                      for a in topo.agents}, path


@pytest.mark.parametrize("seed", range(40))
def test_lookahead_is_the_floyd_warshall_dict_on_random_graphs(seed: int) -> None:
    """Random message graphs: zero delays, parallel keys of different delays, self-loops,
    unreachable agents, broadcast keys; delays up to an hour in ns."""
    from adnmesh.sim import topology

    rng = np.random.default_rng(seed)
    agents = tuple(f"a{i}" for i in range(int(rng.integers(1, 25))))
    links, receivers = {}, {}
    for k in range(int(rng.integers(0, 3 * len(agents) + 1))):
        key = f"k{k}"
        delay = int(rng.choice([0, 1, 10**8, int(rng.integers(0, 36 * 10**11))]))
        links[(str(rng.choice(agents)), key)] = LinkParams("l", delay_ns=delay)
        size = int(rng.integers(0, len(agents) + 1))
        receivers[key] = tuple(str(a) for a in rng.choice(agents, size, replace=False))
    got = topology._lookahead(agents, links, receivers)
    want = lookahead_reference(agents, links, receivers)
    assert list(got.items()) == list(want.items())
    assert all(type(d) is int for d in got.values())


@pytest.mark.parametrize("seed", range(30))
def test_the_coordinators_lbts_search_stops_early_and_finds_the_minimum(seed: int) -> None:
    """The LBTS of every agent equals the full minimum over its sources (min_p E_p +
    lookahead(p, b), bounded by the horizon) for E with infinities, ties, far and near
    times, on random message graphs: the search stops at the first source too far away."""
    from adnmesh.sim import topology

    rng = np.random.default_rng(seed)
    agents = tuple(f"a{i}" for i in range(int(rng.integers(1, 30))))
    links, receivers = {}, {}
    for k in range(int(rng.integers(0, 3 * len(agents) + 1))):
        key = f"k{k}"
        delay = int(rng.choice([0, 1, 10**8, int(rng.integers(0, 10**10))]))
        links[(str(rng.choice(agents)), key)] = LinkParams("l", delay_ns=delay)
        size = int(rng.integers(0, len(agents) + 1))
        receivers[key] = tuple(str(a) for a in rng.choice(agents, size, replace=False))
    lookahead = topology._lookahead(agents, links, receivers)
    coordinator = Coordinator.__new__(Coordinator)
    index = {a: i for i, a in enumerate(agents)}
    sources = [[] for _ in agents]
    for (p, q), d in lookahead.items():
        sources[index[q]].append((index[p], d))
    coordinator._sources = [tuple(sorted(s, key=lambda pd: (pd[1], pd[0]))) for s in sources]
    for _ in range(20):
        e = [rng.choice([math.inf, -math.inf, int(rng.integers(0, 10**10)), 5 * 10**9])
             for _ in agents]
        e = [x if math.isinf(x) else int(x) for x in e]
        horizon = int(rng.choice([10**10, 2 * 10**10, 3 * 10**9]))
        e_min = min(e)
        for b in range(len(agents)):
            want = min([horizon] + [e[p] + d for p, d in sources[b]])
            assert coordinator._lbts(b, e, e_min, horizon) == want


def test_topology_of_1000_ders_takes_seconds(tmp_path: Path, configs_dir: Path) -> None:
    """The documented maximum, 1,000 DERs: the topology (every agent computes it, and up
    before it starts any) and the coordinator in seconds (the Floyd-Warshall loop and the
    coordinator's per-receiver pass took minutes, cubic)."""
    import subprocess
    import sys
    import yaml

    doc = yaml.safe_load((configs_dir / "examples" / "runtime-step.yaml").read_text())
    der = doc["ders"][0]
    doc["ders"] = [{**der, "id": f"D{i:04d}", "sgen": f"sgen {i}"} for i in range(1000)]
    doc["scenario"]["availability"] = []
    path = tmp_path / "adn-1000.yaml"
    path.write_text(yaml.safe_dump(doc))
    code = ("import sys, time; from adnmesh.config import load_config; "
            "from adnmesh.sim.topology import Topology; from adnmesh.sim.clock import Coordinator; "
            "t = time.perf_counter(); top = Topology.from_config(load_config(sys.argv[1])); "
            "Coordinator(top, 10**9); print(len(top.agents), len(top.lookahead_ns), "
            "time.perf_counter() - t)")
    done = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True,
                          text=True, timeout=60, check=True)
    agents, pairs, _ = done.stdout.split()
    assert (int(agents), int(pairs)) == (1003, 1003 ** 2)


def test_coordinator_starts_one_stage_and_rejects_protocol_errors(config: Config) -> None:
    topo = Topology.from_config(config)
    clock = Coordinator(topo, end_ns=ns(1.0))
    for agent in topo.agents:
        assert clock.on_report(Report(agent, 0, 0, {})) == []
    # nobody can make a full window (one loop: 0.2 s) yet: one stage goes first, the DERs,
    # as far as the CPFC's T_com allows; the measurement waits for them (zero-delay path)
    assert {(g.agent, g.until_ns) for g in clock.start()} == {("der/SGen1", ns(0.1)),
                                                                ("der/SGen2", ns(0.1))}
    # a first report again (an agent repeats it until the start: one can be lost) is taken
    assert clock.on_report(Report("measurement", 0, 0, {})) == []
    with pytest.raises(ClockError, match="second report"):       # one that sent something is not
        clock.on_report(Report("measurement", 0, 0, {"adn/x/measurement/p_ip": (1, 5)}))
    with pytest.raises(ClockError, match="granted only to"):     # under a grant never given:
        clock.on_report(Report("der/SGen1", ns(0.1), 0, {}, granted_ns=ns(5)))   # a forger's
    clock.on_report(Report("der/SGen1", ns(0.1), 0, {}, granted_ns=ns(0.1)))
    with pytest.raises(ClockError, match="second report"):       # after a grant: one report
        clock.on_report(Report("der/SGen1", ns(0.1), 0, {}))
    with pytest.raises(ClockError, match="unknown agent"):
        clock.on_report(Report("grid", 0, 0, {}))


def drive(clock: Coordinator, grants, sent=lambda grant: {}, stop=lambda grant: False):
    """Answer every grant with a report (next event = end of the window); return the grants."""
    log, queue = [], list(grants)
    while queue:
        grant = queue.pop(0)
        log.append(grant)
        if stop(grant):
            break
        queue += clock.on_report(Report(grant.agent, grant.until_ns, grant.expect,
                                        sent(grant)))
    return log


def test_coordinator_counts_messages_in_flight(config: Config) -> None:
    topo = Topology.from_config(config)
    keys = topo.keys
    clock = Coordinator(topo, end_ns=ns(1.0))
    for agent in topo.agents:
        clock.on_report(Report(agent, 0, 0, {}))

    def sent(grant):  # every DER window sends 10 states, the first delivered at its start
        if grant.agent.startswith("der/"):
            return {keys.of("der_state", grant.agent[4:]): (10, grant.until_ns - ns(0.1))}
        return {}

    log = drive(clock, clock.start(), sent, stop=lambda g: g.agent == "measurement")
    meas = log[-1]
    assert meas.agent == "measurement" and meas.expect == 20 and meas.until_ns == ns(0.1)
    # a run stalled here says what the measurement was granted and waits for
    assert clock.describe_busy() == [
        "measurement (granted to 0.1 s once it has 20 messages; 0 at its report before)"]


def test_coordinator_settles_into_full_windows(config: Config) -> None:
    """After the start, every agent advances a whole loop (T_com + T_meas) per grant."""
    topo = Topology.from_config(config)
    clock = Coordinator(topo, end_ns=ns(10.0))
    for agent in topo.agents:
        clock.on_report(Report(agent, 0, 0, {}))
    log = drive(clock, clock.start())
    assert clock.finished
    windows = {}
    for grant in log:
        windows.setdefault(grant.agent, []).append(grant.until_ns)
    for agent in ("cpfc", "measurement", "der/SGen1"):
        steps = np.diff(windows[agent])
        assert np.all(steps[3:-1] == ns(0.2)), (agent, steps)


def test_coordinator_refuses_to_start_before_every_report(config: Config) -> None:
    clock = Coordinator(Topology.from_config(config), end_ns=10)
    clock.on_report(Report("cpfc", 0, 0, {}))
    with pytest.raises(ClockError, match="no report yet"):
        clock.start()


def test_coordinator_drops_a_repeated_first_report_that_crossed_a_grant(config: Config) -> None:
    """An agent repeats its first report until the start; one that arrives after the agent's
    first grant (it says granted_ns 0, behind that grant) is stale and changes nothing, while
    a report without granted_ns (in-process) is taken as the grant's report."""
    topo = Topology.from_config(config)
    clock = Coordinator(topo, end_ns=ns(1.0))
    for agent in topo.agents:
        clock.on_report(Report(agent, 0, 0, {}, granted_ns=0))
    grants = {g.agent: g for g in clock.start()}
    agent = next(a for a, g in grants.items() if g.until_ns > 0)
    taken = clock.reports_received
    assert clock.on_report(Report(agent, 0, 0, {}, granted_ns=0)) == []
    assert agent in clock.busy() and clock.reports_received == taken
    clock.on_report(Report(agent, 0, 0, {}))                      # taken as the grant's report
    assert clock.reports_received == taken + 1


# --- node ---------------------------------------------------------------------------------------


class Ticker(Agent):
    """A minimal agent: a timer every 10 ns that sends a p_ip; records what it gets."""

    agent_id = "measurement"

    def __init__(self, key: str) -> None:
        self.key, self.next, self.seen = key, 0, []

    def next_timer_ns(self):
        return self.next

    def on_timer(self, t_ns):
        self.next += 10
        self.seen.append(("timer", t_ns))
        return [Outgoing(self.key, {"p_ip_w": float(t_ns)})]

    def on_message(self, t_ns, message):
        self.seen.append((message.src[4:], t_ns, message.p_w))
        return []


def state(der: str, t: int, seq: int, p_w: float = 1.0, src: str | None = None) -> bytes:
    return encode(DERState(1, "der_state", src or f"der/{der}", seq, t, t, p_w, 1.0, "control"))


def test_node_orders_messages_before_timers(config: Config) -> None:
    topo = Topology.from_config(config)
    keys = topo.keys
    agent = Ticker(keys.of("p_ip"))
    node = Node(agent, topo, seed=0)
    node.receive(keys.of("der_state", "SGen2"), state("SGen2", 10, 0))
    node.receive(keys.of("der_state", "SGen1"), state("SGen1", 10, 0))
    out = node.advance(21)
    assert agent.seen == [("timer", 0), ("SGen1", 10, 1.0), ("SGen2", 10, 1.0),
                          ("timer", 10), ("timer", 20)]
    assert [decode(k, p).t_deliver_ns for k, p in out] == [ns(0.1), ns(0.1) + 10,
                                                           ns(0.1) + 20]
    report = node.report()
    assert report.sent == {keys.of("p_ip"): (3, ns(0.1))} and report.next_ns == 30
    assert report.received == 2
    assert node.report().sent == {}


def test_node_rejects_before_counting_per_key_and_reason(config: Config) -> None:
    """Only genuine messages count toward what the clock expects; everything else is
    counted per key and reason and never reaches the agent."""
    topo = Topology.from_config(config)
    keys = topo.keys
    agent = Ticker(keys.of("p_ip"))
    node = Node(agent, topo, seed=0)
    k1 = keys.of("der_state", "SGen1")
    node.receive(k1, state("SGen1", 10, 3))
    node.receive(k1, b"garbage")
    node.receive(k1, state("SGen1", 10, 4, src="der/SGen2"))       # another DER's name
    node.receive(k1, state("SGen1", 10, 3, p_w=9.0))                # replay of (10, 3)
    node.receive(keys.of("p_y"), state("SGen1", 10, 5))             # not subscribed
    node.receive(k1, state("SGen1", 10, 2 ** 70))                   # seq out of range
    node.receive(k1, state("SGen1", 10, 4, p_w=3e6))                # beyond its 2 MW
    assert node.counts.received == 1
    assert node.counts.rejected == {
        k1: {"malformed": 1, "wrong_sender": 1, "replayed": 1, "invalid": 1, "implausible": 1},
        keys.of("p_y"): {"not_subscribed": 1}}
    node.advance(21)
    assert agent.seen[1:] == [("SGen1", 10, 1.0), ("timer", 10), ("timer", 20)]
    node.receive(k1, state("SGen1", 9, 9))                  # sent before one it processed
    node.receive(k1, state("SGen1", 15, 0))                         # genuine but in the past
    assert node.counts.received == 2 and node.counts.rejected[k1]["past"] == 1
    assert node.counts.rejected[k1]["replayed"] == 2
    assert node.counts.rejected_total == 8


def test_a_forged_future_message_cannot_shut_out_the_genuine_sender(config: Config) -> None:
    """A message with a far-future send time and a huge seq (someone holding the DER's key)
    is held until its time, not taken as the key's latest: the DER's genuine messages that
    follow are still taken (the gate compares with what the node processed)."""
    topo = Topology.from_config(config)
    agent = Ticker(topo.keys.of("p_ip"))
    node = Node(agent, topo, seed=0)
    k1 = topo.keys.of("der_state", "SGen1")
    node.receive(k1, state("SGen1", ns(300), 10 ** 9))              # the forged one
    for i in range(3):
        node.receive(k1, state("SGen1", 10 + 10 * i, i))            # the DER's own
    assert node.counts.received == 4 and node.counts.rejected == {}
    node.advance(31)
    assert [s for s in agent.seen if s[0] == "SGen1"] == [("SGen1", 10, 1.0), ("SGen1", 20, 1.0),
                                                           ("SGen1", 30, 1.0)]
    node.receive(k1, state("SGen1", 30, 2))                         # a replay of one done
    assert node.counts.rejected == {k1: {"replayed": 1}}


def test_node_counts_at_most_256_rejecting_keys_apart(config: Config) -> None:
    node = Node(Ticker("x"), Topology.from_config(config), seed=0)
    for i in range(300):
        node.receive(f"adn/g/junk/{i}", b"{}")
    assert len(node.counts.rejected) == 257
    assert node.counts.rejected["(other keys)"] == {"not_subscribed": 44}


def fault(key: str, seq: int, kind: str, start_s: float, end_s: float | None, t_send: int = 0,
          **target) -> bytes:
    from payloads import payload
    body = {"fault_id": seq + 1, "kind": kind, "start_ns": ns(start_s),
            "end_ns": None if end_s is None else ns(end_s), **target}
    return payload(key, body, seq=seq, t_send_ns=t_send, t_deliver_ns=ns(start_s))


def test_node_stops_for_good_at_an_injected_kill(config: Config) -> None:
    topo = Topology.from_config(config)
    agent = Ticker(topo.keys.of("p_ip"))
    node = Node(agent, topo, seed=0)
    node.receive(topo.keys.of("fault"), fault(topo.keys.of("fault"), 0, "kill", 25e-9, None,
                                         agent="measurement"))
    faults = topo.keys.of("fault")
    node.receive(faults, fault(faults, 1, "kill", 1.0, None, agent="cpfc"))
    node.advance(21)
    assert not node.killed and [t for _, t in agent.seen] == [0, 10, 20]
    node.advance(100)
    assert node.killed and node.now_ns == 25 and [t for _, t in agent.seen] == [0, 10, 20]
    report = node.report()
    assert report.killed_ns == 25 and report.next_ns is None
    assert node.advance(1000) == []


def test_node_impairs_its_own_links_and_drops_while_offline(config: Config) -> None:
    topo = Topology.from_config(config)
    keys = topo.keys
    der = Node(build_agent("der/SGen1", config), topo, seed=0)
    der.receive(keys.of("fault"), fault(keys.of("fault"), 0, "der_offline", 1.0, 2.0, der="SGen1"))
    der.receive(keys.of("fault"), fault(keys.of("fault"), 1, "der_offline", 1.0, 2.0, der="SGen2"))
    der.receive(keys.of("fault"), fault(keys.of("fault"), 0, "der_offline", 1.0, 2.0, der="SGen1"))
    assert der.counts.rejected[keys.of("fault")] == {"replayed": 1}
    for t_ms in range(0, 3000, 10):   # a command every 10 ms, delivered 0.1 s later
        der.receive(keys.of("p_y"), payload_p_y(t_ms, w=t_ms == 0))
    sent = der.advance(ns(3.0))
    heartbeats = [decode(k, p).t_send_ns for k, p in sent if k.endswith("/heartbeat")]
    states = [decode(k, p).t_send_ns for k, p in sent if k.endswith("/state")]
    # due at 0, 1.0 (lost), 1.99 (the watchdog fallback; lost), 2.0 (back in control)
    assert heartbeats == [0, ns(2.0)] and der.counts.lost == 2
    assert len(states) == 300                          # physics: never lost
    assert der.counts.dropped_offline == 100           # commands delivered in [1, 2) s
    assert der.agent.counts["watchdog_trips"] == 1


def payload_p_y(t_ms: int, w: bool = False) -> bytes:
    from payloads import payload
    body = {"p_y": 0.1, "p_ref_w": 0.0, "kp": 1e-7, "ki": 1e-7, "entry": 0}
    if w:
        body["w"] = {"SGen1": 1.0, "SGen2": 1.0}
    return payload("adn/runtime-test/cpfc/p_y", body, seq=t_ms, t_send_ns=t_ms * 1_000_000,
                   t_deliver_ns=t_ms * 1_000_000 + ns(0.1))


def test_link_impairments_lose_delay_and_keep_the_own_stream() -> None:
    params = LinkParams("l", delay_ns=100, jitter_ns=50, loss=0.1, fifo=False)
    plain, impaired = Link(params, 3, "x"), Link(params, 3, "x")
    impaired.impair(Impairment(1, "delay", 1000, 2000, 500))
    impaired.impair(Impairment(2, "loss", 3000, 4000, 0.5))
    impaired.impair(Impairment(3, "outage", 5000, None))
    times = range(0, 6000, 10)
    pairs = [(t, plain.transmit(t), impaired.transmit(t)) for t in times]
    assert all(x == y for t, x, y in pairs if t < 1000 or 2000 <= t < 3000 or 4000 <= t < 5000)
    assert all(y == x + 500 for t, x, y in pairs if 1000 <= t < 2000 and x is not None)
    assert all(y is None for t, x, y in pairs if t >= 5000)
    in_window = [(x, y) for t, x, y in pairs if 3000 <= t < 4000 and x is not None]
    extra_lost = sum(y is None for x, y in in_window)
    assert all(y == x for x, y in in_window if y is not None)
    n = len(in_window)
    assert abs(extra_lost - n / 2) < 4 * math.sqrt(n / 4)     # loss 0.5 on its own stream


def test_a_restarted_node_begins_late_and_rejects_older_messages(config: Config) -> None:
    topo = Topology.from_config(config)
    keys = topo.keys
    agent = build_agent("measurement", config)
    node = Node(agent, topo, seed=0, start_ns=ns(2.005))
    assert agent.next_timer_ns() == ns(2.01) and node.now_ns == ns(2.005)
    node.receive(keys.of("der_state", "SGen1"), state("SGen1", ns(2.0), 0))
    node.receive(keys.of("der_state", "SGen1"), state("SGen1", ns(2.01), 1))
    assert node.counts.rejected == {keys.of("der_state", "SGen1"): {"before_start": 1}}
    assert node.counts.received == 1


# --- the in-process runner: determinism and agreement with the numerics -------------------------


def p_ip_series(messages) -> tuple[np.ndarray, np.ndarray]:
    bodies = [json.loads(p) for k, p in messages if k.endswith("/measurement/p_ip")]
    return (np.array([b["t_send_ns"] for b in bodies]) * 1e-9,
            np.array([b["p_ip_w"] for b in bodies]))


def test_gains_of_the_test_table_meet_the_constraints(config: Config) -> None:
    from adnmesh.loopmodel.evaluation import evaluate
    figures = evaluate(plant_from_ders(config.ders, config.t_com_s, config.t_meas_s), KP2, KI2)
    assert bool(figures.stable[0]) and figures.disk_margin[0] >= 1.5
    assert figures.overshoot_pct[0] < 1.0


def test_local_run_is_deterministic(config: Config, schedule: GainSchedule) -> None:
    noisy = with_runtime(config, links=config.runtime.links.model_copy(
        update={"cpfc_to_der": LinkSettings(jitter_s=0.02, loss=0.05)}))
    first = run_local(noisy, schedule).messages
    assert first == run_local(noisy, schedule).messages
    other_seed = run_local(with_runtime(noisy, seed=noisy.runtime.seed + 1), schedule).messages
    assert other_seed != first


@pytest.mark.parametrize("period_s", [0.02, 0.01, 0.005])
def test_sampled_loop_converges_to_the_numerics(config: Config, schedule: GainSchedule,
                                                period_s: float) -> None:
    """The runtime's step response of P_IP differs from the continuous-time closed loop
    (adnmesh.loopmodel.step_response) by the zero-order hold of P_Y only: about half a period of extra delay,
    so |error| <= h * max|dy/dt| (measured: 0.2 h max|dy/dt|, first order in h)."""
    cfg = with_runtime(config, pi_period_s=period_s, measurement_period_s=period_s)
    t, p_ip = p_ip_series(run_local(cfg, schedule, end_s=7.9).messages)
    t_num, y_num = simulate_step(plant_from_ders(cfg.ders, cfg.t_com_s, cfg.t_meas_s), KP2, KI2,
                                 7.0, 0.001)
    slope = np.max(np.abs(np.diff(y_num[0]))) / 0.001
    after = t >= 1.0
    p_before = -3e6 + 0.5e6
    assert np.all(p_ip[~after] == p_before)                    # at rest before the step
    y = (p_ip[after] - p_before) / 1e6
    error = np.max(np.abs(y - np.interp(t[after] - 1.0, t_num, y_num[0])))
    assert error <= period_s * slope
    assert error == pytest.approx(0.2 * period_s * slope, rel=0.25)   # first order in h


def test_local_run_switches_gains_without_a_bump(config: Config, schedule: GainSchedule) -> None:
    run = run_local(config, schedule)
    (event,) = run.nodes["cpfc"].agent.switches
    assert event.t_ns == ns(8.2)           # 8 s + heartbeat link 0.1 s + SI link 0.1 s
    assert event.record.p_y_after == event.record.p_y_before
    assert run.nodes["cpfc"].agent.pi.x_i != 0




def test_a_forged_fault_shuts_out_none_of_ups_own(config: Config) -> None:
    """Open profile: someone sends a valid fault as ``up`` with a huge seq, a far send time and
    a number ``up`` uses. Faults are taken at once, so the gate's order rule must not then
    refuse ``up``'s own faults (seq 0, 1, sent earlier): the node counts them (the clock
    expects them) and applies the kill under the same fault number (the run stalled)."""
    from payloads import payload

    topo = Topology.from_config(config)
    node = Node(Ticker(topo.keys.of("p_ip")), topo, seed=0)
    faults = topo.keys.of("fault")
    node.receive(faults, payload(faults, {"fault_id": 1, "kind": "ict_outage",
                                          "start_ns": 150 * 10**9, "end_ns": 160 * 10**9},
                                 seq=10**9, t_send_ns=150 * 10**9))
    me = node.agent_id
    node.receive(faults, payload(faults, {"fault_id": 1, "kind": "kill", "start_ns": 50,
                                          "end_ns": None, "agent": me,
                                          "origin": "quarantine"}, seq=0))
    node.receive(faults, payload(faults, {"fault_id": 2, "kind": "ict_outage", "start_ns": 60,
                                          "end_ns": None}, seq=1))
    assert node.counts.received == 3 and node.counts.rejected == {}
    assert node.kill_ns == 50
    node.receive(faults, payload(faults, {"fault_id": 2, "kind": "ict_outage", "start_ns": 60,
                                          "end_ns": None}, seq=1))     # the same again
    assert node.counts.received == 3 and node.counts.rejected == {faults: {"replayed": 1}}


def test_a_quarantined_senders_messages_leave_the_count_on_both_sides(config: Config) -> None:
    """Someone with der/SGen2's identity sends 3 states the measurement counts and no report
    of SGen2's accounts for. Once the clock quarantines SGen2, the measurement's next grant cuts
    SGen2's state key: the node takes out all it counted there (SGen2's 4 genuine states and
    the 3 forged) and the clock all SGen2's reports counted, so the grant waits for the 2
    states of SGen1 still in flight. Without the cut the 3 forged ones stood in for them: the
    measurement went ahead without them, and they came in its past (a CI run of the stolen key
    test lost its SI messages so, and its last step never settled)."""
    topo = Topology.from_config(config)
    keys = topo.keys
    k1, k2 = keys.of("der_state", "SGen1"), keys.of("der_state", "SGen2")
    node = Node(Ticker(keys.of("p_ip")), topo, seed=0)
    clock = Coordinator(topo, end_ns=ns(10.0))
    for agent in topo.agents:
        clock.take_report(node.report() if agent == "measurement" else Report(agent, 0, 0, {}))
    clock.start()
    sent = {"der/SGen1": {k1: (5, ns(0.1))}, "der/SGen2": {k2: (4, ns(0.1))}}
    for der in ("der/SGen1", "der/SGen2"):
        clock.take_report(Report(der, ns(0.1), 0, sent[der], granted_ns=ns(0.1)))
    for seq in range(3):
        node.receive(k1, state("SGen1", ns(0.1) + seq, seq))           # 2 of SGen1's in flight
    for seq in range(4):
        node.receive(k2, state("SGen2", ns(0.1) + seq, seq))
    for seq in range(3):                                                   # the forger's
        node.receive(k2, state("SGen2", ns(5.0) + seq, 10**9 + seq))
    assert node.counts.received == 10
    queue = clock.quarantine("der/SGen2", ns(0.1))
    while queue[0].agent != "measurement":     # the others answer; SGen1 sends nothing more
        g = queue.pop(0)
        queue += clock.on_report(Report(g.agent, g.until_ns, g.expect, {}, granted_ns=g.until_ns,
                                        cuts=g.cuts))
    grant = queue[0]
    assert (grant.expect, grant.cut_keys, grant.cuts) == (5, (k2,), 1)
    node.take_cut(grant.cut_keys, grant.cuts)
    assert node.counts.received == 3 < grant.expect                    # it waits
    node.receive(k2, state("SGen2", ns(6.0), 10**9 + 5))                # not counted any more
    node.receive(k1, state("SGen1", ns(0.1) + 3, 3))
    node.receive(k1, state("SGen1", ns(0.1) + 4, 4))
    assert node.counts.received == grant.expect == 5
    report = node.report()
    assert report.cuts == 1 and report.received == 5
    node.take_cut(grant.cut_keys, grant.cuts)                          # the same cut again
    assert node.counts.received == 5


def clock_after_4_states_of_sgen2(config: Config) -> Coordinator:
    """A started clock whose der/SGen2 reported 4 states sent to the measurement."""
    topo = Topology.from_config(config)
    clock = Coordinator(topo, end_ns=ns(10.0))
    for agent in topo.agents:
        clock.take_report(Report(agent, 0, 0, {}))
    clock.start()
    clock.take_report(Report("der/SGen2", ns(0.1), 0,
                             {topo.keys.of("der_state", "SGen2"): (4, ns(0.1))},
                             granted_ns=ns(0.1)))
    return clock


def test_a_report_from_before_a_cut_counts_as_missing_messages(config: Config) -> None:
    """A report made before its agent took a quarantine's cut counts messages the clock no
    longer expects: the clock takes it as not having every message (a grant that syncs), not
    as having them all."""
    clock = clock_after_4_states_of_sgen2(config)
    clock.quarantine("der/SGen2", ns(0.1))
    assert clock._expected[clock._index["measurement"]] == 0
    clock.take_report(Report("measurement", ns(0.2), 4, {}, granted_ns=0))   # cuts=0: stale
    assert clock._received[clock._index["measurement"]] == -1
    clock.take_report(Report("cpfc", ns(0.2), 0, {}, granted_ns=0, cuts=1))
    assert clock._received[clock._index["cpfc"]] == 0


def test_a_node_counts_per_key_from_its_first_report(config: Config) -> None:
    """What a node counted before its first report is in the clock's baseline (a restarted
    agent's first report: the clock keeps that one): a later cut takes out only what came
    after it."""
    topo = Topology.from_config(config)
    k2 = topo.keys.of("der_state", "SGen2")
    node = Node(Ticker(topo.keys.of("p_ip")), topo, seed=0)
    node.receive(k2, state("SGen2", 10, 0))
    assert node.report().received == 1                                 # a first report
    node.receive(k2, state("SGen2", 11, 1))
    node.receive(k2, state("SGen2", 12, 2))
    assert node.report().received == 3                                 # a first report, again
    node.take_cut((k2,), 1)
    assert node.counts.received == 1 and node.report().cuts == 1


def test_a_quarantine_marks_its_idle_receivers_as_lacking_messages(config: Config) -> None:
    """A receiver idle at the quarantine reported a count the clock no longer expects: it
    counts as lacking messages (at a hold it gets a grant that syncs it)."""
    clock = clock_after_4_states_of_sgen2(config)
    m = clock._index["measurement"]
    clock.take_report(Report("measurement", 0, 4, {}, granted_ns=0))
    assert clock._received[m] == clock._expected[m] == 4
    clock.quarantine("der/SGen2", ns(0.1))
    assert (clock._received[m], clock._expected[m]) == (-1, 0)
    assert clock._received[clock._index["der/SGen1"]] == 0              # not a receiver


def test_a_quarantined_agent_is_never_taken_back(config: Config) -> None:
    """A restart planned for an agent that is then quarantined does not happen: a report in
    its name (perhaps the forger's) is not taken at the barrier, and the barrier is gone."""
    topo = Topology.from_config(config)
    clock = Coordinator(topo, end_ns=ns(10.0))
    for agent in topo.agents:
        clock.take_report(Report(agent, 0, 0, {}))
    clock.start()
    clock.plan_restart("der/SGen2", ns(0.05))
    clock.quarantine("der/SGen2", ns(0.02))
    assert not clock.take_report(Report("der/SGen2", ns(0.05), 0, {}))
    assert clock._barrier() == math.inf and clock.take_rejoined() == []
    assert clock.is_dead("der/SGen2")


def test_a_quarantine_cuts_the_agent_off_also_from_what_the_node_holds(config: Config) -> None:
    """``up`` quarantines der/SGen1 (a kill with origin ``quarantine``) at 50 ns: what SGen1
    sent before stays, what it sent from then on is dropped, also if it was already held."""
    topo = Topology.from_config(config)
    agent = Ticker(topo.keys.of("p_ip"))
    node = Node(agent, topo, seed=0)
    k1 = topo.keys.of("der_state", "SGen1")
    node.receive(k1, state("SGen1", 10, 0))
    node.receive(k1, state("SGen1", 60, 1))                  # held when the quarantine comes
    from payloads import payload
    faults = topo.keys.of("fault")
    node.receive(faults, payload(faults, {"fault_id": 1, "kind": "kill", "start_ns": 50,
                                          "end_ns": None, "agent": "der/SGen1",
                                          "origin": "quarantine"}, t_deliver_ns=50))
    node.receive(k1, state("SGen1", 70, 2))                  # after it: cut off at once
    node.advance(100)
    assert [s for s in agent.seen if s[0] == "SGen1"] == [("SGen1", 10, 1.0)]
    assert node.counts.rejected == {k1: {"quarantined": 2}}
    # every message SGen1 sent counts as received (its clock reports count them all), the one
    # dropped on arrival too: 3 states and the fault
    assert node.counts.received == 4
    assert not node.killed                                   # it was not the node's own agent
