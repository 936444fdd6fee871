"""A hierarchy of ADNs on the sim clock: the site agent, the ADN taking its reference offset
from above, the hierarchy's topology, and one shared ``adnmesh cascade --run`` of two small
ADNs with two upper steps, a site cut off and back, and plants leaving both ADNs."""
import contextlib
import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest

from adnmesh.cli import main
from adnmesh.config import load_config
from adnmesh.control.adn_site import AdnSite
from adnmesh.control.cpfc_controller import CPFC, GainSchedule
from adnmesh.loopmodel.step_figures import step_figures
from adnmesh.recording import read_recording
from adnmesh.sim.hierarchy_topology import hierarchy_topology, qualified
from adnmesh.wire.keys import Keys
from adnmesh.wire.units import ns
from payloads import message

EXAMPLES = Path(__file__).resolve().parent.parent / "configs" / "examples"

HIERARCHY = f"""name: hv
t_meas_s: 0.2
constraints: {{disk_margin_min: 1.5, overshoot_max_pct: 1.0}}
adns:
  - {{id: wtchp, config: {EXAMPLES / 'wt-chp.yaml'}, t_com_s: 0.3, hv_bus: HV1 Bus 29}}
  - {{id: mixed, config: {EXAMPLES / 'mixed-4.yaml'}, t_com_s: 0.25, hv_bus: HV1 Bus 41,
     replaces: []}}
hv_grid: {{simbench_code: 1-HV-mixed--0-sw}}
scenario:
  duration_s: 95
  p_ref_steps: [{{t_s: 5, delta_w: 1.0e+6}}, {{t_s: 20, delta_w: -0.5e+6}}]
faults:
  - {{kind: der_offline, der: wtchp, t_s: 35, duration_s: 15}}
  - {{kind: der_offline, der: wtchp, t_s: 85}}
"""
"""Both ADNs hang from SimBench's HV grid (wtchp in place of the MV stand-ins at its bus, mixed
beside them); wt-chp loses its WT at 80 s, mixed-4 two of its four plants (their own
scenarios); then wtchp's site is cut off again, for good."""

STEP_W = 1.0e6
FINAL_W = 0.5e6   # the reference after both steps, above the operating point


def final_ref_w(topics) -> float:
    """The upper reference after both steps, W (the HV grid's exchange at the operating
    point plus both steps)."""
    _, ref = series(topics, "adn/hv/scenario/p_ref", "p_ref_w")
    assert ref[-1] - ref[0] == FINAL_W
    return float(ref[-1])


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    """One ``adnmesh cascade --run``, shared by the tests below: (out folder, printed,
    recording messages by topic)."""
    folder = tmp_path_factory.mktemp("hierarchy")
    path = folder / "h.yaml"
    path.write_text(HIERARCHY)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["cascade", str(path), "--out", str(folder / "out"), "--run"]) == 0
    recording = read_recording(folder / "out" / "hv.run.mcap")
    topics: dict[str, list] = {}
    for m in recording.messages:
        topics.setdefault(m.topic, []).append(json.loads(m.data))
    return folder / "out", printed.getvalue(), topics, recording


def hv_gains(out: Path) -> dict[str, float]:
    """The HV grid's ``dP_IP/dP`` at each ADN's bus at the operating point, by central
    differences of pandapower's ``runpp`` on the net the command wrote (loads as
    impedances, as the upper config solves it)."""
    import pandapower as pp

    from adnmesh.grid.simbench_net import loads_as_impedances

    net = pp.from_json(str(out / "hv.hv.json"))
    loads_as_impedances(net)
    upper = load_config(out / "hv.upper.yaml")
    gains = {}
    for der in upper.ders:
        row = net.sgen.index[net.sgen.name == der.id][0]
        exchange = []
        for dp in (-1e-3, 1e-3):      # MW
            net.sgen.loc[row, "p_mw"] = der.p_sched_w / 1e6 + dp
            pp.runpp(net)
            exchange.append(-net.res_ext_grid.p_mw.sum())
        net.sgen.loc[row, "p_mw"] = der.p_sched_w / 1e6
        gains[der.id] = (exchange[1] - exchange[0]) / 2e-3
    return gains


def series(topics, topic: str, field: str):
    bodies = sorted(topics[topic], key=lambda b: b["t_send_ns"])
    return (np.array([b["t_send_ns"] for b in bodies]) / 1e9,
            np.array([b[field] for b in bodies], dtype=float))


def switches(topics, topic: str) -> list[dict]:
    return sorted((b for b in topics[topic] if "switch" in b), key=lambda b: b["t_send_ns"])


