"""``adnmesh up`` on a hierarchy file: every level's agents as processes, each ADN a site with a
router of its own linked to ``up``'s, one sim clock for all -- one shared run of two small ADNs
with two upper steps, a site cut off from the level above, a lower ADN losing its wind turbine
and a site router killed and started again -- and the pieces it is made of (the levels file,
the clock's hold, the options a hierarchy does not take)."""
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from adnmesh.cli import main
from adnmesh.config import load_hierarchy
from adnmesh.errors import ConfigError
from adnmesh.recording import read_recording
from adnmesh.sim.clock import Coordinator, Report
from adnmesh.sim.hierarchy_levels import load_levels
from adnmesh.sim.hierarchy_run import Level, run_hierarchy
from adnmesh.sim.topology import Topology
from up_runs import data_messages

EXAMPLES = Path(__file__).resolve().parent.parent / "configs" / "examples"

HIERARCHY = """name: hv
t_meas_s: 0.2
constraints: {{disk_margin_min: 1.5, overshoot_max_pct: 1.0}}
adns:
  - {{id: wtchp, config: wt-chp.yaml, t_com_s: 0.3}}
  - {{id: mixed, config: {mixed}, t_com_s: 0.25}}
scenario:
  duration_s: 45
  p_ref_steps: [{{t_s: 2, delta_w: 1.0e+6}}, {{t_s: 14, delta_w: -0.5e+6}}]
faults:
  - {{kind: der_offline, der: wtchp, t_s: 25, duration_s: 6}}
site_restarts:
  - {{adn: mixed, t_s: 8, down_s: 0.5}}
"""
"""Two ADNs without an HV grid (the upper P_IP is the sum of their exchanges); mixed's site
router killed at 8 s, wtchp's site cut off from the level above from 25 to 31 s, its own wind
turbine gone at 40 s (its config's availability change, moved from 80 s)."""

SITE_AGENTS = 8      # mixed's CPFC, measurement, monitor and 4 DERs, and the upper der/mixed

FORGED = {"adn/hv/cpfc/p_y": {"p_y": 0.25, "p_ref_w": 1e6, "kp": 5e-8, "ki": 2e-7, "entry": 1},
          "adn/hv/scenario/p_ref": {"p_ref_w": -2.5e6},
          "adn/hv/der/mixed/offset": {"offset_w": 2.5e5}}
