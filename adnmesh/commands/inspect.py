"""``adnmesh inspect RUN.mcap``: what a recording holds, and recovery of a killed run's file."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import yaml
from rich.console import Console
from rich.table import Table

from adnmesh.commands import input_file, output_path
from adnmesh.config import Constraints
from adnmesh.recording import (
    PUBLISHED_METADATA,
    RUN_METADATA,
    UNCOUNTED_METADATA,
    Recording,
    count_differences,
    read_recording,
    recover,
    validate_recording,
)
from adnmesh.results.figures import RunFigures, run_figures, step_table
from adnmesh.results.rules import natural_key
from adnmesh.results.series import RunData, grid_of_topic, read_grid
from adnmesh.recording.stream import ScannedRecording

__all__ = ["EXIT_PROBLEMS", "add_parser", "run", "settling_band_pct", "sorted_topics",
           "topic_table"]

EXIT_PROBLEMS = 1
"""Exit code when the recording is readable but wrong: counts differ from what the agents
published, or (with ``--validate``) a message does not match its schema."""

_RUN_KEYS = ("run_id", "clock", "seed", "adnmesh_version", "config_path", "config_sha256",
             "table_sha256")


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``inspect`` subparser."""
    parser = subparsers.add_parser(
        "inspect",
        help="summarise a recording; recover a killed run's file",
        description="Print what the recording RUN holds: the run's metadata, every topic with "
        "its message type, count and time range, and the summary figures (P_IP's response to "
        "each P_ref step, tracking error, gain switches, availability changes, faults). A "
        "truncated recording (killed run) is recovered into a complete file, by default RUN "
        "with the suffix .recovered.mcap. Exit code 1 if the recorded counts differ from those "
        "the agents published (when the recording has them) or, with --validate, if a message "
        "does not match its JSON Schema; 0 otherwise; 2 for a user error (no such file, not "
        "an MCAP file, a damaged one).",
    )
    parser.add_argument("recording", metavar="RUN", help="recording (.mcap), e.g. logs/<run>.mcap")
    parser.add_argument("--recover-to", metavar="OUT", type=Path,
                        help="where to write the recovered file of a truncated recording")
    parser.add_argument("--validate", action="store_true",
                        help="check every message against its channel's JSON Schema")
    parser.add_argument("--metadata", action="store_true",
                        help="print every metadata record in full (including the config)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object instead (file, run, topics, counts, "
                        "figures, events; times in s of sim time, powers in W)")
    parser.add_argument("--grid", metavar="NAME",
                        help="a recording of several grids (a hierarchy's): only this grid's "
                        "topics, figures and events (default: the figures of the recording's "
                        "own grid, the upper level's)")
    return parser


def _s(t_ns: int, t0_ns: int) -> str:
    return f"{(t_ns - t0_ns) / 1e9:.3f}"


def sorted_topics(recording: ScannedRecording) -> list:
    """The recording's ``(topic, stats)`` in the natural order of the topics (``der/SGen2``
    before ``der/SGen10``), as ``inspect`` lists them."""
    return sorted(recording.channel_stats.items(), key=lambda item: natural_key(item[0]))


def topic_table(recording: ScannedRecording, t0_ns: int, grid: str | None = None) -> Table:
    """Return the per-topic table, sorted (:func:`sorted_topics`): type, count, first and last
    send time, s (only the topics of ``grid``, if given)."""
    rows = [(topic, stats) for topic, stats in sorted_topics(recording)
            if grid is None or grid_of_topic(topic) == grid]
    title = f"{len(rows)} topics" + ("" if grid is None else f" of grid {grid}")
    table = Table(title=title, title_justify="left")
    for column in ("topic", "type", "messages", "first [s]", "last [s]"):
        table.add_column(column, justify="left" if column in ("topic", "type") else "right")
    for topic, stats in rows:
        seen = stats.count > 0
        table.add_row(topic, stats.info.schema_name or "-", str(stats.count),
                      _s(stats.first_publish_ns, t0_ns) if seen else "-",
                      _s(stats.last_publish_ns, t0_ns) if seen else "-")
    return table


