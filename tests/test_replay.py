"""Tests of the conversion to Rerun (adnmesh replay), the series table and adnmesh plot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from adnmesh.cli import main
from adnmesh.recording import read_recording
from adnmesh.results.figures import run_figures
from adnmesh.results.rerun_export import (
    DELIVERY_TIMELINE,
    SIM_TIMELINE,
    export_rrd,
    rerun_entity_path,
    viewer_command,
)
from adnmesh.results.rules import SERIES, match_key
from adnmesh.results.series import extract
from rrd_columns import rrd_columns
from synthetic_runs import FAKE_DERS, write_fake_run


@pytest.fixture(scope="module")
def fake(tmp_path_factory) -> Path:
    """A recorded fake run (60 s of sim time)."""
    path = tmp_path_factory.mktemp("fake") / "fake.mcap"
    write_fake_run(path)
    return path


@pytest.fixture(scope="module")
def rrd(fake: Path) -> dict[str, dict[str, list]]:
    """The fake run exported to .rrd and read back with rerun: entity path -> column -> values."""
    from rerun.chunk import RrdReader

    out = export_rrd(read_recording(fake), fake.with_suffix(".rrd"))
    reader = RrdReader(out)
    assert len(reader.recordings()) == 1 and len(reader.blueprints()) == 1
    return rrd_columns(out, reader)


def _mcap_values(recording, topic: str, field: str) -> list[tuple[int, int, float]]:
    """(send time, delivery time, value) of ``field`` on ``topic``, read straight from MCAP."""
    return sorted((m.publish_time_ns, m.log_time_ns, float(m.payload()[field]))
                  for m in recording.messages if m.topic == topic)


def _rrd_values(rrd, path: str) -> list[tuple[int, int, float]]:
    entity = rrd[rerun_entity_path(path)]
    values = [v[0] for v in entity["Scalars:scalars"]]
    return sorted(zip(entity[SIM_TIMELINE], entity[DELIVERY_TIMELINE], values))


@pytest.mark.parametrize("topic, field", [
    ("adn/fake/scenario/p_ref", "p_ref_w"),
    ("adn/fake/measurement/p_ip", "p_ip_w"),
    ("adn/fake/cpfc/p_y", "p_y"),
    ("adn/fake/cpfc/p_y", "kp"),
    *[(f"adn/fake/der/{d}/state", f) for d in FAKE_DERS for f in ("p_w", "setpoint_w")],
])
def test_values_read_back_from_the_rrd_equal_the_mcap_values(fake, rrd, topic, field) -> None:
    expected = _mcap_values(read_recording(fake), topic, field)
    assert len(expected) > 1
    got = _rrd_values(rrd, f"/{topic}/{field}")
    sent = {t for t, _, _ in expected}
    assert [v for v in got if v[0] in sent] == expected  # exact: times in ns, float64
    for t, _, value in (v for v in got if v[0] not in sent):   # a step series' held value
        assert value == [v for s, _, v in expected if s <= t][-1]


def test_step_series_hold_their_value_through_the_whole_run(fake) -> None:
    from adnmesh.results.rerun_export import HOLD_PERIOD_NS, held

    run = extract(read_recording(fake))
    p_ref = run.one("p_ref")
    shown = held(p_ref, 60_100_000_000)
    assert 60_100_000_000 - HOLD_PERIOD_NS < shown.t_ns[-1] <= 60_100_000_000   # to the end
    assert np.diff(np.append(shown.t_ns, 60_100_000_000)).max() <= HOLD_PERIOD_NS
    index = np.searchsorted(p_ref.t_ns, shown.t_ns, side="right") - 1
    assert np.array_equal(shown.values, p_ref.values[index])       # the step function itself
    assert np.all(shown.log_time_ns >= shown.t_ns)
    p_ip = run.one("p_ip")
    assert held(p_ip, 60_100_000_000) is p_ip                       # not a step series


def test_named_series_and_step_interpolation_in_the_rrd(rrd) -> None:
    def style(path: str) -> tuple[str, int]:
        entity = rrd[rerun_entity_path(path)]
        return entity["SeriesLines:names"][0][0], entity["SeriesLines:interpolation_mode"][0][0]

    linear, step_after = 1, 2
    assert style("/adn/fake/measurement/p_ip/p_ip_w") == ("P_IP", linear)
    assert style("/adn/fake/scenario/p_ref/p_ref_w") == ("P_ref", step_after)
    assert style("/adn/fake/cpfc/p_y/p_y") == ("P_Y", linear)
    assert style("/adn/fake/der/WT1/state/p_w") == ("WT1 infeed", linear)
    assert style("/adn/fake/der/CHP1/state/setpoint_w") == ("CHP1 setpoint", step_after)
    assert style("/adn/fake/availability/si/available/WT2") == ("WT2 available", step_after)


def test_availability_is_a_step_series_per_der(rrd) -> None:
    wt = _rrd_values(rrd, "/adn/fake/availability/si/available/WT1")
    chp = _rrd_values(rrd, "/adn/fake/availability/si/available/CHP1")
    assert {v for t, _, v in wt if t < 25e9} == {1.0}
    assert {v for t, _, v in wt if t >= 25e9} == {0.0}
    assert {v for _, _, v in chp} == {1.0}
    count = _rrd_values(rrd, "/adn/fake/availability/si/available_count")
    assert count[0][2] == 4.0 and count[-1][2] == 2.0


def test_gain_switches_and_faults_are_text_log_entries(rrd) -> None:
    gains = rrd[rerun_entity_path("/adn/fake/cpfc/p_y/events")]
    assert gains[SIM_TIMELINE] == [25_000_000_000]
    assert gains["TextLog:text"][0][0] == (
        "gain switch to entry 12: K_P 6.593e-08 -> 6.364e-07 1/W, K_I 3.297e-07 -> 7.273e-07 "
        "1/(W s), P_Y -0.001432 -> -0.001341; DERs: CHP1, PV1")
    assert gains["TextLog:level"] == [["INFO"]]
    faults = rrd[rerun_entity_path("/adn/fake/faults/events")]
    assert faults[SIM_TIMELINE] == [40_000_000_000]
    assert [t[0] for t in faults["TextLog:text"]] == [
        "fault 1: der_offline of CHP1 from 40 s to 42 s"]
    assert faults["TextLog:level"] == [["WARN"]]
    modes = rrd[rerun_entity_path("/adn/fake/der/CHP1/state/events")]
    assert modes[SIM_TIMELINE] == [41_000_000_000, 42_000_000_000]
    assert [t[0] for t in modes["TextLog:text"]] == ["CHP1: mode control -> watchdog",
                                                     "CHP1: mode watchdog -> control"]
    assert modes["TextLog:level"] == [["WARN"], ["INFO"]]
    availability = rrd[rerun_entity_path("/adn/fake/availability/si/events")]
    assert availability[SIM_TIMELINE] == [0, 25_000_000_000]


def test_match_key_placeholders_and_wildcards() -> None:
    assert match_key("adn/{grid}/der/{der}/state", "adn/g1/der/SGen3/state") == {
        "grid": "g1", "der": "SGen3"}
    assert match_key("adn/{grid}/der/{der}/state", "adn/g1/der/SGen3/command") is None
    assert match_key("adn/{grid}/fault/**", "adn/g/fault/ict/cpfc") == {"grid": "g"}
    assert match_key("adn/*/faults", "adn/g/faults") == {}
    assert match_key("adn/{grid}/fault/**", "adn/g/fault") is None


def test_every_series_pattern_has_the_roles_the_views_use() -> None:
    roles = {field.role for fields in SERIES.values() for field in fields}
    assert {"p_ref", "p_ip", "p_y", "kp", "ki", "der_infeed", "der_setpoint"} <= roles


def test_unknown_keys_keep_their_numbers_and_bodies_are_unwrapped(tmp_path: Path) -> None:
    from adnmesh.recording import Recorder

    path = tmp_path / "other.mcap"
    schemas = {"any": {"type": "object"}}
    with Recorder(path, metadata={}, schemas=schemas) as recorder:
        recorder.write("adn/g/new/thing", "any", b'{"v": 1, "seq": 3, "x_w": 5, "flag": true}',
                       log_time_ns=2, publish_time_ns=1)
        recorder.write("adn/g/measurement/p_ip", "any", b'{"v": 1, "body": {"p_ip_w": 7.5}}',
                       log_time_ns=2, publish_time_ns=1)
        recorder.write("adn/g/measurement/p_ip", "any", b'[1, 2]', log_time_ns=3,
                       publish_time_ns=2)
    run = extract(read_recording(path))
    assert list(run.series) == ["/adn/g/new/thing/x_w", "/adn/g/measurement/p_ip/p_ip_w"]
    assert run.series["/adn/g/new/thing/x_w"].role == "other"
    assert run.one("p_ip").values.tolist() == [7.5]


def test_summary_figures_of_the_fake_run(fake) -> None:
    figures = run_figures(extract(read_recording(fake)))
    assert [s.t_s for s in figures.steps] == [5.0, 15.0, 30.0, 50.0]
    first = figures.steps[0]
    assert first.step_w == 1.0e6 and first.p_ref_w == pytest.approx(2.7e6)
    assert 0.5 < first.figures.rise_time_s < 3 and first.figures.settling_time_s < 5
    assert first.figures.overshoot_pct < 1
    slow = figures.steps[2]  # after the WTs left: the CHP plant dominates
    assert slow.figures.rise_time_s > 3 * first.figures.rise_time_s
    # each window ends at the next event: step, gain switch, fault start, end of the run
    assert [s.window_s for s in figures.steps] == [10.0, 10.0, 10.0, 10.0]
    assert (figures.gain_switches, figures.availability_changes, figures.faults,
            figures.mode_changes) == (1, 1, 1, 4)
    assert figures.max_error_w == pytest.approx(1.0e6, rel=0.01)


def test_viewer_commands_bind_to_localhost(tmp_path: Path) -> None:
    native = viewer_command(tmp_path / "r.rrd")
    web = viewer_command(tmp_path / "r.rrd", web=True, web_port=9191)
    for command in (native, web):
        assert command[command.index("--bind") + 1] == "127.0.0.1"
        assert command[1] == str(tmp_path / "r.rrd") and Path(command[0]).name == "rerun"
    assert "--web-viewer" in web and web[web.index("--web-viewer-port") + 1] == "9191"
    assert "--web-viewer" not in native


def test_replay_command_writes_an_rrd_headless(fake, tmp_path: Path, capsys) -> None:
    out = tmp_path / "run.rrd"
    assert main(["replay", str(fake), "--rrd", str(out)]) == 0
    assert out.stat().st_size > 10_000
    assert capsys.readouterr().out.startswith(f"{out}: ")


def test_replay_refuses_two_targets(fake, capsys) -> None:
    assert main(["replay", str(fake), "--rrd", "x.rrd", "--web"]) == 2
    assert "not allowed with argument" in capsys.readouterr().err


def test_plot_command_draws_a_png(fake, tmp_path: Path, capsys) -> None:
    out = tmp_path / "fig.png"
    assert main(["plot", str(fake), "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert capsys.readouterr().out == f"{out}: written\n"
    from matplotlib.image import imread

    image = imread(out)
    assert image.shape[0] > 500 and image.shape[1] > 1000
    assert np.unique(image[::5, ::5].reshape(-1, image.shape[-1]), axis=0).shape[0] > 10  # drawn


def test_plot_refuses_an_unknown_format(fake, tmp_path: Path, capsys) -> None:
    assert main(["plot", str(fake), "-o", str(tmp_path / "fig.xyz")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("adnmesh: error: ") and "unknown figure format '.xyz'" in err
    assert err.count("\n") == 1


@pytest.mark.parametrize("command", ["replay", "plot"])
def test_replay_and_plot_reject_a_non_mcap_file(tmp_path: Path, command: str, capsys) -> None:
    path = tmp_path / "notes.mcap"
    path.write_text("not a recording\n")
    assert main([command, str(path)]) == 2
    err = capsys.readouterr().err
    assert err == f"adnmesh: error: {path}: not an MCAP file (it does not start with the MCAP " \
                  "magic)\n"


def test_plot_of_a_truncated_recording_notes_it(fake, tmp_path: Path, capsys) -> None:
    path = tmp_path / "cut.mcap"
    path.write_bytes(fake.read_bytes()[:-2000])
    assert main(["plot", str(path), "-o", str(tmp_path / "cut.png")]) == 0
    assert "is truncated (killed run?)" in capsys.readouterr().err


def test_the_series_table_understands_the_runtimes_messages(tmp_path: Path) -> None:
    from adnmesh.recording import Recorder, validate_recording
    from adnmesh.wire.envelope import decode
    from adnmesh.wire.keys import Keys, route
    from adnmesh.wire.messages import Switch
    from adnmesh.wire.schemas import message_schemas
    from payloads import payload

    keys = Keys("g")
    switch = Switch(p_y_before=0.1, p_y_limited=0.1, kp_before=1e-7, ki_before=2e-7)
    sent = [
        (keys.of("p_ref"), {"p_ref_w": 2.0e6}),
        (keys.of("p_ip"), {"p_ip_w": 1.5e6}),
        (keys.of("p_y"), {"p_y": 0.1, "p_ref_w": 2e6, "kp": 1e-7, "ki": 2e-7, "entry": 3}),
        (keys.of("p_y"), {"p_y": 0.1, "p_ref_w": 2e6, "kp": 3e-7, "ki": 4e-7, "entry": 1,
                    "w": {"SGen1": 1.0}, "switch": switch}),
        (keys.of("der_state", "SGen1"), {"p_w": 1e6, "setpoint_w": 1.1e6, "mode": "control"}),
        (keys.of("heartbeat", "SGen1"), {"available": True}),
        (keys.of("si"), {"si": {"SGen1": True, "SGen2": False}}),
        (keys.of("fault"), {"fault_id": 1, "kind": "der_offline", "der": "SGen2",
                       "start_ns": 700_000_000, "end_ns": None}),
    ]
    path = tmp_path / "runtime.mcap"
    with Recorder(path, metadata={}, schemas=message_schemas()) as recorder:
        for i, (key, body) in enumerate(sent):
            t_ns = i * 100_000_000
            data = payload(key, body, seq=i, t_send_ns=t_ns, t_deliver_ns=t_ns + 1)
            decode(key, data)  # a valid message of the runtime
            recorder.write(key, route(key).type, data, log_time_ns=t_ns + 1,
                           publish_time_ns=t_ns)
    recording = read_recording(path)
    assert validate_recording(recording) == []
    run = extract(recording)
    assert {s.name for s in run.series.values()} == {
        "P_ref", "P_IP", "P_Y", "K_P", "K_I", "table entry", "SGen1 infeed", "SGen1 setpoint",
        "DERs available", "SGen1 available", "SGen2 available"}
    assert [e.kind for e in run.events] == ["gain_switch", "availability", "fault"]
    assert run.events[0].text.startswith("gain switch to entry 1: K_P 1e-07 -> 3e-07 1/W")


def test_the_time_plot_has_the_gains_on_their_own_panel_with_units(fake) -> None:
    from adnmesh.results.time_plot import plot_run
    from adnmesh.results.series import read_run

    fig = plot_run(read_run(fake)[0].run, title="fake run")
    panels = [ax for ax in fig.axes if ax.get_ylabel()]
    gains = [ax for ax in panels if ax.get_ylabel().startswith("K_P, K_I")]
    assert len(gains) == 1 and gains[0].get_yscale() == "log"
    labels = {line.get_label() for line in gains[0].get_lines()}
    assert {"K_P [1/W]", "K_I [1/(W s)]"} <= labels
    assert not any(line.get_label().startswith("K_") for ax in panels if ax is not gains[0]
                   for line in ax.get_lines())
    assert fig.get_suptitle().startswith(f"fake run: {len(FAKE_DERS)} DERs, sim time 0–")
