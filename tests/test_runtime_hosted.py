"""Several DER agents in one process (``runtime.ders_per_process``, issue 41): the same
messages as one process per DER, kills of hosted DERs, and what is refused."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from adnmesh.config import load_config
from adnmesh.runtime.children import hosted_ders_argv
from up_runs import data_messages, run_up, write_case

# SGen2 killed at 3 s and restarted 2 s later (in a process of its own), SGen1 killed for good
# at 10 s: both DERs of the hosting process leave it, which then ends
FAULTS = [{"kind": "kill", "agent": "der/SGen2", "t_s": 3, "restart_after_s": 2},
          {"kind": "kill", "agent": "der/SGen1", "t_s": 10}]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The runtime case with the kills above, one process per DER and both DERs in one."""
    found = {}
    for per_process in (1, 2):
        tmp = tmp_path_factory.mktemp(f"hosted{per_process}")
        config, table = write_case(tmp, "case", runtime={"faults": FAULTS,
                                                          "ders_per_process": per_process})
        found[per_process] = run_up(tmp, config, table, "case")
    return found


def test_hosted_ders_send_the_messages_of_one_process_each(runs) -> None:
    (_, alone, s_alone), (result, hosted, s_hosted) = runs[1], runs[2]
    assert data_messages(hosted) == data_messages(alone)
    assert len(data_messages(hosted)) > 2000
    # one link fewer: the two DERs share a session (and SGen2's restart has its own)
    assert s_alone["extra"]["links_accepted"] == 6
    assert s_hosted["extra"]["links_accepted"] == 5
    assert s_hosted["extra"]["ended"] == "finished"
    assert "der/SGen2 restarting at 5 s" in result.stderr
    assert "killed after the shutdown timeout" not in result.stderr


def test_a_killed_hosted_der_leaves_its_process_to_the_others(runs) -> None:
    """SGen2's kill at 3 s does not stop SGen1, which shares its process: SGen1 sends its
    state up to its own kill at 10 s."""
    _, hosted, _ = runs[2]
    state = [m for m in hosted.messages if m.topic.endswith("/der/SGen1/state")]
    assert max(m.publish_time_ns for m in state) >= 9.9e9
    sgen2 = [m.publish_time_ns for m in hosted.messages if m.topic.endswith("/der/SGen2/state")]
    assert not [t for t in sgen2 if 3.05e9 < t < 5e9]         # dead between kill and restart


def test_up_starts_the_ders_in_groups_of_ders_per_process(tmp_path) -> None:
    from adnmesh.runtime.launcher import UpOptions, _Launch

    config_path, table = write_case(tmp_path, "groups", runtime={"ders_per_process": 2})
    config = load_config(config_path)
    launch = _Launch(UpOptions(config=config, table_path=table, out=tmp_path / "g.mcap"))
    try:
        agents = list(launch.topology.agents)
        groups = launch.process_groups(agents)
    finally:
        launch.recorder.close()
    assert sorted(a for g in groups for a in g) == sorted(agents)
    assert ["der/SGen1", "der/SGen2"] in groups
    assert all(len(g) == 1 for g in groups if "der/SGen1" not in g)


def test_the_hosting_command_line_takes_powers_and_parameters_only_from_all() -> None:
    argv = hosted_ders_argv([("A", 1.0, "{}"), ("B", 2.0, "{}")], Path("c.yaml"), "tcp/x:1")
    assert argv[argv.index("--der"):] == ["--der", "A", "--p-avail-w", "1.0", "--model-params",
                                          "{}", "--der", "B", "--p-avail-w", "2.0",
                                          "--model-params", "{}"]
    argv = hosted_ders_argv([("A", 1.0, None), ("B", None, None)], Path("c.yaml"), "tcp/x:1")
    assert argv[argv.index("--der"):] == ["--der", "A", "--der", "B"]


@pytest.mark.parametrize("extra, says", [
    (["--p-avail-w", "1e6"], "--p-avail-w must be given once per --der (2), got 1"),
    (["--certs", "certs"], "several --der need the open profile"),
])
def test_the_der_program_refuses_a_hosting_command_it_cannot_follow(tmp_path, extra,
                                                                    says) -> None:
    config, _ = write_case(tmp_path, "refused")
    done = subprocess.run([sys.executable, "-m", "adnmesh.agents.der", str(config), "--der",
                           "SGen1", "--der", "SGen2", *extra], capture_output=True, text=True,
                          timeout=60, check=False)
    assert done.returncode == 2
    assert says in done.stderr.splitlines()[-1]