def settling_band_pct(recording: Recording) -> float:
    """The settling band of the recorded run's config (``constraints.settling_band_pct``, as
    ``adnmesh up``'s summary uses it), else the default, %."""
    try:
        document = yaml.safe_load(recording.run.get("config", "")) or {}
        band = document.get("constraints", {}).get("settling_band_pct")
    except (yaml.YAMLError, AttributeError):
        band = None
    valid = isinstance(band, int | float) and not isinstance(band, bool) and band > 0
    return float(band) if valid else Constraints().settling_band_pct


def planned_steps(recording: Recording) -> tuple[list[tuple[float, float]], float]:
    """The recorded run's scenario steps ``(t_s, delta_w)`` and the CPFC's sampling period, s
    (``adnmesh up``'s summary says what became of each); none if the config is unreadable."""
    try:
        document = yaml.safe_load(recording.run.get("config", "")) or {}
        steps = [(float(s["t_s"]), float(s["delta_w"]))
                 for s in document.get("scenario", {}).get("p_ref_steps", ())]
        period = float((document.get("runtime") or {}).get("pi_period_s", 0.01))
    except (yaml.YAMLError, AttributeError, KeyError, TypeError, ValueError):
        return [], 0.0
    return steps, period


class _SummaryMessages:
    """The messages ``adnmesh up``'s summary reads (:class:`~adnmesh.results.summary.RunSeries`),
    taken in the same pass as the series: ``P_IP`` as columns, ``p_y`` only where it carries a
    switch record, the few others whole."""

    def __init__(self) -> None:
        from adnmesh.results.summary import SUMMARY_TYPES

        self.types = SUMMARY_TYPES
        self.p_ip: list[tuple[np.ndarray, ...]] = []
        self.whole: list[tuple[int, int, str, bytes]] = []

    def sink_for(self, info):
        kind = info.schema_name
        if kind not in self.types:
            return None
        if kind == "p_ip":
            return _Fields(("t_send_ns", "p_ip_w", "q_ip_var"), self._p_ip)
        if kind in ("p_y", "q_y"):
            return _Fields(("switch", "design"), lambda batch, columns: self._y(kind, batch,
                                                                               columns))
        return lambda batch: self._keep(kind, batch, range(len(batch)))

    def _p_ip(self, batch, columns) -> None:
        t, p = columns.columns["t_send_ns"], columns.columns["p_ip_w"]
        q = columns.columns.get("q_ip_var") or [None] * len(t)
        rows = [i for i in range(len(t)) if columns.valid[i] and isinstance(t[i], int)
                and isinstance(p[i], int | float)]
        self.p_ip.append((batch.publish_time_ns[rows], batch.ordinal[rows],
                          np.asarray([t[i] for i in rows], dtype=np.int64),
                          np.asarray([p[i] for i in rows], dtype=np.float64),
                          np.asarray([q[i] if isinstance(q[i], int | float) else np.nan
                                      for i in rows], dtype=np.float64)))

    def _y(self, kind: str, batch, columns) -> None:
        switch, design = columns.columns["switch"], columns.columns["design"]
        self._keep(kind, batch, [i for i, (s, d) in enumerate(zip(switch, design))
                                 if isinstance(s, dict) or isinstance(d, dict)])

    def _keep(self, kind: str, batch, rows) -> None:
        payloads = batch.payloads
        for i in rows:
            self.whole.append((int(batch.publish_time_ns[i]), int(batch.ordinal[i]), kind,
                               payloads[i]))

    def series(self):
        """The :class:`~adnmesh.results.summary.RunSeries` of the messages taken."""
        from adnmesh.results.summary import RunSeries

        series = RunSeries()
        if self.p_ip:
            publish, ordinal, t_ns, p_w, q_var = (np.concatenate(c) for c in zip(*self.p_ip))
            order = np.lexsort((ordinal, publish))
            series.p_ip_t_ns, series.p_ip_w = t_ns[order].tolist(), p_w[order].tolist()
            with_q = order[np.isfinite(q_var[order])]
            series.q_ip_t_ns, series.q_ip_var = t_ns[with_q].tolist(), q_var[with_q].tolist()
        for _, _, kind, payload in sorted(self.whole, key=lambda m: m[:2]):
            try:
                series.add(kind, json.loads(payload))
            except (ValueError, KeyError, TypeError):
                continue                  # not one of adnmesh's messages: no figures from it
        if not series.p_ref_t_ns:         # P_IP without P_ref: no deviations to figure
            series.p_ip_t_ns, series.p_ip_w = [], []
        return series