"""What the rogue with wtchp's CPFC certificate puts: valid messages of the upper level (its
CPFC's P_Y, its reference) and an offset for mixed, sent at 10 s."""
FORGED_SEQ = 10**6


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    """One ``adnmesh up`` of the hierarchy in the secure profile (a certificate per agent as
    ``<grid>:<agent>`` and per site router), with a rogue: once every agent is ready, a
    session holding wtchp's CPFC certificate puts a valid P_Y and P_ref of the upper level and
    an offset for mixed (:data:`FORGED`) at ``up``'s router. (folder, summary JSON, stderr,
    merged recording.)"""
    import zenoh

    from adnmesh.runtime.bus import client_config
    from payloads import payload
    from up_runs import end_all, wait_for_line

    folder = tmp_path_factory.mktemp("hierarchy-up")
    wt_chp = (EXAMPLES / "wt-chp.yaml").read_text()
    assert "{t_s: 80, available: false, ders: [SGen1]}" in wt_chp
    (folder / "wt-chp.yaml").write_text(wt_chp.replace("{t_s: 80, available: false",
                                                       "{t_s: 40, available: false"))
    (folder / "h.yaml").write_text(HIERARCHY.format(mixed=EXAMPLES / "mixed-4.yaml"))
    assert main(["certs", str(folder / "certs"), "--config", str(folder / "h.yaml")]) == 0
    up = subprocess.Popen([sys.executable, "-m", "adnmesh", "up", "h.yaml", "--certs", "certs",
                           "--out", "run.mcap", "--summary-json", "s.json"], cwd=folder,
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    try:
        lines = wait_for_line(up, "agents ready", 600)
        said = "".join(lines)
        found = {name: re.search(pattern, said) for name, pattern in (
            ("up", r"router on (tls/[0-9.:]+)"), ("wtchp", r"wtchp on (tls/[0-9.:]+)"),
            ("mixed", r"mixed on (tls/[0-9.:]+)"))}
        assert all(found.values()), said
        for router in ("up", "mixed", "wtchp"):
            with zenoh.open(client_config([found[router].group(1)], folder / "certs",
                                          "wtchp:cpfc")) as rogue:
                for key, body in FORGED.items():
                    rogue.put(key, payload(key, body, seq=FORGED_SEQ, t_send_ns=10**10))
                if router == "wtchp":    # its own key at its own site: that does get through
                    rogue.put("adn/wtchp/event/cpfc", b"not a message")
                for _ in rogue.liveliness().get("adn/*/alive/up", timeout=1.0):
                    pass                   # a round trip behind the puts: they are out
    finally:
        (_, err), = end_all([up])
    err = "".join(lines) + err
    assert up.returncode == 0, err[-3000:]
    summary = json.loads((folder / "s.json").read_text())
    return folder, summary, err, read_recording(folder / "run.mcap")


def test_every_level_runs_as_processes_behind_its_sites_router(ran) -> None:
    folder, summary, err, recording = ran
    assert list(summary["levels"]) == ["hv", "wtchp", "mixed"]
    agents = {g: s["extra"]["agents"] for g, s in summary["levels"].items()}
    assert agents == {"hv": 5, "wtchp": 5, "mixed": 7}
    assert "sites: wtchp on tls/127.0.0.1:" in err and ", mixed on tls/127.0.0.1:" in err
    assert "17 agents ready in " in err
    # one recording per level, merged into one; all of one run
    assert recording.complete and {t.split("/")[1] for t in recording.channels} == \
        {"hv", "wtchp", "mixed"}
    alone = {g: read_recording(folder / f"run.{g}.mcap") for g in ("hv", "wtchp", "mixed")}
    assert {r.run["run_id"] for r in alone.values()} == {recording.run["run_id"]}
    top = {(m.topic, bytes(m.data), m.publish_time_ns) for r in alone.values()
           for m in r.messages}
    assert sum(len(r.messages) for r in alone.values()) == len(top)
    merged = {(m.topic, bytes(m.data), m.publish_time_ns) for m in recording.messages}
    assert merged == top and len(merged) == len(recording.messages)


def test_each_site_records_what_its_agents_publish(ran) -> None:
    """Every site router records its agents' messages (mixed's twice: before its kill, a file
    left unfinished and recovered, and after its restart), as ``up`` recorded them at the top
    (but first reports its agents sent before ``up`` heard them, which only the site has)."""
    folder, _, _, recording = ran
    merged = {(m.topic, bytes(m.data), m.publish_time_ns) for m in recording.messages}
    sites = {name: read_recording(folder / f"run.{name.replace('.', '.site.')}.mcap"
                                  if "." in name else folder / f"run.{name}.site.mcap")
             for name in ("wtchp", "mixed", "mixed.1")}
    assert not sites["mixed"].complete and sites["mixed.1"].complete
    assert sites["wtchp"].complete
    for name, site in sites.items():
        assert site.run["run_id"] == recording.run["run_id"] and site.messages, name
        grid = name.split(".")[0]
        assert {m.topic.split("/")[1] for m in site.messages} == {"hv", grid}
        assert all((m.topic, bytes(m.data), m.publish_time_ns) in merged
                   for m in site.messages if "/clock/report/" not in m.topic), name
    upper = {m.topic for m in sites["wtchp"].messages if m.topic.startswith("adn/hv/")}
    assert "adn/hv/der/wtchp/offset" in upper and all("/der/wtchp" in t for t in upper)
    before, after = (max(m.publish_time_ns for m in sites["mixed"].messages),
                     min(m.publish_time_ns for m in sites["mixed.1"].messages))
    assert before <= 8 * 10**9 <= after
    levels = load_levels(folder / "run.levels.json")
    assert set(levels.adns) == {"wtchp", "mixed"} and levels.upper.grid == "hv"


def test_the_processes_exchange_exactly_what_the_in_process_run_computes(ran) -> None:
    """The same levels run by :func:`adnmesh.sim.hierarchy_run.run_hierarchy` in this process
    send the very payloads the processes sent (the site router's restart left no trace but
    its two events)."""
    folder, _, _, recording = ran
    levels = load_levels(folder / "run.levels.json")
    upper = Level(levels.upper, levels.schedule("hv"), levels.lower_switch_rule())
    adns = {a: Level(config, levels.schedule(a)) for a, config in levels.adns.items()}
    run = run_hierarchy(upper, adns, levels.offset_delay_s)
    expected = sorted(((k, p) for k, p in run.messages
                       if "/clock/" not in k and not k.endswith(("/rejected", "/control/fault"))),
                      key=lambda m: (json.loads(m[1])["t_deliver_ns"], m[0],
                                     json.loads(m[1])["seq"]))
    got = data_messages(recording)
    site = [json.loads(p) for k, p in got if b'"kind":"site_' in p]
    assert [(e["kind"], e["subject"], e["t_send_ns"]) for e in site] == [
        ("site_down", "router/mixed", 8 * 10**9), ("site_back", "router/mixed", 8 * 10**9)]
    assert [m for m in got if b'"kind":"site_' not in m[1]] == expected


def test_the_site_router_killed_and_restarted_is_waited_for(ran) -> None:
    _, _, err, _ = ran
    killed = re.search(r"site router mixed \(pid (\d+)\) killed at 8 s \(planned\); the run "
                       rf"waits for its {SITE_AGENTS} agents", err)
    back = re.search(rf"site router mixed back \(pid (\d+)\): {SITE_AGENTS} of {SITE_AGENTS} "
                     r"agents reconnected [0-9.]+ s after the kill; the run goes on", err)
    assert killed and back, err[-3000:]
    assert killed.group(1) != back.group(1)          # a new process
    assert "Zenoh session" not in err                # the drops are the site's, said there


def test_the_upper_steps_are_within_their_design_and_the_site_cut_off_is_bumpless(ran) -> None:
    _, summary, _, _ = ran
    upper = summary["levels"]["hv"]
    assert [s["t_s"] for s in upper["steps"]] == [2.0, 14.0]
    for step in upper["steps"]:           # settled into the 5 % band, no overshoot
        assert step["figures"]["settling_time_s"] is not None, step
        assert step["figures"]["overshoot_pct"] < 1.0, step
    # each within what its entry was certified for on the exact cascade
    checks = upper["design_checks"]
    assert [c["t_s"] for c in checks] == [2.0, 14.0] and all(c["over"] == [] for c in checks)
    # the site cut off at 25 s: the level above counts its ADN unavailable, switches without
    # it bumplessly, and takes it back when it returns
    switches = [(round(s["t_s"]), s["available"]) for s in upper["switches"]]
    assert [a for _, a in switches[:2]] == [["mixed"], ["mixed", "wtchp"]]
    assert 25 < switches[0][0] < 28 and 31 <= switches[1][0] < 34
    assert all(abs(s["p_y_jump"]) < 1e-9 for s in upper["switches"])


def test_the_lower_adn_losing_its_wind_turbine_switches_on_its_own(ran) -> None:
    _, summary, _, _ = ran
    lower = summary["levels"]["wtchp"]
    assert [(round(s["t_s"]), s["available"]) for s in lower["switches"]] == [(40, ["SGen5"])]
    assert summary["levels"]["mixed"]["steps"] == [] and lower["steps"] == []


# -- the pieces ------------------------------------------------------------------------------


def test_a_levels_file_that_is_not_one_is_one_line(tmp_path) -> None:
    bad = tmp_path / "x.levels.json"
    for text, said in (('{"upper_config": 1}', "not a levels file of adnmesh up"),
                       ("[", "not a levels file of adnmesh up")):
        bad.write_text(text)
        with pytest.raises(ConfigError, match=said) as info:
            load_levels(bad)
        assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match="cannot read the levels file"):
        load_levels(tmp_path / "missing.json")


