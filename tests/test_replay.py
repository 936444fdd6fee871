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


def _mcap_values(recording, topic: str, field: str,
                 factor: float = 1.0) -> list[tuple[int, int, float]]:
    """(send time, delivery time, value times ``factor``) of ``field`` on ``topic``, read
    straight from MCAP."""
    return sorted((m.publish_time_ns, m.log_time_ns, float(m.payload()[field]) * factor)
                  for m in recording.messages if m.topic == topic)


def _rrd_values(rrd, path: str) -> list[tuple[int, int, float]]:
    entity = rrd[rerun_entity_path(path)]
    values = [v[0] for v in entity["Scalars:scalars"]]
    return sorted(zip(entity[SIM_TIMELINE], entity[DELIVERY_TIMELINE], values))


@pytest.mark.parametrize("topic, field, factor", [
    ("adn/fake/scenario/p_ref", "p_ref_w", 1e-6),          # MW
    ("adn/fake/measurement/p_ip", "p_ip_w", 1e-6),
    ("adn/fake/cpfc/p_y", "p_y", 1.0),                      # per unit
    ("adn/fake/cpfc/p_y", "kp", 1e6),                       # 1/MW
    ("adn/fake/cpfc/p_y", "ki", 1e6),                       # 1/(MW s)
    *[(f"adn/fake/der/{d}/state", f, 1e-6) for d in FAKE_DERS for f in ("p_w", "setpoint_w")],
])
def test_values_read_back_from_the_rrd_are_the_mcap_values_in_mw(fake, rrd, topic, field,
                                                                  factor) -> None:
    expected = _mcap_values(read_recording(fake), topic, field, factor)
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


def _style(rrd, path: str) -> tuple[str, int, tuple[int, int, int]]:
    """Name, interpolation mode and RGB colour of the series at ``path``."""
    entity = rrd[rerun_entity_path(path)]
    rgba = entity["SeriesLines:colors"][0][0]
    return (entity["SeriesLines:names"][0][0], entity["SeriesLines:interpolation_mode"][0][0],
            (rgba >> 24 & 255, rgba >> 16 & 255, rgba >> 8 & 255))


def test_named_series_with_their_units_and_step_interpolation_in_the_rrd(rrd) -> None:
    def style(path: str) -> tuple[str, int]:
        return _style(rrd, path)[:2]

    linear, step_after = 1, 2
    assert style("/adn/fake/measurement/p_ip/p_ip_w") == ("P_IP [MW]", linear)
    assert style("/adn/fake/scenario/p_ref/p_ref_w") == ("P_ref [MW]", step_after)
    assert style("/adn/fake/cpfc/p_y/p_y") == ("P_Y", linear)
    assert style("/adn/fake/cpfc/p_y/kp") == ("K_P [1/MW]", step_after)
    assert style("/adn/fake/cpfc/p_y/ki") == ("K_I [1/(MW s)]", step_after)
    assert style("/adn/fake/der/WT1/state/p_w") == ("WT1 infeed [MW]", linear)
    assert style("/adn/fake/der/CHP1/state/setpoint_w") == ("CHP1 setpoint [MW]", step_after)
    assert style("/adn/fake/availability/si/available/WT2") == ("WT2 available", step_after)
    assert style("/adn/fake/availability/si/available_count") == ("DERs available", step_after)


def test_every_der_has_its_own_colour_and_its_setpoint_a_lighter_one(rrd) -> None:
    from adnmesh.results.rules import DER_COLORS, lighter

    infeed = {d: _style(rrd, f"/adn/fake/der/{d}/state/p_w")[2] for d in FAKE_DERS}
    setpoint = {d: _style(rrd, f"/adn/fake/der/{d}/state/setpoint_w")[2] for d in FAKE_DERS}
    available = {d: _style(rrd, f"/adn/fake/availability/si/available/{d}")[2]
                 for d in FAKE_DERS}
    assert len(set(infeed.values())) == len(FAKE_DERS)               # one colour per DER
    assert infeed["CHP1"] == DER_COLORS[0] and infeed["WT2"] == DER_COLORS[3]   # natural order
    for d in FAKE_DERS:
        assert setpoint[d] == lighter(infeed[d]) != infeed[d]        # related, told apart
        assert sum(setpoint[d]) > sum(infeed[d])
        assert available[d] == infeed[d]
    assert not set(setpoint.values()) & set(infeed.values())


