"""Tests of the live view (``adnmesh up --view``): the series and events streamed to Rerun while
a run goes equal those ``adnmesh replay`` writes afterwards; the viewer binds 127.0.0.1; the
progress bar's lines."""

from __future__ import annotations

import bisect
import io
import os
import signal
import threading
import time
import urllib.parse
from collections import deque
from pathlib import Path

import pytest
from rich.console import Console

from adnmesh.errors import UsageError
from adnmesh.recording import read_recording
from adnmesh.results.live import LiveView
from adnmesh.results.rerun_export import (APPLICATION_ID, DELIVERY_TIMELINE, SIM_TIMELINE,
                                            export_rrd)
from adnmesh.results.rules import Event
from adnmesh.results.series import extract
from adnmesh.runtime.liveview import ViewTarget, open_view, parse_view, viewer_argv
from adnmesh.runtime.progress import RunProgress, event_line, speed_factor
from rrd_columns import rrd_columns
from synthetic_runs import write_fake_run


def samples(entity: dict[str, list]) -> list[tuple[int, int, float]]:
    """(sim time, delivery time, value) of a series entity, sorted."""
    return sorted(zip(entity[SIM_TIMELINE], entity[DELIVERY_TIMELINE],
                      (v[0] for v in entity["Scalars:scalars"])))


def texts(entity: dict[str, list]) -> list[tuple[int, str]]:
    return sorted(zip(entity[SIM_TIMELINE], entity["TextLog:text"]))


def compare_with_replay(live_rrd: Path, replay_rrd: Path, run, limits=None) -> None:
    """Every series and event log of the replay is in the live file: dense series sample for
    sample; step series with every real sample, held values equal to the value held (the
    grid's band, ``limits``, is a step series too)."""
    from adnmesh.results.rerun_export import limit_series, rerun_entity_path

    live, replay = rrd_columns(live_rrd), rrd_columns(replay_rrd)
    real = {rerun_entity_path(s.entity_path): set(s.t_ns.tolist())
            for s in [*run.series.values(), *limit_series(run, limits)] if s.step}
    compared = 0
    for path, entity in replay.items():
        if "Scalars:scalars" in entity:
            got, want = samples(live[path]), samples(entity)
            if path in real:     # the real samples, and held values equal to the value held
                assert [v for v in got if v[0] in real[path]] == \
                    [v for v in want if v[0] in real[path]], path
                times = [s for s, _, _ in want]
                for t, _, value in got:
                    assert value == want[bisect.bisect_right(times, t) - 1][2], path
            else:
                assert got == want, path
            compared += 1
        elif "TextLog:text" in entity:
            assert texts(live[path]) == texts(entity), path
            compared += 1
    assert compared >= 10


