"""The access control of the secure profile (adnmesh/runtime/acl.py, security.py, bus.py):
derived from the topology, it agrees with the receivers' own rule (the key's sender), and a
router configured with it does what it says: against a real Zenoh router with mutual TLS,
every identity may publish exactly its own keys and receives exactly what it needs."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
import zenoh

from adnmesh.config import load_config
from adnmesh.errors import UsageError
from adnmesh.runtime.acl import access_control, launcher_keys, rights
from adnmesh.runtime.bus import client_config, free_port, router_config
from adnmesh.runtime.certificates import issue
from adnmesh.runtime.identity import identities
from adnmesh.sim.topology import Topology
from adnmesh.names import LAUNCHER, OPERATOR
from adnmesh.wire.keys import route

REPO = Path(__file__).resolve().parent.parent
CASE = REPO / "configs" / "examples" / "runtime-step.yaml"


@pytest.fixture(scope="module")
def topology() -> Topology:
    return Topology.from_config(load_config(CASE))


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    directory = tmp_path_factory.mktemp("certs") / "certs"
    issue(directory, [*identities(load_config(CASE)), "router/site"])
    other = tmp_path_factory.mktemp("other") / "certs"
    issue(other, ["der/SGen1"])
    return directory


def test_every_identity_may_publish_exactly_the_keys_it_is_the_sender_of(topology) -> None:
    """The router's rule and the receivers' rule (``route(key).sender``) agree: no identity
    may publish a key another one sends."""
    table = rights(topology)
    assert set(table) == set(topology.agents) | {OPERATOR}
    for identity, r in table.items():
        assert r.publishes and all(route(k).sender == identity for k in r.publishes), identity
    published = [k for r in table.values() for k in r.publishes]
    assert len(published) == len(set(published))
    every_key = {k for (_, k) in topology.links} | {topology.keys.of("fault_request")}
    every_key |= {topology.keys.of("clock_report", a) for a in topology.agents}
    every_key |= {topology.keys.of("agent_bye", a) for a in topology.agents}
    assert set(published) == every_key
    assert all(route(k).sender == LAUNCHER for k in launcher_keys(topology))


def test_every_agent_receives_what_its_node_subscribes_and_its_own_clock(topology) -> None:
    keys = topology.keys
    for agent in topology.agents:
        r = rights(topology)[agent]
        assert set(r.receives) == set(topology.subscriptions[agent]) | {
            keys.of("clock_grant", agent), keys.of("clock_kill", agent), keys.of("clock_start"),
            keys.of("clock_stop")}
        assert r.token == keys.liveliness(agent) and r.watches == (keys.liveliness(LAUNCHER),)
    assert rights(topology)["der/SGen1"].receives.count(keys.of("p_y")) == 1
    assert keys.of("p_ip") not in rights(topology)["der/SGen1"].receives


def test_the_zenoh_section_denies_by_default_and_names_every_rule_it_uses(topology) -> None:
    section = access_control(topology, ["router/site"])
    assert section["enabled"] is True and section["default_permission"] == "deny"
    rule_ids = [r["id"] for r in section["rules"]]
    assert len(rule_ids) == len(set(rule_ids))
    subjects = {s["id"]: s for s in section["subjects"]}
    for policy in section["policies"]:
        assert set(policy["rules"]) <= set(rule_ids) and set(policy["subjects"]) <= set(subjects)
    assert {s["id"] for s in section["subjects"]} == {*rights(topology), "router/site"}
    assert all(s["cert_common_names"] == [s["id"]] for s in subjects.values())
    for rule in section["rules"]:
        assert rule["permission"] == "allow" and rule["key_exprs"]
        for key in rule["key_exprs"]:
            zenoh.KeyExpr(key)                    # a valid key expression
    site = [r for r in section["rules"] if r["id"] == "router/site forwards"][0]
    assert not set(site["key_exprs"]) & set(launcher_keys(topology))


# -- against a real router ------------------------------------------------------------------------


class Router:
    """A secure-profile router with the run's access control and a local subscriber on
    everything (as ``up``'s recorder)."""

    def __init__(self, topology: Topology, certs: Path) -> None:
        self.endpoint = f"tls/127.0.0.1:{free_port()}"
        self.session = zenoh.open(router_config([self.endpoint], certs=certs, identity=LAUNCHER,
                                                access_control=access_control(topology)))
        self.got: list[tuple[str, bytes]] = []
        self.changed = threading.Condition()
        self.session.declare_subscriber(topology.keys.all, self._on,
                                        allowed_origin=zenoh.Locality.REMOTE)

    def _on(self, sample: zenoh.Sample) -> None:
        with self.changed:
            self.got.append((str(sample.key_expr), sample.payload.to_bytes()))
            self.changed.notify_all()

    def wait_for(self, item, timeout_s: float = 10.0) -> bool:
        with self.changed:
            return self.changed.wait_for(lambda: item in self.got, timeout_s)


@pytest.fixture(scope="module")
def router(topology, certs):
    found = Router(topology, certs)
    yield found
    found.session.close()


def every_key(topology) -> list[str]:
    found = {k for r in rights(topology).values() for k in r.publishes}
    return sorted(found | set(launcher_keys(topology)))


def test_each_identity_can_put_on_its_own_keys_only(topology, certs, router) -> None:
    """Every identity puts on every key of the run, then on its own report key (or the fault
    request) as a sentinel: samples of one session arrive in order, so once the sentinel is in,
    the router has decided on everything before it."""
    keys = topology.keys
    for identity in rights(topology):
        with zenoh.open(client_config([router.endpoint], certs, identity)) as session:
            for key in every_key(topology):
                session.put(key, f"{identity} {key}".encode())
            sentinel = rights(topology)[identity].publishes[0]
            session.put(sentinel, b"sentinel " + identity.encode())
            assert router.wait_for((sentinel, b"sentinel " + identity.encode()))
        delivered = {k for k, p in router.got if p == f"{identity} {k}".encode()}
        assert delivered == set(rights(topology)[identity].publishes), identity
    assert not any(k in launcher_keys(topology) for k, _ in router.got)
    assert keys.of("p_y") in {k for k, p in router.got if p == f"cpfc {k}".encode()}


def test_each_identity_receives_only_what_it_needs(topology, certs, router) -> None:
    """A DER subscribes to every key; once ``up`` (the router's session) sees its subscribers
    on the keys it may receive (matching status), ``up`` publishes on every key and last on
    clock/start: only the DER's keys arrive (a session's samples arrive in order)."""
    got: list[str] = []
    done = threading.Event()
    keys = topology.keys
    allowed = rights(topology)["der/SGen1"].receives

    def on_sample(sample: zenoh.Sample) -> None:
        got.append(str(sample.key_expr))
        if str(sample.key_expr) == keys.of("clock_start"):
            done.set()

    with zenoh.open(client_config([router.endpoint], certs, "der/SGen1")) as session:
        subscribers = [session.declare_subscriber(k, on_sample,
                                                  allowed_origin=zenoh.Locality.REMOTE)
                       for k in every_key(topology)]
        # refused by the router as a whole; in the session it sees what the others receive
        wide = session.declare_subscriber(keys.all, on_sample,
                                          allowed_origin=zenoh.Locality.REMOTE)
        publishers = {k: router.session.declare_publisher(
            k, allowed_destination=zenoh.Locality.REMOTE) for k in every_key(topology)}
        matched = threading.Semaphore(0)
        listeners = [publishers[k].declare_matching_listener(
            lambda status: status.matching and matched.release()) for k in allowed]
        for _ in allowed:
            assert matched.acquire(timeout=10), "the DER's subscriptions did not arrive"
        for key in every_key(topology):
            if key != keys.of("clock_start"):
                publishers[key].put(b"from up")
        publishers[keys.of("clock_start")].put(b"from up")
        assert done.wait(10)
        for handle in [*listeners, *publishers.values(), wide, *subscribers]:
            handle.undeclare()
    assert set(got) == set(allowed)


def test_no_certificate_another_ca_or_plain_tcp_cannot_connect(topology, certs, router,
                                                               tmp_path) -> None:
    import json
    other = tmp_path / "other"
    issue(other, ["der/SGen1"])

    def config(tls: dict | None, endpoint: str = router.endpoint) -> zenoh.Config:
        found = zenoh.Config()
        found.insert_json5("mode", '"client"')
        found.insert_json5("connect/endpoints", json.dumps([endpoint]))
        found.insert_json5("scouting/multicast/enabled", "false")
        if tls is not None:
            found.insert_json5("transport/link/tls", json.dumps(tls))
        return found

    ca = str(certs / "ca.pem")
    attempts = {
        "no client certificate": config({"root_ca_certificate": ca}),
        "a certificate from another CA": config({
            "root_ca_certificate": ca, "enable_mtls": True,
            "connect_certificate": str(other / "der" / "SGen1.pem"),
            "connect_private_key": str(other / "der" / "SGen1.key")}),
        "plain TCP": config(None, router.endpoint.replace("tls/", "tcp/")),
    }
    for what, attempt in attempts.items():
        with pytest.raises(zenoh.ZError):
            zenoh.open(attempt).close()
            pytest.fail(f"{what}: connected")
    links = [link.auth_identifier for link in router.session.info.links()]
    assert links == []


def test_endpoints_and_certificates_must_fit_the_profile(certs) -> None:
    with pytest.raises(UsageError, match="speaks only TLS"):
        client_config(["tcp/127.0.0.1:7447"], certs, "cpfc")
    with pytest.raises(UsageError, match="needs certificates"):
        client_config(["tls/127.0.0.1:7447"])
    with pytest.raises(UsageError, match="missing or unreadable"):
        client_config(["tls/127.0.0.1:7447"], certs, "der/Nope")