def test_the_run_is_one_recording_of_every_level(ran) -> None:
    out, printed, topics, recording = ran
    assert recording.complete
    assert {t.split("/")[1] for t in topics} == {"hv", "wtchp", "mixed"}
    assert (out / "hv.run.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "ran hv: 2 ADNs, 17 agents, 95 s" in printed
    # the site agents speak for their ADNs in the upper grid; each ADN's CPFC hears them
    assert {"adn/hv/der/wtchp/offset", "adn/hv/der/mixed/offset", "adn/wtchp/measurement/exchange",
            "adn/hv/der/wtchp/state", "adn/hv/der/wtchp/heartbeat"} <= set(topics)
    # each level alone beside it: together every message, each a one-grid recording
    alone = {g: read_recording(out / f"hv.run.{g}.mcap") for g in ("hv", "wtchp", "mixed")}
    assert sum(len(r.messages) for r in alone.values()) == len(recording.messages)
    assert all({t.split("/")[1] for t in r.channels} == {g} for g, r in alone.items())


def test_the_upper_level_acts_on_the_hv_grids_exchange(ran) -> None:
    """The upper P_IP is the HV grid's exchange with the level above (pandapower's ``runpp`` of
    the net the command wrote, every ADN at its operating point), wtchp in place of its bus's
    MV stand-ins, mixed beside them."""
    import pandapower as pp

    from adnmesh.grid.simbench_net import loads_as_impedances

    out, _, topics, _ = ran
    net = pp.from_json(str(out / "hv.hv.json"))

    def named(kind, name):
        return bool(net[kind].in_service[net[kind].name == name].iloc[0])

    assert not named("load", "HV1 Load 46") and not named("sgen", "HV1 Sgen 49")
    assert named("load", "HV1 Load 47") and named("sgen", "HV1 Sgen 50")
    upper = load_config(out / "hv.upper.yaml")
    for der in upper.ders:
        net.sgen.loc[net.sgen.name == der.id, "p_mw"] = der.p_sched_w / 1e6
    loads_as_impedances(net)
    pp.runpp(net)
    t, p = series(topics, "adn/hv/measurement/p_ip", "p_ip_w")
    assert p[0] == pytest.approx(-net.res_ext_grid.p_mw.sum() * 1e6, abs=1.0)
    assert p[0] > 1e9       # the HV grid's export at lW, not the ADNs' few MW
    # the ADNs' schedules are their lowest: the operating point is the reachable range's lower
    # end, found by power flows to their tolerance, and it is no reference out of reach
    kinds = [b["kind"] for b in topics["adn/hv/event/cpfc"]]
    assert "reference_clipped" not in kinds and "reference_reachable" not in kinds


def test_the_two_stage_power_flow_is_the_combined_nets(ran) -> None:
    """The rural ADN solved alone and its exchange injected at HV1 Bus 17 of the run's HV net
    (the upper level's model) against ``runpp`` of the HV and MV nets as one (the MV net's 110 kV
    bus fused with HV1 Bus 17, its external grid gone): at the operating point and with every
    DER 20 % above its schedule (1.1 MW more).
    """
    import copy

    import pandapower as pp
    from pandapower.toolbox import fuse_buses, merge_nets

    from adnmesh.control.operating_point import initial_p_ip_w, initial_q_ip_var
    from adnmesh.grid.hv_attach import Attachment, attach_adns, hv_base
    from adnmesh.grid.simbench_net import grid_net, loads_as_impedances

    config = load_config(EXAMPLES.parent / "simbench.yaml")
    p_sched = sum(d.p_sched_w for d in config.ders)
    capacity = sum(d.p_inst_w for d in config.ders)
    p0, q0 = initial_p_ip_w(config), initial_q_ip_var(config)
    attach = Attachment("rural", "HV1 Bus 17", capacity, p0 - p_sched, q0)
    two_stage = hv_base("pandapower", str(ran[0] / "hv.hv.json"), None)   # 1-HV-mixed at lW
    attach_adns(two_stage, [attach])
    loads_as_impedances(two_stage)
    # the combined net: the HV net with the stand-ins gone and the MV net in their place
    hv = copy.deepcopy(two_stage)
    hv.sgen.loc[hv.sgen.name.str.startswith("rural"), "in_service"] = False
    mv = grid_net(config.simbench_code, "lW", "impedance")
    for net in (hv, mv):        # merge_nets refuses NaN in boolean columns
        for column in ("controllable", "reactive_capability_curve"):
            if column in net.sgen:
                net.sgen[column] = net.sgen[column].astype(object).fillna(False).astype(bool)
    mv_slack_bus = int(mv.ext_grid.bus.iloc[0])
    mv.ext_grid["in_service"] = False
    combined, lookup = merge_nets(hv, mv, validate=False, return_net2_reindex_lookup=True)
    hv_bus = int(hv.bus.index[hv.bus.name == "HV1 Bus 17"][0])
    fuse_buses(combined, hv_bus, {lookup["bus"][mv_slack_bus]})
    combined.ext_grid = combined.ext_grid[combined.ext_grid.in_service.astype(bool)]
    mv.ext_grid["in_service"] = True
    for share in (1.0, 1.2):
        for d in config.ders:
            for net in (mv, combined):
                net.sgen.loc[net.sgen.name == d.sgen, "p_mw"] = share * d.p_sched_w / 1e6
        pp.runpp(mv)
        p_ip = -mv.res_ext_grid.p_mw.sum() * 1e6
        two_stage.sgen.loc[two_stage.sgen.name == "rural", "p_mw"] = (p_sched + p_ip - p0) / 1e6
        pp.runpp(two_stage)
        pp.runpp(combined)
        error_w = (combined.res_ext_grid.p_mw.sum() - two_stage.res_ext_grid.p_mw.sum()) * 1e6
        # at the operating point below 1 kW of 1.25 GW; 1.1 MW away the ADN's Q (held at its
        # operating point's) has moved by 0.1 Mvar, and the HV losses with it: a few kW
        assert abs(error_w) < (1e3 if share == 1.0 else 5e3), (share, error_w)
        v_hv = two_stage.res_bus.vm_pu[hv_bus]
        assert abs(v_hv - float(mv.ext_grid.vm_pu.iloc[0])) < 1e-3    # the interface voltage


def test_inspect_reads_the_upper_level_alone_with_its_design(ran, capsys) -> None:
    out = ran[0]
    assert main(["inspect", str(out / "hv.run.hv.mcap")]) == 0
    printed = capsys.readouterr().out
    assert "P_IP after each P_ref step" in printed and "designed" in printed


def test_the_levels_recordings_merge_into_the_recording_of_every_level(ran, capsys,
                                                                      tmp_path) -> None:
    """``adnmesh merge`` of the three levels' recordings holds what the run's recording of
    every level holds, in delivery-time order (a message recorded twice is kept once:
    ``test_merge``, and the sites' recordings of ``test_hierarchy_up``)."""
    out = ran[0]
    levels = [str(out / f"hv.run.{g}.mcap") for g in ("hv", "wtchp", "mixed")]
    merged = tmp_path / "merged.mcap"
    assert main(["merge", str(merged), *levels]) == 0
    assert "(0 recorded twice, kept once), grids hv" in capsys.readouterr().out

    def held(path):
        return sorted((m.topic, m.log_time_ns, m.publish_time_ns, m.data)
                      for m in read_recording(path).messages)

    assert held(merged) == held(out / "hv.run.mcap")
    times = [m.log_time_ns for m in read_recording(merged).messages]
    assert times == sorted(times)


def test_inspect_shows_one_grid_of_the_recording_of_every_level(ran, capsys, tmp_path) -> None:
    """The recording of every level: the upper level's figures by default (its own grid),
    another's with --grid, in one pass each (and plot the same); each grid's series as read
    alone."""
    from adnmesh.results.series import read_run, read_runs

    out = ran[0]
    merged = out / "hv.run.mcap"
    assert main(["inspect", str(merged)]) == 0
    printed = capsys.readouterr().out
    (line,) = [x for x in printed.splitlines() if x.startswith("3 grids: ")]
    assert "the figures below are grid hv's" in line
    assert sorted(line[len("3 grids: "):].split(";")[0].split(", ")) == ["hv", "mixed", "wtchp"]
    steps = printed.split("P_IP after each P_ref step")[1].split("tracking error")[0]
    assert "+1.000" in steps and "-0.500" in steps and "designed" in steps   # the upper steps
    assert main(["inspect", str(merged), "--grid", "mixed", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["figures_of"] == "mixed" and sorted(report["grids"]) == ["hv", "mixed", "wtchp"]
    assert report["topics"] and all(t["topic"].startswith("adn/mixed/") for t in report["topics"])
    assert report["figures"]["gain_switches"] == 1       # mixed's own switch at 80 s
    assert main(["inspect", str(merged), "--grid", "nope"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--grid nope: not a grid of" in err[0] and "wtchp" in err[0]
    # plot: the same choice of grid
    for argv in (["--grid", "mixed"], []):
        figure = tmp_path / f"plot{len(argv)}.png"
        assert main(["plot", str(merged), "-o", str(figure), *argv]) == 0
        assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    capsys.readouterr()
    assert main(["plot", str(merged), "-o", str(tmp_path / "x.png"), "--grid", "nope"]) == 2
    assert "--grid nope: not a grid of" in capsys.readouterr().err
    # export: every grid's series; the Foxglove layout of one grid, with that grid's DERs
    assert main(["export", str(merged), "--foxglove-layout", str(tmp_path / "l.json")]) == 0
    assert "Foxglove layout for grid hv and 2 DERs" in capsys.readouterr().out
    assert main(["export", str(merged), "--foxglove-layout", str(tmp_path / "m.json"),
                 "--grid", "mixed"]) == 0
    assert "Foxglove layout for grid mixed and 4 DERs" in capsys.readouterr().out
    assert "adn/hv/" not in (tmp_path / "m.json").read_text()
    # replay: every grid's series, the layout a tab per grid with that grid's plots only
    from adnmesh.results.rerun_export import blueprint
    from adnmesh.results.series import extract

    tabs = blueprint(extract(read_recording(merged))).root_container
    assert sorted(str(t.name) for t in tabs.contents) == ["hv", "mixed", "wtchp"]
    def paths(container) -> list[str]:
        found = []
        for item in container.contents:
            found += (paths(item) if hasattr(item, "kind") else
                      [str(p) for p in item.contents or []])
        return found

    for tab in tabs.contents:
        shown = paths(tab)
        assert shown and all(p.startswith(f"/adn/{tab.name}/") for p in shown), tab.name
    assert main(["export", str(merged), "--csv", str(tmp_path / "csv")]) == 0   # names apart
    names = {p.name for p in (tmp_path / "csv").iterdir()}
    assert {"hv.measurement_p_ip.csv", "wtchp.measurement_p_ip.csv",
            "mixed.measurement_p_ip.csv"} <= names
    # each grid's availability apart: the upper SI names the ADNs only, and the whole file
    # has the events of the grids read apart, no more
    header = (tmp_path / "csv" / "hv.availability_si.csv").read_text().splitlines()[0]
    assert header == "time_s,DERs available,mixed available,wtchp available"
    whole = read_run(merged)[0].run
    assert len(whole.events) == sum(len(part[0].events) for part in read_runs(merged)[1].values())
    _, parts = read_runs(merged)
    alone = read_run(merged, grid="wtchp")[0].run.one("p_ip")
    together = parts["wtchp"][0].one("p_ip")
    assert np.array_equal(alone.t_ns, together.t_ns) and np.array_equal(alone.values,
                                                                          together.values)


def test_the_upper_step_follows_the_cascade_certificate(ran) -> None:
    """The agents' run against the exact cascade's step (the certificate's own numerics):
    the first step, with both ADNs, rises and settles as certified."""
    out, printed, topics, _ = ran
    rows = {r["adns"]: r for r in csv.DictReader((out / "hv.cascade.csv").open())}
    certified = rows["wtchp mixed"]
    t, p = series(topics, "adn/hv/measurement/p_ip", "p_ip_w")
    t_ref, ref = series(topics, "adn/hv/scenario/p_ref", "p_ref_w")
    assert ref[0] == pytest.approx(p[0]) and ref[1] - ref[0] == STEP_W
    inside = (t >= 5.0) & (t < 20.0)
    f = step_figures(t[inside] - 5.0, (p[inside] - ref[0]) / STEP_W)
    assert f.rise_time_s == pytest.approx(float(certified["rise_time_s"]), abs=0.02)
    assert f.settling_time_s == pytest.approx(float(certified["settling_time_s"]), abs=0.02)
    assert f.overshoot_pct <= 1.0
    assert "certified: rise" in printed and "OVER THE DESIGN" not in printed


def test_a_site_cut_off_is_left_out_bumplessly_and_its_adn_holds_its_reference(ran) -> None:
    _, printed, topics, _ = ran
    drop, back = switches(topics, "adn/hv/cpfc/p_y")[:2]
    # heard of within the heartbeat timeout (2.5 s) and the SI link after the cut at 35 s
    assert 35.0 < drop["t_send_ns"] / 1e9 < 35.0 + 2.5 + 1.0
    assert drop["w"].get("wtchp", 0) == 0 and drop["w"]["mixed"] > 0
    assert 50.0 < back["t_send_ns"] / 1e9 < 52.0 and back["w"]["wtchp"] > 0
    # the ADN runs on its last reference while cut off: its offset and its P_ref stay
    t_off, offset = series(topics, "adn/hv/der/wtchp/offset", "offset_w")
    held = offset[(t_off > 35.0) & (t_off < back["t_send_ns"] / 1e9)]
    assert held.size > 10 and np.ptp(held) == 0 and held[0] > 0
    t_ref, _ = series(topics, "adn/wtchp/scenario/p_ref", "p_ref_w")
    assert not np.any((t_ref > 36.0) & (t_ref < back["t_send_ns"] / 1e9))   # no new P_ref
    # neither the drop nor the return moves the sum of the exchanges by more than 1 % of a step
    t, p = series(topics, "adn/hv/measurement/p_ip", "p_ip_w")
    for switch in (drop, back):
        at = switch["t_send_ns"] / 1e9
        window = (t >= at) & (t < min(at + 10.0, 80.0))
        assert np.max(np.abs(p[window] - final_ref_w(topics))) < 0.01 * STEP_W, at
    assert "switch at" in printed


def test_adns_losing_plants_are_compensated_from_above(ran) -> None:
    """At 80 s wtchp's WT and two of mixed's plants leave: each ADN switches its own gains,
    and the upper loop brings the sum back towards its reference (slowly: what is left are
    CHPs, and the upper gains stay those of the ADNs with all their plants)."""
    _, _, topics, _ = ran
    for adn in ("wtchp", "mixed"):
        (switch,) = [s for s in switches(topics, f"adn/{adn}/cpfc/p_y")
                     if s["t_send_ns"] > ns(80.0)]
        assert switch["t_send_ns"] < ns(81.0)
    t, p = series(topics, "adn/hv/measurement/p_ip", "p_ip_w")
    after = (t > 80.0) & (t < 85.0)
    worst = np.max(np.abs(p[after] - final_ref_w(topics)))
    assert worst > 0.05 * STEP_W                       # the loss is felt ...
    assert p[after][-1] - np.min(p[after]) > 0.2 * worst   # ... and taken back from above


def test_the_site_agent_turns_set_points_into_offsets_and_holds_when_cut_off() -> None:
    upper = load_config(EXAMPLES.parent / "simbench.yaml").model_copy(update={"grid": "hv"})
    der = upper.ders[0].model_copy(update={"p_sched_w": 1e5})
    site = AdnSite(der, upper, p_ip0_w=3e6)
    keys = Keys("hv")
    weights = {d.id: 1.0 for d in upper.ders}
    out = site.on_message(ns(0.5), message(keys.of("p_y"), ns(0.5), {
        "p_y": 0.1, "p_ref_w": 0.0, "kp": 1e-7, "ki": 1e-7, "entry": 0, "w": weights}))
    (sent,) = [o for o in out if o.key == keys.of("adn_offset", der.id)]
    assert sent.body["offset_w"] == pytest.approx(0.1 * der.p_inst_w)
    # the ADN's exchange, as the upper DER's infeed: schedule + change from its operating point
    site.on_message(ns(0.6), message(keys.of("adn_exchange"), ns(0.6), {"p_ip_w": 3.2e6},
                                     src="measurement"))
    while site.next_timer_ns() <= ns(0.6):
        out = site.on_timer(site.next_timer_ns())
    (state,) = [o for o in out if o.key == keys.of("der_state", der.id)]
    assert state.body["p_w"] == pytest.approx(1e5 + 2e5) and state.body["held"] == 0
    # every DER of the ADN at a limit upwards: the upper measurement hears it (anti-windup)
    site.on_message(ns(0.61), message(keys.of("adn_exchange"), ns(0.61),
                                      {"p_ip_w": 3.2e6, "held": "up"}, src="measurement"))
    out = site.on_timer(site.next_timer_ns())
    (state,) = [o for o in out if o.key == keys.of("der_state", der.id)]
    assert state.body["held"] == 1
    # no command for longer than the watchdog: the offset stays, repeated unchanged
    offsets = []
    while site.next_timer_ns() <= ns(4.0):
        t = site.next_timer_ns()
        site.on_message(t, message(keys.of("adn_exchange"), t, {"p_ip_w": 3.2e6},
                                   src="measurement"))
        offsets += [o.body["offset_w"] for o in site.on_timer(t)
                    if o.key == keys.of("adn_offset", der.id)]
    assert site.der_controller.mode == "watchdog" and offsets
    assert offsets == pytest.approx([0.1 * der.p_inst_w] * len(offsets))
    # back, but in an entry without it: it keeps the offset until a weight comes
    out = site.on_message(ns(4.1), message(keys.of("p_y"), ns(4.1), {
        "p_y": 0.3, "p_ref_w": 0.0, "kp": 1e-7, "ki": 1e-7, "entry": 1,
        "w": {d: 0.0 for d in weights}}))
    assert site.plant.offset_w == pytest.approx(0.1 * der.p_inst_w)
    site.on_message(ns(4.2), message(keys.of("p_y"), ns(4.2), {
        "p_y": 0.3, "p_ref_w": 0.0, "kp": 1e-7, "ki": 1e-7, "entry": 2, "w": weights}))
    assert site.plant.offset_w == pytest.approx(0.3 * der.p_inst_w)


def test_a_silent_adn_is_an_unavailable_actuator_of_the_level_above() -> None:
    upper = load_config(EXAMPLES.parent / "simbench.yaml").model_copy(update={"grid": "hv"})
    site = AdnSite(upper.ders[0], upper, p_ip0_w=0.0)
    beats = []
    while site.next_timer_ns() <= ns(3.0):
        beats += [o.body for o in site.on_timer(site.next_timer_ns())
                  if o.key.endswith("/heartbeat")]
    assert beats[0]["available"] and not beats[-1]["available"]


def test_the_adns_cpfc_takes_the_offset_from_above_into_its_reference() -> None:
    config = load_config(EXAMPLES / "wt-chp.yaml")
    cpfc = CPFC(config, GainSchedule(config, None))
    keys = Keys(config.grid)
    first = [o for o in cpfc.on_timer(0) if o.key == keys.of("p_ref")]
    start = first[0].body["p_ref_w"]
    assert "offset_w" not in first[0].body        # an ADN alone: no offset said
    cpfc.on_message(ns(0.005), message(Keys("hv").of("adn_offset", "x"), ns(0.005),
                                       {"offset_w": 2.5e5}))
    sent = [o for o in cpfc.on_timer(ns(0.01)) if o.key == keys.of("p_ref")]
    assert sent[0].body == {"p_ref_w": start + 2.5e5, "offset_w": 2.5e5}   # which part it is
    # the same offset again changes nothing; a smaller one lowers the reference
    cpfc.on_message(ns(0.015), message(Keys("hv").of("adn_offset", "x"), ns(0.015),
                                       {"offset_w": 2.5e5}))
    assert not [o for o in cpfc.on_timer(ns(0.02)) if o.key == keys.of("p_ref")]
    cpfc.on_message(ns(0.025), message(Keys("hv").of("adn_offset", "x"), ns(0.025),
                                       {"offset_w": 1e5}))
    sent = [o for o in cpfc.on_timer(ns(0.03)) if o.key == keys.of("p_ref")]
    assert sent[0].body == {"p_ref_w": start + 1e5, "offset_w": 1e5}


def test_an_offset_from_above_is_no_step_of_an_adns_reference() -> None:
    """The summary's steps (and the figures' and the watches') are the changes of P_ref less
    the offset it includes: the offset is an input the ADN tracks."""
    from adnmesh.loopmodel.step_figures import reference_step_figures
    from adnmesh.results.summary import RunSeries

    t_ref = [0, ns(1.0), ns(1.2), ns(5.0), ns(5.2)]
    p_ref = [10e6, 10.1e6, 10.15e6, 11.15e6, 11.1e6]
    offset = [0.0, 0.1e6, 0.15e6, 0.15e6, 0.1e6]      # a step of +1 MW of its own at 5 s
    t_ip = np.arange(0, ns(10.0), ns(0.1))
    p_ip = np.where(t_ip < ns(5.0), 10.1e6, 11.1e6)
    alone = reference_step_figures(t_ip, p_ip, t_ref, p_ref, [], ns(10.0))
    assert [round(s.t_s, 3) for s in alone] == [1.0, 1.2, 5.0, 5.2]     # every change
    steps = reference_step_figures(t_ip, p_ip, t_ref, p_ref, [], ns(10.0), offset_w=offset)
    assert [(round(s.t_s, 3), s.step_w) for s in steps] == [(5.0, 1e6)]
    assert steps[0].window_s == pytest.approx(5.0)    # to the end: the offsets do not cut it
    series = RunSeries()
    for t, p, o in zip(t_ref, p_ref, offset):
        series.add("p_ref", {"t_send_ns": t, "p_ref_w": p, **({"offset_w": o} if o else {})})
    assert series.step_records() == [3] and series.step_times_ns() == [ns(5.0)]
    series.add("p_ref", {"t_send_ns": ns(6.0), "p_ref_w": 12.1e6, "offset_w": 0.1e6})
    assert series.step_times_ns() == [ns(5.0), ns(6.0)]     # found on from where it was
    series.p_ref_w, series.p_ref_offset_w = [1.0, 2.0], [0.0, 0.0]   # assigned anew
    series.p_ref_t_ns = [0, 7]
    assert series.step_records() == [1]
    series.p_ref_offset_w = [0.0, 1.0]                                 # the offsets alone
    assert series.step_records() == []


def test_an_adns_cpfc_says_offsets_that_are_no_steps_at_any_operating_point() -> None:
    """At a P_ref that is no round number (the rural ADN's 16.55 MW), P_ref less its offset
    carries rounding: no record of offsets alone is a step, and a step of its own is."""
    from adnmesh.loopmodel.step_figures import reference_step_figures
    from adnmesh.results.summary import RunSeries

    config = load_config(EXAMPLES / "wt-chp.yaml")
    start = 16550347.61628497
    cpfc = CPFC(config, GainSchedule(config, None), start_ref=start, steps=[(ns(1.0), 1e6)])
    keys, upper = Keys(config.grid), Keys("hv")
    series = RunSeries()
    rng = np.random.default_rng(7)
    for k in range(200):
        t = k * cpfc.period_ns
        if k % 3 == 1:
            cpfc.on_message(t, message(upper.of("adn_offset", "x"), t,
                                       {"offset_w": float(rng.uniform(-5e5, 5e5))}))
        for o in cpfc.on_timer(t):
            if o.key == keys.of("p_ref"):
                series.add("p_ref", {"t_send_ns": t, **o.body})
    assert len(series.p_ref_w) > 50
    (step,) = series.step_records()
    assert series.p_ref_t_ns[step] >= ns(1.0) > series.p_ref_t_ns[step - 1]
    own = np.asarray(series.p_ref_w) - np.asarray(series.p_ref_offsets())
    assert np.ptp(own[:step]) < 1e-6 and np.ptp(own[step:]) < 1e-6    # only rounding
    t = np.arange(0, ns(3.0), ns(0.1))
    figures = reference_step_figures(t, np.full(t.size, start), series.p_ref_t_ns,
                                     series.p_ref_w, [], ns(3.0),
                                     offset_w=series.p_ref_offsets())
    assert len(figures) == 1 and figures[0].step_w == pytest.approx(
        1e6 + series.p_ref_offsets()[step] - series.p_ref_offsets()[step - 1])


def test_the_hierarchy_topology_links_each_site_to_its_adn() -> None:
    upper = load_config(EXAMPLES.parent / "simbench.yaml").model_copy(
        update={"grid": "hv", "ders": ()})
    wt = load_config(EXAMPLES / "wt-chp.yaml")
    upper = upper.model_copy(update={"ders": (wt.ders[0].model_copy(update={"id": "a"}),)})
    lower = wt.model_copy(update={"grid": "a"})
    topology = hierarchy_topology(upper, {"a": lower}, {"a": 0.05})
    site, cpfc = qualified("hv", "der/a"), qualified("a", "cpfc")
    assert topology.receivers["adn/hv/der/a/offset"] == (cpfc,)
    assert site in topology.receivers["adn/a/measurement/exchange"]
    assert topology.lookahead_ns[(site, cpfc)] == ns(0.05)
    assert all(topology.lookahead_ns[(a, a)] > 0 for a in topology.agents)
    with pytest.raises(ValueError, match="grid name of its own"):
        hierarchy_topology(upper, {"a": lower.model_copy(update={"grid": "hv"})}, {"a": 0.0})
    with pytest.raises(ValueError, match="not DERs of the upper config"):
        hierarchy_topology(upper, {"b": lower}, {"b": 0.0})


def test_a_level_quarantines_its_der_on_the_shared_clock() -> None:
    """A level's launch quarantines its DER by its own id: on the hierarchy's one clock the
    qualified agent is dead, and its keys are cut at its receivers, which the clock names
    qualified too."""
    import threading

    from adnmesh.runtime.level_clock import LevelClock, SharedClock

    lower = load_config(EXAMPLES / "wt-chp.yaml").model_copy(update={"grid": "a"})
    upper = load_config(EXAMPLES.parent / "simbench.yaml").model_copy(
        update={"grid": "hv", "ders": (lower.ders[0].model_copy(update={"id": "a"}),)})
    topology = hierarchy_topology(upper, {"a": lower}, {"a": 0.05})
    shared = SharedClock(topology, ns(10.0), threading.Event())
    der = lower.ders[0].id
    LevelClock(shared, "a").quarantine(f"der/{der}", ns(1.0))
    clock = shared.coordinator
    assert clock.is_dead(qualified("a", f"der/{der}"))
    state = f"adn/a/der/{der}/state"
    cut = {clock.agents[r]: keys for r, keys in clock._cut_keys.items()}
    assert cut[qualified("a", "measurement")] == (state,)
    assert all(state in cut[a] for a in topology.receivers[state])


def test_an_adn_named_as_its_hierarchy_is_a_one_line_error(tmp_path, capsys) -> None:
    path = tmp_path / "h.yaml"
    path.write_text(HIERARCHY.replace("id: mixed", "id: hv"))
    assert main(["cascade", str(path), "--run"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "must differ from the hierarchy's name" in err


def test_the_adns_measurement_sends_its_exchange_at_once_with_its_limit_state() -> None:
    from adnmesh.control.measurement_point import Measurement

    config = load_config(EXAMPLES / "wt-chp.yaml")
    keys = Keys(config.grid)
    measurement = Measurement(config, exchange=True)
    for der in config.ders:
        measurement.on_message(0, message(keys.of("der_state", der.id), 0, {
            "p_w": 1e5, "setpoint_w": 1e5, "mode": "control", "held": 1}))
    out = measurement.on_timer(0)
    (p_ip,) = [o.body for o in out if o.key == keys.of("p_ip")]
    (exchange,) = [o.body for o in out if o.key == keys.of("adn_exchange")]
    assert exchange == {"p_ip_w": p_ip["p_ip_w"], "held": "up"}
    assert not [o for o in Measurement(config).on_timer(0) if o.key == keys.of("adn_exchange")]


def test_the_upper_cpfc_backs_off_when_adns_switch_to_slower_loops(ran) -> None:
    """At 80 s both ADNs switch to entries of slower plants and announce their new loops; the
    upper CPFC applies the rule: the factor it takes makes the cascade meet the constraints in
    python-control's evaluation (Padé models), and the gains before it do not."""
    import control as ct

    from adnmesh.cascade.control_models import cascade_models
    from adnmesh.cascade.lower_adn import announced
    from adnmesh.cascade.structure import Cascade
    from adnmesh.wire.messages import AdnActuator
    import msgspec

    out, _, topics, recording = ran
    events = [b for b in topics["adn/hv/event/cpfc"] if b["kind"].startswith("cascade_")
              and b["t_send_ns"] < ns(85.0)]
    assert [e["kind"] for e in events][-1] == "cascade_retuned"
    # the gains the rule took once both ADNs had announced (each verdict at the next sample)
    rule = [s for s in switches(topics, "adn/hv/cpfc/p_y") if ns(80.0) < s["t_send_ns"] < ns(85.0)]
    assert len(rule) == 2 and rule[0]["kp"] > rule[1]["kp"]
    switch = rule[-1]
    base = rule[0]["switch"]["kp_before"], rule[0]["switch"]["ki_before"]
    factor = switch["kp"] / base[0]
    assert 0 < factor < 1 and switch["ki"] / base[1] == pytest.approx(factor)
    # the loops the ADNs announced last, as the upper CPFC heard them
    lowers = {}
    for m in recording.messages:
        if m.topic.endswith("/cpfc/actuator"):
            body = msgspec.json.decode(m.data, type=AdnActuator)
            lowers[body.grid] = announced(body.grid, body)
    upper = load_config(out / "hv.upper.yaml")
    w = switch["w"]
    gains = hv_gains(out)     # the HV grid's dP_IP/dP, from pandapower's runpp
    cascade = Cascade(tuple(lowers[a] for a in ("wtchp", "mixed")),
                      tuple(w[a] * upper.ders_by_id([a])[0].p_inst_w * gains[a]
                            for a in ("wtchp", "mixed")), (0.3, 0.25), 0.2)
    t = np.arange(0.0, 400.0, 0.05)
    for kp, ki, meets in ((switch["kp"], switch["ki"], True), (*base, False)):
        loop, closed = cascade_models(cascade, kp, ki, order=10)
        dm, _, _ = ct.disk_margins(loop, np.geomspace(1e-4, 1e2, 3000))
        y = np.squeeze(ct.step_response(closed, T=t).outputs)
        overshoot = 100 * (np.max(y) - 1)
        assert (dm >= 1.5 - 1e-3 and overshoot < 1.0 + 1e-2) == meets, (kp, dm, overshoot)


def test_an_announcement_the_cascade_cannot_take_is_said_and_the_gains_stay() -> None:
    """An ADN's loop with a delay off the cascade's 0.1 ms grid: counted, a warning, no
    retune."""
    from types import SimpleNamespace

    from adnmesh.cascade.lower_adn import announced
    from adnmesh.cascade.switches import LowerSwitchRule
    from adnmesh.wire.messages import ActuatorGroup

    from adnmesh.tuning.table import SchedulingTable, TableEntry

    config = load_config(EXAMPLES / "wt-chp.yaml").model_copy(update={"grid": "hv"})
    ids = [d.id for d in config.ders]
    table = SchedulingTable("", {}, "paper", tuple(ids))
    table.add(TableEntry(tuple(ids), 1e-7, 1e-7, dict.fromkeys(ids, 1.0)))
    cpfc = CPFC(config, GainSchedule(config, table))
    good = {"entry": 0, "ders": ["SGen1"], "capacity_w": 2e6, "range_up_w": 2e6,
            "range_down_w": 0.0, "kp": 1e-7, "ki": 3e-7, "t_com_s": 0.15, "t_meas_s": 0.1,
            "groups": [{"t_delay_s": 0.01, "t_lag_s": 0.234, "model": "pt1", "gain_w": 2e6}]}
    start = announced(ids[0], SimpleNamespace(**{**good, "groups": [
        ActuatorGroup(**good["groups"][0])]}))
    cpfc.lower_switch_rule = LowerSwitchRule({i: start for i in ids}, dict.fromkeys(ids, 1e6),
                                             dict.fromkeys(ids, 0.2), 0.2, config.constraints)
    bad = {**good, "grid": ids[0], "t_com_s": 0.15003}
    out = cpfc.on_message(ns(1.0), message(Keys("a").of("adn_actuator"), ns(1.0), bad))
    assert [o.body["kind"] for o in out] == ["cascade_rule"]
    assert "not evaluated" in out[0].body["text"]
    assert cpfc.counts["rejected_announcements"] == 1 and cpfc._retuning is None


def test_an_adns_own_steps_are_left_out_unless_kept(tmp_path) -> None:
    from adnmesh.config import load_hierarchy
    from adnmesh.study.hierarchy import _adn_level

    path = tmp_path / "h.yaml"
    path.write_text(HIERARCHY.replace("t_com_s: 0.25,", "t_com_s: 0.25, keep_steps: true,"))
    hierarchy = load_hierarchy(path)
    dropped, kept = (_adn_level(hierarchy, adn).config for adn in hierarchy.adns)
    own = load_config(EXAMPLES / "mixed-4.yaml").scenario
    assert (dropped.grid, kept.grid) == ("wtchp", "mixed")
    assert dropped.scenario.p_ref_steps == () and dropped.scenario.availability
    assert kept.scenario == own


def test_a_fault_on_an_unknown_adn_is_a_one_line_error_before_any_tuning(tmp_path, capsys) -> None:
    path = tmp_path / "h.yaml"
    path.write_text(HIERARCHY.replace("der: wtchp", "der: nowhere"))
    assert main(["cascade", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "faults[0].der: unknown ADN id 'nowhere'" in err[0]


def test_the_rule_runs_again_when_the_upper_cpfc_switches_to_other_adns(ran) -> None:
    """wtchp's site is cut off at 85 s, after both ADNs switched to slower loops: the upper
    CPFC switches to mixed alone with its table entry, evaluates that cascade with mixed's
    loop as announced, and backs its gains off from there."""
    _, _, topics, _ = ran
    late = [s for s in switches(topics, "adn/hv/cpfc/p_y") if s["t_send_ns"] > ns(85.0)]
    drop, retuned = late[:2]
    assert drop["w"].get("wtchp", 0) == 0 and retuned["w"] == drop["w"]
    said = [b for b in topics["adn/hv/event/cpfc"] if b["t_send_ns"] > ns(85.0)]
    assert said[0]["kind"] == "cascade_rule" and "the ADNs in use changed" in said[0]["text"]
    assert said[-1]["kind"] == "cascade_retuned"
    assert 0 < retuned["kp"] / retuned["switch"]["kp_before"] < 1


def test_a_restarted_site_agent_sends_no_offset_before_its_first_command() -> None:
    upper = load_config(EXAMPLES.parent / "simbench.yaml").model_copy(update={"grid": "hv"})
    keys = Keys("hv")
    site = AdnSite(upper.ders[0], upper, p_ip0_w=0.0)
    site.resume(ns(40.0))
    offset_key = keys.of("adn_offset", upper.ders[0].id)
    sent = []
    while site.next_timer_ns() <= ns(41.0):
        sent += [o for o in site.on_timer(site.next_timer_ns()) if o.key == offset_key]
    assert not sent                    # the ADN keeps the offset it last heard
    out = site.on_message(ns(41.05), message(keys.of("p_y"), ns(41.05), {
        "p_y": 0.2, "p_ref_w": 0.0, "kp": 1e-7, "ki": 1e-7, "entry": 3,
        "w": {d.id: 1.0 for d in upper.ders}}))
    (offset,) = [o.body["offset_w"] for o in out if o.key == offset_key]
    assert offset == pytest.approx(0.2 * upper.ders[0].p_inst_w)


def test_an_adn_below_a_level_announces_itself_again_every_weights_period() -> None:
    """So that a restarted upper CPFC learns the loops it runs on; alone it does not."""
    config = load_config(EXAMPLES / "wt-chp.yaml")
    keys = Keys(config.grid)

    def announced(hear_offset: bool) -> list[int]:
        cpfc = CPFC(config, GainSchedule(config, None))
        times = []
        while cpfc.next_timer_ns() <= ns(2.5):      # DERs unheard of: none in use after
            t = cpfc.next_timer_ns()
            if hear_offset and t == ns(0.5):
                cpfc.on_message(t, message(Keys("hv").of("adn_offset", "x"), t,
                                           {"offset_w": 1e5}))
            times += [t for o in cpfc.on_timer(t) if o.key == keys.of("adn_actuator")]
        return times

    assert announced(False) == [0]
    assert announced(True) == [0, ns(1.0), ns(2.0)]


@pytest.mark.parametrize("change, said", [
    ("t_com_s: 0.25,", "t_com_s: 0.0,", ),
    ("der: wtchp, t_s: 85}", "agent: der/nowhere, t_s: 85, restart_after_s: 1}")],
    ids=["no-delay", "kill-of-no-adn"])
def test_more_hierarchy_files_that_are_refused_before_any_tuning(tmp_path, capsys, change,
                                                                 said) -> None:
    path = tmp_path / "h.yaml"
    body = HIERARCHY.replace(change, said)
    body = body.replace("kind: der_offline, agent:", "kind: kill, agent:")
    path.write_text(body)
    assert main(["cascade", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ("at least 0.001 s" in err[0] or "unknown ADN id 'nowhere'" in err[0])