def test_der_colours_are_distinct_for_many_ders() -> None:
    from adnmesh.results.rules import DER_COLORS, der_colors, natural_key

    ids = [f"SGen{i}" for i in range(1, 41)]
    colors = der_colors(reversed(ids))
    assert len(set(colors.values())) == 40
    assert sorted(ids, key=natural_key)[:3] == ["SGen1", "SGen2", "SGen3"]
    assert der_colors(["SGen10", "SGen2"])["SGen2"] == DER_COLORS[0]   # 2 before 10
    assert colors["SGen2"] == DER_COLORS[1]


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

    run = read_run(fake)[0].run
    fig = plot_run(run, title="fake run")
    panels = [ax for ax in fig.axes if ax.get_ylabel()]
    gains = [ax for ax in panels if ax.get_ylabel().startswith("K_P, K_I")]
    assert len(gains) == 1 and gains[0].get_yscale() == "log"
    labels = {line.get_label() for line in gains[0].get_lines()}
    assert {"K_P [1/MW]", "K_I [1/(MW s)]"} <= labels
    assert not any(line.get_label().startswith("K_") for ax in panels if ax is not gains[0]
                   for line in ax.get_lines())
    assert fig.get_suptitle().startswith(f"fake run: {len(FAKE_DERS)} DERs, sim time 0–")
    # every gain lies between labelled ticks, with ticks enough to read it
    shown = np.concatenate([run.one("kp").values, run.one("ki").values]) * 1e6   # per MW
    ticks = [t for t in gains[0].get_yticks() if gains[0].get_ylim()[0] <= t
             <= gains[0].get_ylim()[1]]
    assert len(ticks) >= 4 and min(ticks) < shown.min() and max(ticks) > shown.max()
    fig.canvas.draw()
    assert all(t.get_text() for t in gains[0].get_yticklabels())


def test_the_time_plot_is_in_mw_with_every_der_and_a_legend_per_axis(fake) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from adnmesh.results.rules import der_colors, lighter
    from adnmesh.results.series import read_run
    from adnmesh.results.time_plot import plot_run

    run = read_run(fake)[0].run
    fig = plot_run(run)
    FigureCanvasAgg(fig).draw()
    by_label = {ax.get_ylabel(): ax for ax in fig.axes}
    top = by_label["active power at the IP [MW]"]
    p_ip = next(line for line in top.get_lines() if line.get_label() == "P_IP [MW]")
    assert np.array_equal(p_ip.get_ydata(), run.one("p_ip").values * 1e-6)
    ders = by_label["DER infeed, set-point [MW]"]
    legend = [t.get_text() for t in ders.get_legend().get_texts()]
    assert legend == ["CHP1", "PV1", "WT1", "WT2", "infeed", "set-point"]   # every DER
    colors = {d: tuple(c / 255 for c in rgb) for d, rgb in der_colors(FAKE_DERS).items()}
    drawn = {(line.get_color(), line.get_linestyle()) for line in ders.get_lines()}
    for der, rgb in colors.items():          # its infeed solid, its set-point lighter, dashed
        assert (rgb, "-") in drawn
        assert (tuple(c / 255 for c in lighter(der_colors(FAKE_DERS)[der])), "--") in drawn
    for ax in fig.axes:                      # a legend per axis, of that axis' lines only
        if ax.get_legend() is not None and ax is not ders:
            own = {line.get_label() for line in ax.get_lines()} | {
                p.get_label() for p in ax.patches} | {c.get_label() for c in ax.collections}
            assert {t.get_text() for t in ax.get_legend().get_texts()} <= own