def test_hosting_is_refused_in_the_secure_profile(tmp_path, capsys) -> None:
    from adnmesh.cli import main

    config, table = write_case(tmp_path, "secure", runtime={"ders_per_process": 2})
    assert main(["up", str(config), "--table", str(table), "--secure"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "runtime.ders_per_process 2 is for the open profile" in err


def test_the_keys_of_every_der_of_a_kind_are_one_wildcard_subscriber() -> None:
    """Open profile: the measurement's 1,000 ``der/<id>/state`` keys are one subscriber whose
    callback takes only those keys; a key alone, or the secure profile, stays exact."""
    from adnmesh.runtime.process import subscription_patterns

    keys = ["adn/g/der/A/state", "adn/g/der/B/state", "adn/g/der/A/heartbeat", "adn/g/faults",
            "adn/g/cpfc/p_y"]
    assert subscription_patterns(keys) == {
        "adn/g/der/*/state": frozenset({"adn/g/der/A/state", "adn/g/der/B/state"}),
        "adn/g/der/A/heartbeat": None, "adn/g/faults": None, "adn/g/cpfc/p_y": None}
    assert subscription_patterns(keys, wildcards=False) == {k: None for k in keys}


class _Publisher:
    def __init__(self, key, puts):
        self.key, self.puts = key, puts

    def put(self, payload, attachment=None):
        self.puts.append((self.key, payload, attachment))


class _Session:
    def __init__(self):
        self.puts = []

    def declare_publisher(self, key, **_):
        return _Publisher(key, self.puts)


class _Tap:
    def __init__(self):
        self.recorded = []

    def record_own(self, key, message, payload):
        self.recorded.append((key, payload))


def test_the_grants_to_one_hosting_process_go_in_one_sample_and_are_recorded_each() -> None:
    """The sim clock's grants of one batch to the DERs of one process: one Zenoh sample on
    ``clock/grants/<first DER>`` naming them (issue 41: one grant sample per process instead
    of one per DER); recorded under each DER's own grant key, as one process per DER has them.
    A DER alone in its process gets its grant on its own key."""
    from adnmesh.runtime.launcher_bus import LauncherOutbox, SimClockDriver
    from adnmesh.sim.clock import Grant
    from adnmesh.wire.envelope import decode
    from adnmesh.wire.keys import Keys

    keys, session, tap = Keys("g"), _Session(), _Tap()
    hosts = {"der/A": "der/A", "der/B": "der/A"}
    driver = SimClockDriver(None, keys, LauncherOutbox(session, tap), lambda: None,
                            host_of=hosts.get)

    class _Coordinator:
        finished = False

        def now_ns(self):
            return 7

    driver.coordinator = _Coordinator()
    driver._send([Grant("der/A", 200, 3), Grant("cpfc", 200, 5), Grant("der/B", 200, 4)])
    assert [(k, a) for k, _, a in session.puts] == [
        ("adn/g/clock/grant/cpfc", None), ("adn/g/clock/grants/der/A", b"der/A\nder/B")]
    batch = session.puts[1][1].split(b"\n")
    assert [k for k, _ in tap.recorded] == ["adn/g/clock/grant/cpfc", "adn/g/clock/grant/der/A",
                                            "adn/g/clock/grant/der/B"]
    assert [p for _, p in tap.recorded[1:]] == batch
    granted = [decode(keys.of("clock_grant", a), p) for a, p in zip(("der/A", "der/B"), batch)]
    assert [(g.until_ns, g.expect, g.t_send_ns) for g in granted] == [(200, 3, 7), (200, 4, 7)]


class _Hosted:
    def __init__(self, agent):
        self.agent, self.took, self.rejected = agent, [], []
        self.samples = {"clock_in": 0}

    def take_grant(self, payload, counted):
        self.took.append(payload)
        self.samples["clock_in"] += counted

    def reject(self, key, reason):
        self.rejected.append((key, reason))

    def guarded(self, callback):
        return callback


class _Sample:
    def __init__(self, payload, attachment):
        self.payload = _Bytes(payload)
        self.attachment = None if attachment is None else _Bytes(attachment)


class _Bytes:
    def __init__(self, data):
        self.data = data

    def to_bytes(self):
        return self.data


@pytest.mark.parametrize("payload, names, rejected", [
    (b"g1\ng2", b"der/A\nder/B", False),
    (b"g1\ng2", b"der/A", True),                  # names and grants do not pair up
    (b"g1", None, True),                          # no names
    (b"g1\ng2", b"der/A\nder/C", True),           # an agent not hosted here
])
def test_a_hosting_process_hands_each_grant_of_its_sample_to_its_agent(payload, names,
                                                                        rejected) -> None:
    from adnmesh.runtime.host import _on_grants
    from adnmesh.wire.keys import Keys

    agents = [_Hosted("der/A"), _Hosted("der/B")]
    _on_grants(agents, Keys("g"))(_Sample(payload, names))
    if rejected:
        assert [a.took for a in agents] == [[], []]
        assert agents[0].rejected[0][0] == "adn/g/clock/grants/der/A"
        assert "grant sample" in agents[0].rejected[0][1]
    else:
        assert [a.took for a in agents] == [[b"g1"], [b"g2"]] and not agents[0].rejected
    assert [a.samples["clock_in"] for a in agents] == [1, 0]     # one sample, counted once