class _Fields:
    """A sink that wants the payload fields ``fields`` decoded."""

    def __init__(self, fields: tuple[str, ...], take) -> None:
        self.fields, self._take = fields, take

    def __call__(self, batch) -> None:
        from adnmesh.recording.stream import decode_fields

        self._take(batch, batch.columns or decode_fields(batch, self.fields))


def _summary(recording: ScannedRecording, messages: _SummaryMessages, band_pct: float):
    """``adnmesh up``'s summary of the recorded run (its per-fault and grid figures)."""
    from adnmesh.results.summary import summarize

    ends = [s.last_publish_ns for s in recording.channel_stats.values() if s.count]
    planned, sample_s = planned_steps(recording)
    return summarize(messages.series(), end_ns=max(ends, default=0), band_pct=band_pct,
                     planned_steps=planned, sample_s=sample_s)


def _print_figures(console: Console, run_data: RunData, figures: RunFigures, summary) -> None:
    from adnmesh.results.design_check import design_lines
    from adnmesh.results.summary import coupling_line, fault_table, grid_line, scenario_lines

    if figures.steps:
        console.print(step_table(figures.steps, figures.band_pct, checks=summary.design_checks))
    for line in design_lines(summary.design_checks):
        console.print(line)
    if summary.coupling is not None:
        console.print(step_table(summary.q_steps, figures.band_pct, "Q_IP after each Q_ref step",
                                 summary.q_design_checks, unit="var"))
        for line in design_lines(summary.q_design_checks, unit="var"):
            console.print(line)
        console.print(coupling_line(summary.coupling))
    for line in scenario_lines(summary.scenario_steps):
        console.print(line)
    if figures.rms_error_w is not None:
        console.print(f"tracking error P_IP - P_ref: RMS {figures.rms_error_w / 1e6:.4f} MW, "
                      f"max {figures.max_error_w / 1e6:.4f} MW")
    console.print(f"events: {figures.gain_switches} gain switches, "
                  f"{figures.availability_changes} availability changes, {figures.faults} fault "
                  f"events, {figures.mode_changes} DER mode changes")
    if summary.faults:
        console.print(fault_table(summary.faults))
    if summary.grid is not None:
        console.print(grid_line(summary.grid))
    for event in _shown_events(run_data):
        console.print(f"  {run_data.seconds(event.t_ns):9.3f} s  {event.text}")


def _shown_events(run_data: RunData) -> list:
    """The events, without the first availability event (the initial state)."""
    initial = next((e for e in run_data.events if e.kind == "availability"), None)
    return [e for e in run_data.events if e is not initial]


def _count_check(recording: ScannedRecording) -> tuple[str, list, dict]:
    """("absent" | "ok" | "mismatch", the differences, the topics not counted and why)."""
    published = recording.metadata.get(PUBLISHED_METADATA)
    if published is None:
        return "absent", [], {}
    uncounted = dict(recording.metadata.get(UNCOUNTED_METADATA, {}))
    if recording.run.get("events_topic"):
        uncounted[recording.run["events_topic"]] = "the recorder's log of the run's events"
    recorded = {k: v for k, v in recording.counts().items() if k not in uncounted}
    differences = count_differences({k: int(v) for k, v in published.items()}, recorded)
    shown = {topic: why for topic, why in uncounted.items() if topic in recording.channels}
    return ("mismatch" if differences else "ok"), differences, shown


