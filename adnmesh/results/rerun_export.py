"""Converting a recording into Rerun data (``adnmesh replay``).

Rerun reads MCAP itself but does not decode JSON channels, so adnmesh converts: every series of
:func:`adnmesh.results.series.extract` becomes an entity ``/<key>/<field>`` of ``Scalars``
with a static ``SeriesLines`` style (its name, and step interpolation for step series), indexed
by two timelines: ``sim_time`` (send time, from t0) and ``delivery_time`` (delivery time, from
t0), both durations. Events (gain switches, availability changes, faults) become ``TextLog``
entries at ``/<key>/events``. A blueprint lays out P_IP with P_ref, P_Y, the DERs' infeed and
setpoints, availability, the gains and the event log.

:func:`export_rrd` writes an ``.rrd`` file without any viewer (headless);
:func:`viewer_command` is the command that opens one in a viewer bound to 127.0.0.1.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import sys
from pathlib import Path

import numpy as np

from adnmesh.recording.reader import Recording
from adnmesh.recording.stream import ScannedRecording
from adnmesh.results.rules import Event
from adnmesh.results.series import RunData, Series, extract

__all__ = [
    "APPLICATION_ID",
    "DELIVERY_TIMELINE",
    "SIM_TIMELINE",
    "HOLD_PERIOD_NS",
    "blueprint",
    "events_path",
    "export_rrd",
    "held",
    "log_run",
    "log_style",
    "rerun_entity_path",
    "rerun_executable",
    "send_events",
    "send_series",
    "viewer_command",
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


def _views(run: RunData, roles: tuple[str, ...]) -> list[str]:
    return [rerun_entity_path(s.entity_path) for role in roles for s in run.by_role(role)]


def blueprint(run: RunData):
    """Return the Rerun blueprint for ``run``: the main plots, laid out."""
    import rerun.blueprint as rrb

    def plot(name: str, *roles: str):
        return rrb.TimeSeriesView(name=name, origin="/", contents=_views(run, roles) or [],
                                  time_ranges=whole, axis_x=rrb.TimeAxis(view_range=everything))

    import rerun as rr

    everything = rr.encodings.TimeRange(start=rrb.TimeRangeBoundary.infinite(),
                                        end=rrb.TimeRangeBoundary.infinite())
    whole = rrb.VisibleTimeRange(SIM_TIMELINE, start=rrb.TimeRangeBoundary.infinite(),
                                 end=rrb.TimeRangeBoundary.infinite())    # the whole run

    events = sorted({events_path(e) for e in run.events})
    return rrb.Blueprint(
        rrb.Vertical(
            plot("P_IP and P_ref [W]", "p_ref", "p_ip"),
            plot("P_Y", "p_y"),
            rrb.Horizontal(plot("DER infeed [W]", "der_infeed"),
                           plot("DER setpoints [W]", "der_setpoint")),
            rrb.Horizontal(plot("availability (1 = available)", "availability"),
                           plot("gains K_P [1/W], K_I [1/(W s)]", "kp", "ki"),
                           rrb.TextLogView(name="events", origin="/", contents=events or [])),
            row_shares=[3, 2, 2, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=SIM_TIMELINE, state="collapsed", play_state="paused"),
    )


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


def log_style(rec, series: Series) -> None:
    """Log the static style of ``series`` (its name; step interpolation for a step series)."""
    import rerun as rr

    rec.log(rerun_entity_path(series.entity_path),
            rr.SeriesLines(names=series.name, colors=series.color,
                           interpolation_mode="StepAfter" if series.step else "Linear"),
            static=True)


def send_series(rec, series: Series, t0_ns: int) -> None:
    """Send the samples of ``series`` on both timelines (columnar, in slices)."""
    import rerun as rr

    path = rerun_entity_path(series.entity_path)
    for at in range(0, series.t_ns.size, _SEND_ROWS):   # in slices: Rerun's memory is per row
        rows = slice(at, at + _SEND_ROWS)
        rec.send_columns(
            path,
            indexes=[rr.TimeColumn(SIM_TIMELINE, duration=_durations(series.t_ns[rows], t0_ns)),
                     rr.TimeColumn(DELIVERY_TIMELINE,
                                   duration=_durations(series.log_time_ns[rows], t0_ns))],
            columns=rr.Scalars.columns(scalars=series.values[rows]))


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
        log_style(rec, series)
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


def viewer_command(rrd_path: str | Path, *, web: bool = False, port: int | None = None,
                   web_port: int | None = None) -> list[str]:
    """Return the command that opens ``rrd_path`` in the Rerun viewer, bound to 127.0.0.1.

    ``web`` serves the web viewer over HTTP (``web_port``, default Rerun's 9090) instead of
    starting the native viewer. ``port`` is the viewer's gRPC port (default: Rerun's).
    """
    command = [*rerun_executable(), str(rrd_path), "--bind", "127.0.0.1"]
    if port is not None:
        command += ["--port", str(port)]
    if web:
        command += ["--web-viewer"]
        if web_port is not None:
            command += ["--web-viewer-port", str(web_port)]
    return command