@pytest.fixture(scope="module")
def fake(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("live") / "fake.mcap"
    write_fake_run(path, duration_s=30.0)
    return path


def test_the_live_view_of_a_run_fed_in_pieces_equals_its_replay(fake, tmp_path) -> None:
    """The fake run's messages, fed as the recorder writes them (in delivery order, a piece
    per sim second, sent after each), give the series and events of ``replay``."""
    import rerun as rr

    recording = read_recording(fake)
    rec = rr.RecordingStream(APPLICATION_ID, recording_id="fake")
    rec.save(tmp_path / "live.rrd")
    events: list[Event] = []
    view = LiveView(rec, on_events=events.extend)
    messages = sorted(recording.messages, key=lambda m: m.log_time_ns)
    second = 1
    for m in messages:
        if m.log_time_ns >= second * 1_000_000_000:
            view.send_pending()
            second += 1
        view.take(m.topic, m.schema_name, [(bytes(m.data), m.log_time_ns, m.publish_time_ns)])
    view.close()
    assert view.error is None and view.sends > 20
    run = extract(recording)
    export_rrd(recording, tmp_path / "replay.rrd")
    compare_with_replay(tmp_path / "live.rrd", tmp_path / "replay.rrd", run)
    assert sorted((e.t_ns, e.text) for e in events) == sorted((e.t_ns, e.text) for e in run.events)


def test_view_targets() -> None:
    assert parse_view(None) is None
    assert parse_view("native") == ViewTarget("native")
    assert parse_view("web") == ViewTarget("web")
    assert parse_view("out/run.rrd") == ViewTarget("file", Path("out/run.rrd"))
    with pytest.raises(UsageError, match="--view"):
        parse_view("browser")
    argv = viewer_argv(True, 1234, 5678)
    assert argv[argv.index("--bind") + 1] == "127.0.0.1"
    assert argv[argv.index("--port") + 1] == "1234"
    assert argv[argv.index("--web-viewer-port") + 1] == "5678" and "--serve-web" in argv


def _listening(pid: int) -> set[str]:
    """Local addresses (ip:port) of the TCP sockets ``pid`` listens on (from /proc)."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except FileNotFoundError:     # closed since the listing: not a listening socket
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            parts = line.split()
            if parts[3] == "0A" and parts[9] in inodes:          # LISTEN
                address, port = parts[1].split(":")
                ip = ".".join(str(int(address[i:i + 2], 16)) for i in (6, 4, 2, 0)) \
                    if len(address) == 8 else address
                found.add(f"{ip}:{int(port, 16)}")
    return found


def test_the_web_viewer_listens_on_127_0_0_1_only(tmp_path) -> None:
    lines: list[str] = []
    view = open_view(ViewTarget("web"), "test", lines.append)
    try:
        pid = view.viewer_pid
        line = next(line for line in lines if "web viewer: open http://127.0.0.1:" in line)
        url = urllib.parse.urlsplit(line.split("open ")[1].split()[0])
        web_port = url.port
        (data,) = urllib.parse.parse_qs(url.query)["url"]    # opens the viewer on the data
        grpc = urllib.parse.urlsplit(data)
        assert (grpc.scheme, grpc.hostname, grpc.path) == ("rerun+http", "127.0.0.1", "/proxy")
        found: set[str] = set()
        deadline = time.monotonic() + 30
        while len(found) < 2 and time.monotonic() < deadline:   # poll the process's sockets
            found = _listening(pid)
            threading.Event().wait(0.05)
        assert view.error is None
        assert {f"127.0.0.1:{web_port}", f"127.0.0.1:{grpc.port}"} <= found
        assert found and all(a.startswith("127.0.0.1:") for a in found), found
    finally:
        view.close()
        os.kill(view.viewer_pid, signal.SIGTERM)
        os.waitpid(view.viewer_pid, 0)


def test_a_native_viewer_without_a_display_is_said_in_one_line(monkeypatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    lines: list[str] = []
    assert open_view(ViewTarget("native"), "test", lines.append) is None
    assert len(lines) == 1 and "no display" in lines[0] and "--view web" in lines[0]


def test_progress_prints_the_events_above_the_bar() -> None:
    out = io.StringIO()
    console = Console(file=out, force_terminal=False, width=120)
    switch = Event(12_000_000_000, "gain_switch", "INFO", "gain switch to entry 1", "k")
    quiet = Event(1, "der_mode", "INFO", "SGen1: mode schedule -> control", "k")
    overrun = Event(2, "event", "WARN", "cpfc: overrun", "k", {"kind": "overrun"})
    with RunProgress(console, 60_000_000_000) as bar:
        bar.update(30_000_000_000)
        bar.events([switch, overrun])
    text = out.getvalue()
    assert "t =    12.000 s  gain switch to entry 1" in text
    assert "overrun" not in text
    assert event_line(quiet) is not None and event_line(overrun) is None


def test_speed_factor() -> None:
    assert speed_factor(deque([(0.0, 0)])) is None
    assert speed_factor(deque([(10.0, 0), (12.0, 30_000_000_000)])) == 15.0


def test_both_views_queue_what_they_are_given_by_one_take() -> None:
    """The view in ``up``'s process and the one in its child queue recorded messages the same
    way: one implementation, in order, emptied by whoever hands them on."""
    from adnmesh.results.live import RecordQueue
    from adnmesh.runtime.liveview import ViewProcess

    assert LiveView.take is ViewProcess.take is RecordQueue.take
    queue = RecordQueue()
    queue.take("a", "p_ip", [(b"{}", 2, 1)])
    queue.take("b", "p_y", [(b"{}", 4, 3)])
    assert queue.taken() == [("a", "p_ip", [(b"{}", 2, 1)]), ("b", "p_y", [(b"{}", 4, 3)])]
    assert queue.taken() == []


def test_the_live_view_draws_the_band_and_keeps_each_ders_colour(tmp_path) -> None:
    """The band comes with the grid's first report and is held as the run goes; a DER seen
    later moves the others' colours to those replay gives them (natural order of ids)."""
    import rerun as rr

    from adnmesh.config import GridLimits
    from adnmesh.results.rules import der_colors
    from adnmesh.wire.keys import Keys, route
    from payloads import payload

    keys = Keys("g")
    rec = rr.RecordingStream(APPLICATION_ID, recording_id="band")
    rec.save(tmp_path / "live.rrd")
    view = LiveView(rec, limits=GridLimits(v_min_pu=0.95, v_max_pu=1.05, loading_max_pct=80))
    grid = {"v_min_pu": 1.01, "v_max_pu": 1.04, "line_loading_max_pct": 40.0,
            "trafo_loading_max_pct": 30.0, "q_ip_var": 3.5e5, "samples": 100,
            "outside_band": 0, "not_converged": 0}
    for i, der in enumerate(["SGen10", "SGen2"]):      # SGen2 comes 3 s later
        for s in range(1, 4):
            t_ns = (3 * i + s) * 1_000_000_000
            for key, body in ((keys.of("der_state", der), {"p_w": 1e6, "setpoint_w": 1e6,
                                                           "mode": "control"}),
                              (keys.of("grid_state"), grid)):
                data = payload(key, body, seq=3 * i + s, t_send_ns=t_ns)
                view.take(key, route(key).type, [(data, t_ns, t_ns)])
            view.send_pending()
    view.close()
    assert view.error is None
    live = rrd_columns(tmp_path / "live.rrd")
    band = live["/adn/g/measurement/grid/limits/v_min_pu"]
    assert {v[0] for v in band["Scalars:scalars"]} == {0.95}
    assert max(band[SIM_TIMELINE]) == 6_000_000_000                  # held to the newest time
    assert {v[0] for v in live["/adn/g/measurement/grid/limits/loading_max_pct"][
        "Scalars:scalars"]} == {80.0}
    colors = der_colors(["SGen2", "SGen10"])
    first = live["/adn/g/der/SGen10/state/p_w"]["SeriesLines:colors"][0][0]
    assert first != live["/adn/g/der/SGen10/state/p_w"]["SeriesLines:colors"][-1][0]  # moved
    for der in ("SGen2", "SGen10"):
        rgba = live[f"/adn/g/der/{der}/state/p_w"]["SeriesLines:colors"][-1][0]   # the last
        assert (rgba >> 24 & 255, rgba >> 16 & 255, rgba >> 8 & 255) == colors[der]


def test_a_step_sample_that_comes_after_a_later_one_is_not_shown_held_before(tmp_path) -> None:
    """The agents of one clock window send in any order: P_ref's step at 2 s may come after a
    DER's state of 2 s. The view must not have shown P_ref's old value held at 2 s."""
    import rerun as rr

    from adnmesh.wire.keys import Keys, route
    from payloads import payload

    keys = Keys("g")
    rec = rr.RecordingStream(APPLICATION_ID, recording_id="order")
    rec.save(tmp_path / "live.rrd")
    view = LiveView(rec)
    sent = [(keys.of("p_ref"), {"p_ref_w": -2.5e6}, 0),
            (keys.of("der_state", "SGen1"), {"p_w": 1e6, "setpoint_w": 1e6, "mode": "control"},
             2_000_000_000),
            (keys.of("p_ref"), {"p_ref_w": -1.5e6}, 2_000_000_000)]
    for seq, (key, body, t_ns) in enumerate(sent):
        view.take(key, route(key).type, [(payload(key, body, seq=seq, t_send_ns=t_ns), t_ns,
                                          t_ns)])
        view.send_pending()                          # a send between the two samples of 2 s
    view.close()
    assert view.error is None
    p_ref = samples(rrd_columns(tmp_path / "live.rrd")["/adn/g/scenario/p_ref/p_ref_w"])
    assert [v for t, _, v in p_ref if t == 2_000_000_000] == [-1.5]