def _availability_run(changes: list[float], end_s: float = 100.0):
    """A run of P_IP alone whose available DERs change at ``changes`` (s): 10 DERs, one fewer
    each time."""
    from adnmesh.results.rules import Event
    from adnmesh.results.series import RunData, Series

    ders = [f"D{i}" for i in range(10)]
    events = [Event(int(t * 1e9), "availability", "INFO", "", "adn/g/availability/si",
                    {"available": ders[:10 - k]}) for k, t in enumerate([0.0, *changes])]
    t = np.arange(0, int(end_s * 1e9) + 1, 100_000_000, dtype=np.int64)
    p_ip = Series("P_IP", "/adn/g/measurement/p_ip/p_ip_w", "p_ip", "W", False, None,
                  "adn/g/measurement/p_ip", t, t, np.full(t.size, 1e6))
    return RunData({p_ip.entity_path: p_ip}, events, ders, 0)


@pytest.mark.parametrize("changes", [[10.0, 12.0, 14.0], [97.0], [50.0, 51.0, 99.5],
                                     [30.0, 60.0, 90.0]])
def test_availability_labels_stay_inside_the_axes_and_apart(changes) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from adnmesh.results.time_plot import plot_run

    fig = plot_run(_availability_run(changes))
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    top = fig.axes[0]
    box = top.get_window_extent()
    labels = [t for t in top.texts if "DERs available" in t.get_text()]
    assert [t.get_text() for t in labels] == [f"{9 - k} of 10 DERs available"
                                              for k in range(len(changes))]
    extents = [t.get_window_extent(canvas.get_renderer()) for t in labels]
    for extent in extents:
        assert box.x0 <= extent.x0 and extent.x1 <= box.x1 + 0.5
        assert box.y0 <= extent.y0 and extent.y1 <= box.y1 + 0.5
    for i, a in enumerate(extents):
        for b in extents[i + 1:]:
            assert not a.overlaps(b), (a, b)


def test_the_grid_panels_draw_the_band_and_the_limit(tmp_path: Path) -> None:
    from adnmesh.results.series import read_run, recorded_grid_limits
    from adnmesh.results.time_plot import plot_run

    path = _grid_recording(tmp_path / "grid.mcap",
                           "grid_model:\n  limits: {v_min_pu: 0.95, loading_max_pct: 80}\n")
    found, _ = read_run(path)
    fig = plot_run(found.run, limits=recorded_grid_limits(found.recording.run))
    by_label = {ax.get_ylabel(): ax for ax in fig.axes}
    voltage, loading = by_label["bus voltage [p.u.]"], by_label["loading [%]"]
    flat = {line.get_label(): set(line.get_ydata()) for line in voltage.get_lines()}
    assert flat["band: lowest allowed (0.95 p.u.)"] == {0.95}
    assert flat["band: highest allowed (1.1 p.u.)"] == {1.1}
    assert {1.01} == flat["lowest bus voltage"]
    assert any(line.get_label() == "loading limit (80 %)" and set(line.get_ydata()) == {80}
               for line in loading.get_lines())
    q_ip = by_label["Q_IP [Mvar]"]
    assert q_ip.get_lines()[0].get_ydata()[0] == pytest.approx(0.350001)
    without = plot_run(found.run)          # no band known: none drawn
    assert not any("band" in line.get_label() for ax in without.axes for line in ax.get_lines())


def _grid_recording(path: Path, config: str) -> Path:
    """A short recording of the runtime's P_IP and grid messages with ``config`` embedded."""
    from adnmesh.recording import Recorder
    from adnmesh.wire.keys import Keys, route
    from adnmesh.wire.schemas import message_schemas
    from payloads import payload

    keys = Keys("g")
    grid = {"v_min_pu": 1.01, "v_max_pu": 1.04, "line_loading_max_pct": 40.0,
            "trafo_loading_max_pct": 30.0, "q_ip_var": 3.5e5, "samples": 100,
            "outside_band": 0, "not_converged": 0}
    with Recorder(path, metadata={"run_id": "grid", "config": config},
                  schemas=message_schemas()) as recorder:
        for i in range(1, 6):
            t_ns = i * 1_000_000_000
            for key, body in ((keys.of("p_ip"), {"p_ip_w": 16.5e6 + i, "q_ip_var": 3.5e5 + i}),
                              (keys.of("grid_state"), {**grid, "q_ip_var": 3.5e5 + i})):
                recorder.write(key, route(key).type, payload(key, body, seq=i, t_send_ns=t_ns),
                               log_time_ns=t_ns, publish_time_ns=t_ns)
    return path