def test_an_agent_given_a_level_of_another_config_is_one_line(ran, capsys) -> None:
    from adnmesh.agents.measurement import main as measurement

    folder = ran[0]
    with pytest.raises(SystemExit) as info:
        measurement([str(EXAMPLES / "mixed-4.yaml"), "--connect", "tcp/127.0.0.1:1",
                     "--levels", str(folder / "run.levels.json"), "--level",
                     "wtchp"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("adnmesh agent: error: ") and "is not the config of level wtchp" in err
    with pytest.raises(SystemExit) as info:
        measurement([str(EXAMPLES / "mixed-4.yaml"), "--connect", "tcp/127.0.0.1:1",
                     "--level", "wtchp"])
    assert info.value.code == 2
    assert "--levels and --level go together" in capsys.readouterr().err


@pytest.mark.parametrize("flag", [["--clock", "realtime"], ["--speed", "2"], ["--view", "x.rrd"],
                                  ["--external", "cpfc"], ["--table", "t.json"]])
def test_options_of_one_grid_are_refused_for_a_hierarchy_in_one_line(tmp_path, capsys,
                                                                     flag) -> None:
    (tmp_path / "h.yaml").write_text(HIERARCHY.format(mixed=EXAMPLES / "mixed-4.yaml")
                                     .replace("wt-chp.yaml", str(EXAMPLES / "wt-chp.yaml")))
    assert main(["up", str(tmp_path / "h.yaml"), *flag]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is not for a hierarchy file" in err[0]


def test_certificates_of_one_grid_are_not_a_hierarchys(tmp_path, capsys) -> None:
    """A certificate directory made for one ADN's config lacks the levels' identities: one
    line before anything is tuned or started, naming the command that makes them."""
    (tmp_path / "h.yaml").write_text(HIERARCHY.format(mixed=EXAMPLES / "mixed-4.yaml")
                                     .replace("wt-chp.yaml", str(EXAMPLES / "wt-chp.yaml")))
    assert main(["certs", str(tmp_path / "certs"), "--config",
                 str(EXAMPLES / "mixed-4.yaml")]) == 0
    capsys.readouterr()
    assert main(["up", str(tmp_path / "h.yaml"), "--certs", str(tmp_path / "certs")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no certificate of hv:cpfc; create them with 'adnmesh certs " \
        f"{tmp_path / 'certs'} --config {tmp_path / 'h.yaml'}'" in err[0]
    assert not (tmp_path / "hv-upper").exists()


@pytest.mark.parametrize("restart, said", [
    ("{adn: other, t_s: 10}", "unknown ADN id 'other'"),
    ("{adn: mixed, t_s: 50}", "must not exceed scenario.duration_s (45)"),
    ("{adn: mixed, t_s: 10, down_s: 9}", "site_restarts[0].down_s"),
    ("{adn: mixed, t_s: 10}\n  - {adn: mixed, t_s: 10}",
     "duplicate site restart 'mixed at 10 s' (also site_restarts[0])"),
])
def test_a_site_restart_that_cannot_be_is_refused(tmp_path, restart, said) -> None:
    text = HIERARCHY.format(mixed=EXAMPLES / "mixed-4.yaml").replace(
        "{adn: mixed, t_s: 8, down_s: 0.5}", restart)
    (tmp_path / "h.yaml").write_text(text.replace("wt-chp.yaml", str(EXAMPLES / "wt-chp.yaml")))
    with pytest.raises(ConfigError, match=re.escape(said)):
        load_hierarchy(tmp_path / "h.yaml")


def test_the_clock_holds_where_told_until_released() -> None:
    """A hold at 1 s: grants stop there, :meth:`held_at` says so once every agent is idle
    with everything before it processed; released, the run goes on to its end."""
    from adnmesh.config import load_config

    config = load_config(EXAMPLES / "mixed-4.yaml")
    topology = Topology.from_config(config)
    clock = Coordinator(topology, 3 * 10**9)
    clock.hold(10**9)
    reports = {a: Report(a, 0, 0, {}, None, None) for a in topology.agents}
    for report in reports.values():
        clock.take_report(report)
    grants = clock.start()
    assert grants and all(g.until_ns <= 10**9 for g in grants)
    assert clock.held_at() is None                     # granted, not idle yet
    while grants:
        for g in grants:                               # nothing happens before the hold
            clock.take_report(Report(g.agent, 10**9, 0, {}, None, g.until_ns))
        grants = clock.grants()
    assert clock.held_at() == 10**9 and not clock.finished
    after = clock.release(10**9)
    assert after and all(g.until_ns > 10**9 for g in after) and clock.held_at() is None


def _held_clock(holds: int = 1):
    """mixed-4's agents on a clock held at 1 s (``holds`` times), started; its topology."""
    from adnmesh.config import load_config

    topology = Topology.from_config(load_config(EXAMPLES / "mixed-4.yaml"))
    clock = Coordinator(topology, 3 * 10**9)
    for _ in range(holds):
        clock.hold(10**9)
    for agent in topology.agents:
        clock.take_report(Report(agent, 0, 0, {}, None, None))
    return clock, topology


def _windows(clock, grants, sent=None):
    """Every agent of ``grants`` processes its window (it had the messages it waited for)
    and reports its next event at 1 s, ``sent[agent]`` sent; the grants that follow and
    which of them do not advance."""
    for g in grants:
        clock.take_report(Report(g.agent, 10**9, g.expect, (sent or {}).pop(g.agent, {}), None,
                                 g.until_ns))
    granted = {a: clock.granted_ns(a) for a in clock.agents}
    grants = clock.grants()
    return grants, [g for g in grants if g.until_ns == granted[g.agent]]


def test_a_hold_is_reached_only_when_nothing_is_in_flight() -> None:
    """The CPFC sends P_Y just before the hold, delivered just after it: the DERs, idle at the
    hold, have not counted it. They get a grant that does not advance, wait for it and report;
    only then is the hold reached (a router killed earlier could have lost it)."""
    clock, topology = _held_clock()
    key = next(k for k in topology.publishes("cpfc") if topology.receivers.get(k))
    receivers = set(topology.receivers[key])
    grants, sent = clock.start(), {"cpfc": {key: (1, 10**9 + 5)}}
    synced = []
    while grants and not synced:
        grants, synced = _windows(clock, grants, sent)
    assert {g.agent for g in synced} == receivers and all(g.expect == 1 for g in synced)
    assert clock.held_at() is None                 # they have not reported yet
    grants, synced = _windows(clock, synced)
    assert grants == [] and clock.held_at() == 10**9


def test_two_holds_at_one_time_need_two_releases() -> None:
    clock, _ = _held_clock(holds=2)
    grants = clock.start()
    while grants:
        grants, _ = _windows(clock, grants)
    assert clock.held_at() == 10**9
    assert clock.release(10**9) == [] and clock.held_at() == 10**9     # one still holds
    assert all(g.until_ns > 10**9 for g in clock.release(10**9))
    assert clock.held_at() is None


class _Fakes:
    """A held clock and two levels' launches for :meth:`SiteRouter.supervise`, and a wall
    clock the test moves."""

    def __init__(self, monkeypatch) -> None:
        from types import SimpleNamespace

        from adnmesh.runtime import site_router
        from adnmesh.wire.keys import Keys

        self.now, self.held, self.released, self.said, self.alive = 100.0, None, [], [], set()
        monkeypatch.setattr(site_router.time, "monotonic", lambda: self.now)
        self.launches = [SimpleNamespace(
            config=SimpleNamespace(grid=grid), keys=Keys(grid),
            roster=SimpleNamespace(alive_now=lambda: set(self.alive)),
            recorder=SimpleNamespace(counts=lambda: {}),
            injector=SimpleNamespace(planned_drops=set()),
            options=SimpleNamespace(log=self.said.append),
            outbox=SimpleNamespace(send=lambda key, t, **body: self.said.append(body["kind"])))
            for grid in ("hv", "mixed")]

    def held_at(self):
        return self.held

    def sent_per_key(self):
        return {}

    def hold(self, at_ns):
        pass

    def release(self, at_ns):
        self.released.append(at_ns)
        self.held = None


def test_a_site_restart_goes_in_time_order_and_releases_without_a_session_gone_for_good(
        monkeypatch) -> None:
    from adnmesh.runtime.site_router import BACK_WITHIN_S, PlannedRestart, SiteRouter

    fakes = _Fakes(monkeypatch)
    site = SiteRouter("mixed", Path("mixed.yaml"), "tcp/127.0.0.1:1",
                      {"mixed": ("cpfc", "der/SGen1"), "hv": ("der/mixed",)},
                      [PlannedRestart(2 * 10**9, 0.5), PlannedRestart(10**9, 0.5)])
    started, killed = [], []
    monkeypatch.setattr(site, "start", lambda upstream: started.append(upstream))
    monkeypatch.setattr(site, "kill", lambda: killed.append(fakes.now))
    site.hold(fakes)                                # (file order 2 s, 1 s: taken 1 s first)
    fakes.alive = {"cpfc", "der/SGen1", "der/mixed"}
    fakes.held = 2 * 10**9                          # not this one's time
    site.supervise(fakes, fakes.launches)
    assert killed == []
    fakes.held = 10**9
    site.supervise(fakes, fakes.launches)
    assert killed == [100.0] and [r.state for r in site.restarts] == ["down", "planned"]
    assert fakes.launches[1].injector.planned_drops == {"cpfc", "der/SGen1"}
    fakes.now, fakes.alive = 100.6, set()           # every session gone, down_s over
    site.supervise(fakes, fakes.launches)
    assert len(started) == 1 and site.restarts[0].state == "back"
    fakes.now, fakes.alive = 101.0, {"cpfc", "der/mixed"}     # der/SGen1 does not come back
    site.supervise(fakes, fakes.launches)
    assert fakes.released == []
    fakes.now = 100.0 + BACK_WITHIN_S + 0.1
    site.supervise(fakes, fakes.launches)
    assert fakes.released == [10**9] and site.restarts[0].state == "done"
    assert any("2 of 3 agents reconnected" in line for line in fakes.said)
    # the one gone for good is the injector's again; the ones back are, once it sees them
    assert fakes.launches[1].injector.planned_drops == {"cpfc"}
    assert site.restarts[1].state == "planned"


def test_the_access_control_of_a_hierarchy_gives_each_level_its_own_keys(ran) -> None:
    """The secure profile's rights over the hierarchy's topology: an agent is ``<grid>:<id>``
    (a certificate of one level's CPFC is no other level's), its liveliness its grid's, and
    the three routes that cross levels are the only rights across them."""
    from adnmesh.runtime.acl import access_control, rights
    from adnmesh.runtime.identity import check_identity

    levels = load_levels(ran[0] / "run.levels.json")
    found = rights(levels.topology)
    cpfc, site = found["wtchp:cpfc"], found["hv:der/wtchp"]
    assert cpfc.token == "adn/wtchp/alive/cpfc" and cpfc.watches == ("adn/wtchp/alive/up",)
    assert "adn/wtchp/cpfc/actuator" in cpfc.publishes
    assert all(k.startswith("adn/wtchp/") for k in cpfc.publishes)
    assert "adn/hv/der/wtchp/offset" in cpfc.receives           # its offset from above
    assert "adn/hv/der/wtchp/offset" in site.publishes and site.token == "adn/hv/alive/der/wtchp"
    assert "adn/wtchp/measurement/exchange" in site.receives
    assert "adn/wtchp/cpfc/actuator" in found["hv:cpfc"].receives
    assert not any(k.startswith("adn/hv/") for k in found["mixed:cpfc"].publishes)
    section = access_control(levels.topology, ["router/wtchp", "router/mixed"])
    peer = next(r for r in section["rules"] if r["id"] == "router/mixed is sent")
    assert peer["key_exprs"] == ["adn/hv/**", "adn/mixed/**", "adn/wtchp/**"]
    assert check_identity("wtchp:der/SGen1") == "wtchp:der/SGen1"
    with pytest.raises(Exception, match="not an identity"):
        check_identity("wtchp:bogus")


def test_one_levels_certificate_takes_nothing_of_anothers_keys(ran) -> None:
    """The rogue's forged messages (:data:`FORGED`, with wtchp's CPFC certificate, at ``up``'s
    router and at both site routers) never got past a router: nothing of them is recorded,
    no agent rejected anything (nothing reached one), and the run sent exactly the in-process
    run's messages (above). Its junk on its own key at its own site got through, to be
    rejected by the recorder: the puts were made. Without certificates the same forged P_Y
    stalls the run: the open profile trusts every session."""
    _, summary, _, recording = ran
    assert {s["extra"]["profile"] for s in summary["levels"].values()} == {"secure"}
    # up's router saw the rogue's link: wtchp's CPFC is a client of its site router only
    assert summary["levels"]["hv"]["extra"]["unexpected_sessions"] == 1
    assert summary["levels"]["hv"]["extra"]["links_accepted"] >= 6   # 3 agents, 2 sites, it
    assert {g: s["extra"]["rejected_by_recorder"] for g, s in summary["levels"].items()} == \
        {"hv": 0, "wtchp": 1, "mixed": 0}          # the junk on its own key, and only that
    assert all(s["extra"]["rejected_by_agents"] == 0 for s in summary["levels"].values())
    assert not any(json.loads(m.data)["seq"] == FORGED_SEQ for m in recording.messages
                   if m.topic in FORGED)


def test_a_site_recorder_takes_each_level_on_one_subscriber_and_only_its_agents_keys(
        ran, tmp_path) -> None:
    """One subscriber per level, not per key: a report rides the last sample of its window on
    any of its agent's keys, and per-key subscribers (a Zenoh delivery thread each) let a
    later report overtake an earlier one, which the site's tap then rejected as replayed.
    Every key the site's agents send falls under exactly one subscriber; what else a pattern
    brings (up's grants to them) is not queued."""
    import queue

    import zenoh

    from adnmesh.runtime.site_recorder import SiteRecorder
    from adnmesh.sim.hierarchy_levels import load_levels

    folder = ran[0]
    recorder = SiteRecorder(tmp_path / "site.mcap", load_levels(folder / "run.levels.json"),
                            "mixed", "r")
    declared = []

    class Session:
        def declare_subscriber(self, key, callback):
            declared.append((key, callback))
            return type("Handle", (), {"undeclare": lambda self: None})()

    class Bytes(bytes):
        def to_bytes(self) -> bytes:
            return bytes(self)

    class Queued(queue.Queue):
        def __init__(self) -> None:
            super().__init__()
            self.keys: list = []

        def put_nowait(self, item) -> None:
            self.keys.append(item[0])
            super().put_nowait(item)

    recorder._queue = Queued()
    recorder.declare(Session())
    try:
        assert len(declared) == 2
        for key in recorder.keys:
            assert sum(zenoh.KeyExpr(p).intersects(zenoh.KeyExpr(key))
                       for p, _ in declared) == 1, key
        on_sample = declared[0][1]
        for key in ("adn/mixed/clock/grant/der/SGen2", "adn/mixed/der/SGen2/state"):
            on_sample(type("Sample", (), {"key_expr": key, "payload": Bytes(b"{}"),
                                          "attachment": None})())
        assert recorder._queue.keys == ["adn/mixed/der/SGen2/state"]
    finally:
        recorder.close()