def _check_counts(console: Console, recording: ScannedRecording) -> bool:
    state, differences, uncounted = _count_check(recording)
    if state == "absent":
        console.print("published counts: not in the recording (not checked)")
        return True
    if state == "ok":
        published = recording.metadata[PUBLISHED_METADATA]
        total = sum(v for k, v in recording.counts().items() if k not in uncounted)
        console.print(f"published counts: every message recorded ({total} on {len(published)} "
                      "topics)")
        for topic, why in uncounted.items():
            console.print(f"  not counted: {topic} ({why})")
        return True
    console.print(f"published counts: MISMATCH on {len(differences)} topic(s)")
    for difference in differences:
        console.print(f"  {difference}")
    return False


def run(args: argparse.Namespace) -> int:
    """Read ``args.recording`` and print its summary; recover it if it is truncated."""
    path = input_file(args.recording)
    if args.recover_to is not None:
        output_path(args.recover_to, "--recover-to")
    recording, shown, grids = _read(path, args.grid)
    grid, run_data, figures, summary = shown
    recovered_to = None
    if not recording.complete:
        recovered_to = args.recover_to or path.with_name(path.stem + ".recovered.mcap")
        recover(path, recovered_to)
    problems = validate_recording(read_recording(path), limit=20) if args.validate else None
    if args.json:
        report = _json_report(path, recording, shown, grids, recovered_to, problems,
                              args.grid)
        sys.stdout.write(json.dumps(report, indent=1) + "\n")
        ok = report["counts"]["check"] != "mismatch" and not problems
        return 0 if ok else EXIT_PROBLEMS
    console = Console(highlight=False, markup=False, soft_wrap=True,
                      width=None if sys.stdout.isatty() else _PIPE_WIDTH)
    _print_head(console, path, recording, run_data, recovered_to, args.metadata)
    console.print(topic_table(recording, run_data.t0_ns, args.grid))
    if len(grids) > 1:
        console.print(f"{len(grids)} grids: {', '.join(grids)}; the figures below are grid "
                      f"{grid}'s (another grid's: --grid NAME)")
    _print_figures(console, run_data, figures, summary)
    ok = _check_counts(console, recording)
    if problems is not None:
        ok = _print_problems(console, problems, recording.message_count) and ok
    return 0 if ok else EXIT_PROBLEMS


def _read(path: Path, grid: str | None):
    """``(recording, shown, grids)``: the file, ``(grid, run data, figures, summary)`` of the
    grid asked for or, in a recording of several (a hierarchy's), of its own (its run
    metadata's ``grid``: the upper level's) or else the first
    (:func:`~adnmesh.results.series.read_grid`), and the recording's grids."""
    found, messages, grids, shown = read_grid(path, grid, also=_SummaryMessages)
    recording = found.recording
    band = settling_band_pct(recording)
    return recording, (shown, found.run, run_figures(found.run, band_pct=band),
                       _summary(recording, messages, band)), grids


_PIPE_WIDTH = 10_000
"""Console width when the output is no terminal: tables at their natural width, no name cut."""


def _print_head(console: Console, path: Path, recording: ScannedRecording, run_data: RunData,
                recovered_to: Path | None, metadata: bool) -> None:
    state = "complete" if recording.complete else "TRUNCATED"
    console.print(f"{path}: {state} MCAP recording, {recording.message_count} messages on "
                  f"{len(recording.channel_stats)} topics, {path.stat().st_size} bytes "
                  f"({recording.library})")
    if recovered_to is not None:
        console.print(f"recovered {recording.message_count} messages into {recovered_to} "
                      f"({recording.dropped_bytes} bytes of an unfinished record dropped)")
    run_meta = recording.run
    if run_meta:
        console.print("run: " + ", ".join(f"{k} {run_meta[k]}" for k in _RUN_KEYS if k in run_meta))
    else:
        console.print(f"run: no {RUN_METADATA} metadata (not an adnmesh recording?)")
    if metadata:
        for name, data in recording.metadata_records:
            console.print(f"metadata {name}:")
            for key, value in data.items():
                console.print(f"  {key}: " + value.replace("\n", "\n    ").rstrip())
    span = recording.time_range_ns()
    if span is not None:
        console.print(f"time: {_s(span[0], run_data.t0_ns)} to {_s(span[1], run_data.t0_ns)} s "
                      f"(sim_time, send and delivery times)")