def test_the_grid_is_drawn_with_the_configured_band_and_q_ip_in_mvar(tmp_path: Path) -> None:
    from adnmesh.results.series import read_run

    config = "grid_model:\n  limits: {v_min_pu: 0.95, v_max_pu: 1.05}\n"   # loading: default
    path = _grid_recording(tmp_path / "grid.mcap", config)
    rrd = rrd_columns(export_rrd(read_recording(path), tmp_path / "grid.rrd"))
    limits = "/adn/g/measurement/grid/limits"
    for field, name, value in (("v_min_pu", "band: lowest [p.u.]", 0.95),
                               ("v_max_pu", "band: highest [p.u.]", 1.05),
                               ("loading_max_pct", "loading limit [%]", 100.0)):
        values = _rrd_values(rrd, f"{limits}/{field}")
        assert {v for _, _, v in values} == {value}
        assert values[0][0] == 1_000_000_000 and values[-1][0] == 5_000_000_000   # the whole run
        assert _style(rrd, f"{limits}/{field}")[:2] == (name, 2)
    for entity, name in (("/adn/g/measurement/p_ip/q_ip_var", "Q_IP [Mvar]"),
                         ("/adn/g/measurement/grid/q_ip_var", "Q_IP at the report [Mvar]")):
        q_ip = _rrd_values(rrd, entity)
        assert [v for _, _, v in q_ip] == [(3.5e5 + i) * 1e-6 for i in range(1, 6)]
        assert _style(rrd, entity)[0] == name
    assert _style(rrd, "/adn/g/measurement/grid/v_min_pu")[0] == "lowest bus voltage [p.u.]"
    # without a grid model in the config: no band (and none is made up)
    bare = _grid_recording(tmp_path / "bare.mcap", "grid: g\n")
    assert not any("/limits/" in p for p in rrd_columns(export_rrd(
        read_recording(bare), tmp_path / "bare.rrd")))
    assert read_run(path)[0].run.one("grid_v_min").label == "lowest bus voltage [p.u.]"


def _view_contents(container) -> dict[str, list[str]]:
    """View name -> its entity paths, of every view in a blueprint's container."""
    found = {}
    for item in container.contents:
        if hasattr(item, "kind"):                      # a container
            found.update(_view_contents(item))
        else:
            found[str(item.name)] = list(item.contents)
    return found


def test_the_layout_shows_every_der_and_the_grid_with_its_band(fake, tmp_path: Path) -> None:
    from adnmesh.results.rerun_export import blueprint, limit_series
    from adnmesh.results.series import read_run, recorded_grid_limits

    views = _view_contents(blueprint(extract(read_recording(fake))).root_container)
    for role, view in (("infeed", "DER infeed [MW]"), ("setpoint", "DER set-points [MW]")):
        assert sorted(views[view]) == sorted(
            f"/adn/fake/der/{d}/state/{'p_w' if role == 'infeed' else 'setpoint_w'}"
            for d in FAKE_DERS)
    assert views["P_IP and P_ref [MW]"] and views["gains: K_P [1/MW], K_I [1/(MW s)]"]
    assert not any(name.startswith("grid") for name in views)        # no grid model
    path = _grid_recording(tmp_path / "grid.mcap", "grid_model: {}\n")
    found, _ = read_run(path)
    run = found.run
    for series in limit_series(run, recorded_grid_limits(found.recording.run)):
        run.series[series.entity_path] = series
    views = _view_contents(blueprint(run).root_container)
    limits = "/adn/g/measurement/grid/limits"
    assert views["grid: bus voltages and the band [p.u.]"] == [
        "/adn/g/measurement/grid/v_min_pu", "/adn/g/measurement/grid/v_max_pu",
        f"{limits}/v_max_pu", f"{limits}/v_min_pu"]
    assert views["grid: highest loadings and the limit [%]"][-1] == f"{limits}/loading_max_pct"
    assert views["Q_IP and Q_ref [Mvar]"] == ["/adn/g/measurement/p_ip/q_ip_var"]
