"""Converting a recording into Rerun data (``adnmesh replay``).

Rerun reads MCAP itself but does not decode JSON channels, so adnmesh converts: every series of
:func:`adnmesh.results.series.extract` becomes an entity ``/<key>/<field>`` of ``Scalars``
with a static ``SeriesLines`` style, indexed by two timelines: ``sim_time`` (send time, from
t0) and ``delivery_time`` (delivery time, from t0), both durations. The values are in the units
a controls engineer reads (:data:`adnmesh.results.rules.DISPLAY_UNITS`: MW, Mvar, 1/MW,
1/(MW s)); the style names the series with its unit (``P_IP [MW]``), gives every DER its own
colour (its set-point a lighter shade of it) and steps for step series. With a grid model the
configured band (``grid_model.limits``) is drawn as constant series beside the extremes
(:func:`limit_series`). Events (gain switches, availability changes, faults) become ``TextLog``
entries at ``/<key>/events``. A blueprint lays out P_IP with P_ref, P_Y, the gains and the
events, the DERs' infeed and set-points, availability and the grid.

:func:`export_rrd` writes an ``.rrd`` file without any viewer (headless);
:func:`viewer_command` is the command that opens one in a viewer bound to 127.0.0.1, and
:func:`web_viewer_url` the address that opens the web viewer on its data.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import sys
import urllib.parse
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from adnmesh.recording.reader import Recording
from adnmesh.recording.stream import ScannedRecording
from adnmesh.results.rules import COLORS, Event, series_color
from adnmesh.results.series import (RunData, Series, extract, grid_of_topic, grids_of,
                                    recorded_grid_limits)

__all__ = [
    "APPLICATION_ID",
    "DELIVERY_TIMELINE",
    "SIM_TIMELINE",
    "HOLD_PERIOD_NS",
    "VIEWER_HOST",
    "blueprint",
    "events_path",
    "export_rrd",
    "grpc_url",
    "held",
    "limit_series",
    "log_run",
    "log_style",
    "rerun_entity_path",
    "rerun_executable",
    "send_events",
    "send_series",
    "viewer_command",
    "web_viewer_url",
]

APPLICATION_ID = "adnmesh"
SIM_TIMELINE = "sim_time"
"""Timeline of send times (the instant a value was sampled or decided), duration from t0."""
DELIVERY_TIMELINE = "delivery_time"
"""Timeline of delivery times, duration from t0."""

_LEVELS = {"INFO": "INFO", "WARN": "WARN", "ERROR": "ERROR"}


def rerun_entity_path(path: str) -> str:
    """Return ``path`` (``/a/b/c``) with each part escaped for Rerun."""
    import rerun as rr

    return "/" + "/".join(rr.escape_entity_path_part(p) for p in path.strip("/").split("/"))


def _durations(t_ns: np.ndarray, t0_ns: int) -> np.ndarray:
    return (np.asarray(t_ns, dtype=np.int64) - t0_ns).astype("timedelta64[ns]")


GRID_LIMIT_ROLE = "grid_limit"
"""Role of the constant series of the configured band (:func:`limit_series`)."""


def blueprint(run: RunData):
    """Return the Rerun blueprint for ``run``: the main plots, laid out.

    P_IP and P_ref (MW) beside the event log on top; P_Y, the gains (1/MW, 1/(MW s)), the
    number of DERs available and, with a grid model, Q_IP (Mvar); every DER's infeed and
    set-point (MW), tall enough for a legend of every DER (Rerun gives a legend at most about
    three quarters of its plot's height), and with a grid model the bus voltage extremes with
    the band (p.u.) and the loadings with their limit (%). A run of several grids (a
    hierarchy's) gets that layout once per grid, a tab each.
    """
    import rerun.blueprint as rrb

    grids = grids_of(s.topic for s in run.series.values())
    root = (rrb.Tabs(*(_layout(run, grid) for grid in grids)) if len(grids) > 1
            else _layout(run, None))
    return rrb.Blueprint(
        root,
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=SIM_TIMELINE, state="collapsed", play_state="paused"),
    )


def _layout(run: RunData, grid: str | None):
    """The plots of :func:`blueprint` of ``grid``'s series (None: all), named after it."""
    import rerun as rr
    import rerun.blueprint as rrb

    everything = rr.encodings.TimeRange(start=rrb.TimeRangeBoundary.infinite(),
                                        end=rrb.TimeRangeBoundary.infinite())
    whole = rrb.VisibleTimeRange(SIM_TIMELINE, start=rrb.TimeRangeBoundary.infinite(),
                                 end=rrb.TimeRangeBoundary.infinite())    # the whole run

    def mine(topic: str) -> bool:
        return grid is None or grid_of_topic(topic) == grid

    def of(*roles: str) -> list[Series]:
        return [s for role in roles for s in run.by_role(role) if mine(s.topic)]

    def plot(name: str, *roles: str, paths: Iterable[str] = ()):
        contents = [rerun_entity_path(s.entity_path) for s in of(*roles)]
        contents += [rerun_entity_path(p) for p in paths]
        return rrb.TimeSeriesView(name=name, origin="/", contents=contents or [],
                                  time_ranges=whole, axis_x=rrb.TimeAxis(view_range=everything))

    events = sorted({events_path(e) for e in run.events if mine(e.topic)})
    limits = {s.entity_path for s in of(GRID_LIMIT_ROLE)}
    loading_limit = [p for p in limits if p.endswith("/loading_max_pct")]
    middle = [plot("P_Y (per unit of each DER's w·P_inst)", "p_y"),
              plot("gains: K_P [1/MW], K_I [1/(MW s)]", "kp", "ki"),
              plot("DERs available", "available_count")]
    bottom = [plot("DER infeed [MW]", "der_infeed"),
              plot("DER set-points [MW]", "der_setpoint")]
    if of("q_y"):
        middle.append(plot("Q_Y (per unit of each DER's w·C^Q)", "q_y"))
        bottom.append(plot("DER reactive infeed [Mvar]", "der_q_infeed"))
    if of("q_ip"):
        middle.append(plot("Q_IP and Q_ref [Mvar]", "q_ref", "q_ip"))
    if of("grid_v_min"):
        bottom.append(rrb.Vertical(
            plot("grid: bus voltages and the band [p.u.]", "grid_v_min", "grid_v_max",
                 paths=sorted(limits - set(loading_limit))),
            plot("grid: highest loadings and the limit [%]", "grid_line_loading",
                 "grid_trafo_loading", paths=loading_limit),
            *([plot("tap changer: position", "tap_pos")] if of("tap_pos") else [])))
    return rrb.Vertical(
        rrb.Horizontal(plot("P_IP and P_ref [MW]", "p_ref", "p_ip"),
                       rrb.TextLogView(name="events", origin="/", contents=events or []),
                       column_shares=[3, 2]),
        rrb.Horizontal(*middle),
        rrb.Horizontal(*bottom),
        row_shares=[3, 2, 4.2], name=grid)


def limit_series(run: RunData, limits) -> list[Series]:
    """The configured band of ``run``'s grid as constant step series (one sample at the first
    grid report, held like every step series): the lowest and highest bus voltage allowed
    (p.u.) and the loading limit (%), at ``/<grid key>/limits/<field>``; none without a grid
    model or ``limits`` (a :class:`adnmesh.config.GridLimits`, e.g. from
    :func:`~adnmesh.results.series.recorded_grid_limits`)."""
    grid = run.one("grid_v_min")
    if grid is None or limits is None or not grid.t_ns.size:
        return []
    t, log = grid.t_ns[:1], grid.log_time_ns[:1]
    return [Series(name=name, entity_path=f"/{grid.topic}/limits/{field}", role=GRID_LIMIT_ROLE,
                   unit=unit, step=True, color=COLORS[GRID_LIMIT_ROLE], topic=grid.topic,
                   t_ns=t, log_time_ns=log, values=np.array([value], dtype=np.float64))
            for field, name, unit, value in (
                ("v_min_pu", "band: lowest", "p.u.", limits.v_min_pu),
                ("v_max_pu", "band: highest", "p.u.", limits.v_max_pu),
                ("loading_max_pct", "loading limit", "%", limits.loading_max_pct))]


HOLD_PERIOD_NS = 1_000_000_000
"""A step series (P_ref, availability, gains) gets a sample at least this often, ns, with the
value it holds, up to the run's end: it is drawn in any window of the view, however short."""


def held(series: Series, end_ns: int | None, period_ns: int = HOLD_PERIOD_NS) -> Series:
    """``series`` with the value it holds repeated every ``period_ns`` between its samples
    and after the last up to ``end_ns`` (a step series only; a dense one is left as it is)."""
    t = series.t_ns
    if not series.step or not t.size:
        return series
    end = max(int(t[-1]), end_ns or 0)
    gaps = np.diff(np.append(t, end))
    if gaps.max(initial=0) <= period_ns:
        return series
    grid = np.arange(int(t[0]), end + 1, period_ns, dtype=np.int64)
    grid = grid[~np.isin(grid, t)]
    at = np.searchsorted(t, grid, side="right") - 1
    order = np.argsort(np.concatenate([t, grid]), kind="stable")
    delay = series.log_time_ns - series.t_ns
    return dataclasses.replace(
        series, t_ns=np.concatenate([t, grid])[order],
        log_time_ns=np.concatenate([series.log_time_ns, grid + delay[at]])[order],
        values=np.concatenate([series.values, series.values[at]])[order])


def log_style(rec, series: Series, der_ids: Iterable[str] = ()) -> None:
    """Log the static style of ``series``: its name with the unit shown (``P_IP [MW]``), its
    colour (a DER's own among ``der_ids``, :func:`~adnmesh.results.rules.series_color`) and
    step interpolation for a step series."""
    import rerun as rr

    color = series_color(series.role, series.der, der_ids, series.color)
    rec.log(rerun_entity_path(series.entity_path),
            rr.SeriesLines(names=series.label, colors=color,
                           widths=1.0 if series.role == GRID_LIMIT_ROLE else None,
                           interpolation_mode="StepAfter" if series.step else "Linear"),
            static=True)


def send_series(rec, series: Series, t0_ns: int) -> None:
    """Send the samples of ``series`` on both timelines (columnar, in slices), in the unit
    shown (:meth:`~adnmesh.results.series.Series.shown`: MW, Mvar, 1/MW, 1/(MW s))."""
    import rerun as rr

    path = rerun_entity_path(series.entity_path)
    values = series.shown()
    for at in range(0, series.t_ns.size, _SEND_ROWS):   # in slices: Rerun's memory is per row
        rows = slice(at, at + _SEND_ROWS)
        rec.send_columns(
            path,
            indexes=[rr.TimeColumn(SIM_TIMELINE, duration=_durations(series.t_ns[rows], t0_ns)),
                     rr.TimeColumn(DELIVERY_TIMELINE,
                                   duration=_durations(series.log_time_ns[rows], t0_ns))],
            columns=rr.Scalars.columns(scalars=values[rows]))


def events_path(event: Event) -> str:
    """The Rerun entity of the event log of ``event``'s key."""
    return rerun_entity_path(f"/{event.topic}/events")


def send_events(rec, events: list[Event], t0_ns: int) -> None:
    """Send ``events`` as ``TextLog`` entries, one entity per key."""
    import rerun as rr

    by_path: dict[str, list] = {}
    for event in events:
        by_path.setdefault(events_path(event), []).append(event)
    for path, found in by_path.items():
        rec.send_columns(
            path,
            indexes=[rr.TimeColumn(SIM_TIMELINE,
                                   duration=_durations([e.t_ns for e in found], t0_ns))],
            columns=rr.TextLog.columns(text=[e.text for e in found],
                                       level=[_LEVELS.get(e.level, "INFO") for e in found]))


_SEND_ROWS = 8192


def log_run(rec, run: RunData, *, release: bool = False) -> None:
    """Log every series and event of ``run`` to the Rerun recording stream ``rec``.

    With ``release``, each series is removed from ``run.series`` once it is sent (memory).
    """
    end_ns = run.end_ns()
    for path in list(run.series):
        series = run.series.pop(path) if release else run.series[path]
        log_style(rec, series, run.der_ids)
        send_series(rec, held(series, end_ns), run.t0_ns)
        rec.flush()     # encoded and written: its Arrow copies are let go (memory)
        del series
    send_events(rec, run.events, run.t0_ns)


def export_rrd(recording: Recording | ScannedRecording, out_path: str | Path, *,
               run: RunData | None = None, release: bool = False) -> Path:
    """Write ``recording`` as a Rerun ``.rrd`` file with its blueprint; return the path.

    ``run`` is its series (:func:`~adnmesh.results.series.read_run` reads both in one pass);
    without it they are extracted from ``recording`` (a :class:`Recording`). With ``release``
    the series are taken out of ``run`` as they are written (for a caller that is done with
    them: less memory).

    Needs no display and starts no viewer or server.
    """
    import rerun as rr

    run = run if run is not None else extract(recording)
    limits = {s.entity_path: s for s in limit_series(run, recorded_grid_limits(recording.run))}
    if release:
        run.series.update(limits)
    elif limits:
        run = dataclasses.replace(run, series={**run.series, **limits})
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    recording_id = recording.run.get("run_id") or recording.path.stem
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
    try:
        rec.save(out_path, default_blueprint=blueprint(run))
        rec.send_recording_name(recording_id)
        log_run(rec, run, release=release)
        rec.flush()
    finally:
        rec.disconnect()
    return out_path


def rerun_executable() -> list[str]:
    """Return the command that runs the ``rerun`` program shipped with rerun-sdk.

    The binary itself, not ``python -m rerun`` (which would run it as a child process that
    outlives a killed parent).
    """
    try:
        import rerun_cli
    except ImportError:
        rerun_cli = None
    if rerun_cli is not None:
        binary = Path(rerun_cli.__file__).parent / ("rerun.exe" if os.name == "nt" else "rerun")
        if binary.is_file():
            return [str(binary)]
    found = shutil.which("rerun")
    return [found] if found else [sys.executable, "-m", "rerun_cli"]


VIEWER_HOST = "127.0.0.1"
"""The address every viewer adnmesh starts is bound to (its gRPC server and web server)."""


def grpc_url(port: int, host: str = VIEWER_HOST) -> str:
    """The address of a Rerun viewer's gRPC server (what SDKs and web viewers connect to)."""
    return f"rerun+http://{host}:{port}/proxy"


def web_viewer_url(web_port: int, grpc_port: int, host: str = VIEWER_HOST) -> str:
    """The address that opens Rerun's web viewer (served at ``web_port``) on the data of the
    gRPC server at ``grpc_port``.

    As the ``rerun`` program builds it (rerun 0.41, ``re_sdk/src/web_viewer.rs``: the web
    server's URL, then ``?url=`` and the gRPC server's ``rerun+http://.../proxy`` address,
    percent-encoded), but with ``host`` where rerun writes ``localhost``: the servers are bound
    to 127.0.0.1 only, and a browser may try ``localhost`` as ::1 first. Without ``?url=`` the
    web viewer opens on its welcome page.
    """
    return (f"http://{host}:{web_port}/?url="
            + urllib.parse.quote(grpc_url(grpc_port, host), safe=""))


def viewer_command(rrd_path: str | Path, *, web: bool = False, port: int | None = None,
                   web_port: int | None = None) -> list[str]:
    """Return the command that opens ``rrd_path`` in the Rerun viewer, bound to 127.0.0.1.

    ``web`` serves the web viewer over HTTP (``web_port``, default Rerun's 9090) instead of
    starting the native viewer. ``port`` is the viewer's gRPC port (default: Rerun's); the web
    viewer is opened on the data by :func:`web_viewer_url` with the same ports.
    """
    command = [*rerun_executable(), str(rrd_path), "--bind", VIEWER_HOST]
    if port is not None:
        command += ["--port", str(port)]
    if web:
        command += ["--web-viewer"]
        if web_port is not None:
            command += ["--web-viewer-port", str(web_port)]
    return command