def _print_problems(console: Console, problems: list, messages: int) -> bool:
    """The schema check's result (``--validate``); True if every message is valid."""
    if problems:
        console.print(f"schema check: {len(problems)}{'+' if len(problems) == 20 else ''} "
                      "problems")
        for problem in problems:
            console.print(f"  {problem}")
        return False
    console.print(f"schema check: all {messages} messages valid")
    return True


def _json_report(path: Path, recording: ScannedRecording, shown: tuple, grids: list,
                 recovered_to: Path | None, problems: list | None, grid: str | None) -> dict:
    """``inspect --json``: one object with the file, topics, counts, figures and events
    (``shown``: ``(grid, run data, figures, summary)`` of the grid the figures are of; ``grids``
    every grid of the recording).

    Times are s of sim time from t0; powers W; gains 1/W and 1/(W s); figures that do not
    exist (no 90 % crossing, not settled in the window) are null.
    """
    name, run_data, figures, summary = shown

    def seconds(t_ns):
        return None if t_ns is None else (t_ns - run_data.t0_ns) / 1e9

    state, differences, uncounted = _count_check(recording)
    span = recording.time_range_ns()
    topics = [{"topic": topic, "type": stats.info.schema_name or None, "messages": stats.count,
               "first_s": seconds(stats.first_publish_ns),
               "last_s": seconds(stats.last_publish_ns)}
              for topic, stats in sorted_topics(recording)
              if grid is None or grid_of_topic(topic) == grid]
    return _finite({
        "file": str(path), "complete": recording.complete, "bytes": path.stat().st_size,
        "library": recording.library, "messages": recording.message_count,
        "dropped_bytes": recording.dropped_bytes,
        "recovered_to": None if recovered_to is None else str(recovered_to),
        "run": {k: v for k, v in recording.run.items() if k != "config"},
        "time_s": None if span is None else [seconds(span[0]), seconds(span[1])],
        "topics": topics,
        "counts": {"check": state, "uncounted": uncounted,
                   "differences": [dataclasses.asdict(d) for d in differences]},
        "grids": grids, "figures_of": name, **_figures_json(run_data, figures, summary),
        "schema_check": None if problems is None else [str(p) for p in problems],
    })


def _figures_json(run_data: RunData, figures: RunFigures, summary) -> dict:
    """``{"figures": ..., "events": ...}`` of one grid for :func:`_json_report`."""
    steps = [{"t_s": s.t_s, "step_w": s.step_w, "p_ref_w": s.p_ref_w, "window_s": s.window_s,
              "steady_error_w": s.steady_error_w,
              "settled": bool(s.figures is not None
                              and np.isfinite(s.figures.settling_time_s)),
              **({} if s.figures is None else dataclasses.asdict(s.figures))}
             for s in figures.steps]
    summary_json = summary.to_json()
    return {
        "figures": {"band_pct": figures.band_pct, "steps": steps,
                    "rms_error_w": figures.rms_error_w, "max_error_w": figures.max_error_w,
                    "gain_switches": figures.gain_switches,
                    "availability_changes": figures.availability_changes,
                    "faults": figures.faults, "mode_changes": figures.mode_changes,
                    "switches": summary_json["switches"],
                    "fault_figures": summary_json["faults"], "grid": summary_json["grid"],
                    "scenario_steps": summary_json["scenario_steps"],
                    "design_checks": summary_json["design_checks"],
                    "q_steps": summary_json["q_steps"], "coupling": summary_json["coupling"],
                    "q_design_checks": summary_json["q_design_checks"]},
        "events": [{"t_s": run_data.seconds(e.t_ns), "kind": e.kind, "level": e.level,
                    "text": e.text, "topic": e.topic} for e in _shown_events(run_data)],
    }


def _finite(value):
    """``value`` with NaN and infinities as None (JSON has neither)."""
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, np.generic):
        return _finite(value.item())
    return value
