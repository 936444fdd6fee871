"""``adnmesh inspect RUN.mcap``: what a recording holds, and recovery of a killed run's file."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import yaml
from rich.console import Console
from rich.table import Table

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
from adnmesh.recording.figures import run_figures, step_table
from adnmesh.recording.series import RunData, extract

__all__ = ["EXIT_PROBLEMS", "add_parser", "run", "settling_band_pct", "topic_table"]

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
        "does not match its JSON Schema.",
    )
    parser.add_argument("recording", metavar="RUN", help="recording (.mcap), e.g. logs/<run>.mcap")
    parser.add_argument("--recover-to", metavar="OUT", type=Path,
                        help="where to write the recovered file of a truncated recording")
    parser.add_argument("--validate", action="store_true",
                        help="check every message against its channel's JSON Schema")
    parser.add_argument("--metadata", action="store_true",
                        help="print every metadata record in full (including the config)")
    return parser


def _s(t_ns: int, t0_ns: int) -> str:
    return f"{(t_ns - t0_ns) / 1e9:.3f}"


def topic_table(recording: Recording, t0_ns: int) -> Table:
    """Return the per-topic table: type, count, first and last send time, s."""
    table = Table(title=f"{len(recording.channels)} topics", title_justify="left")
    for column in ("topic", "type", "messages", "first [s]", "last [s]"):
        table.add_column(column, justify="left" if column in ("topic", "type") else "right")
    first: dict[str, int] = {}
    last: dict[str, int] = {}
    for m in recording.messages:
        first[m.topic] = min(first.get(m.topic, m.publish_time_ns), m.publish_time_ns)
        last[m.topic] = max(last.get(m.topic, m.publish_time_ns), m.publish_time_ns)
    for topic, count in recording.counts().items():
        info = recording.channels[topic]
        table.add_row(topic, info.schema_name or "-", str(count),
                      _s(first[topic], t0_ns) if topic in first else "-",
                      _s(last[topic], t0_ns) if topic in last else "-")
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


def _print_faults_and_grid(console: Console, recording: Recording, band_pct: float) -> None:
    """The per-fault and grid figures of ``adnmesh up``'s summary, from the same series."""
    from adnmesh.runtime.summary import MESSAGE_TYPES, RunSeries, fault_table, grid_line, \
        summarize

    series = RunSeries()
    for message in sorted(recording.messages, key=lambda m: m.publish_time_ns):
        if message.schema_name in MESSAGE_TYPES:
            try:
                series.add(message.schema_name, json.loads(message.data))
            except (ValueError, KeyError, TypeError):
                continue                  # not one of adnmesh's messages: no figures from it
    end = max((m.publish_time_ns for m in recording.messages), default=0)
    summary = summarize(series, end_ns=end, band_pct=band_pct)
    if summary.faults:
        console.print(fault_table(summary.faults))
    if summary.grid is not None:
        console.print(grid_line(summary.grid))


def _print_figures(console: Console, run_data: RunData, band_pct: float,
                   recording: Recording) -> None:
    figures = run_figures(run_data, band_pct=band_pct)
    if figures.steps:
        console.print(step_table(figures.steps, figures.band_pct))
    if figures.rms_error_w is not None:
        console.print(f"tracking error P_IP - P_ref: RMS {figures.rms_error_w / 1e6:.4f} MW, "
                      f"max {figures.max_error_w / 1e6:.4f} MW")
    console.print(f"events: {figures.gain_switches} gain switches, "
                  f"{figures.availability_changes} availability changes, {figures.faults} fault "
                  f"events, {figures.mode_changes} DER mode changes")
    _print_faults_and_grid(console, recording, band_pct)
    initial = next((e for e in run_data.events if e.kind == "availability"), None)
    for event in run_data.events:
        if event is not initial:  # the first availability event is the initial state
            console.print(f"  {run_data.seconds(event.t_ns):9.3f} s  {event.text}")


def _check_counts(console: Console, recording: Recording) -> bool:
    published = recording.metadata.get(PUBLISHED_METADATA)
    if published is None:
        console.print("published counts: not in the recording (not checked)")
        return True
    uncounted = recording.metadata.get(UNCOUNTED_METADATA, {})
    recorded = {k: v for k, v in recording.counts().items() if k not in uncounted}
    differences = count_differences({k: int(v) for k, v in published.items()}, recorded)
    if not differences:
        total = sum(recorded.values())
        console.print(f"published counts: every message recorded ({total} on {len(published)} "
                      "topics)")
        for topic, why in uncounted.items():
            if topic in recording.channels:
                console.print(f"  not counted: {topic} ({why})")
        return True
    console.print(f"published counts: MISMATCH on {len(differences)} topic(s)")
    for difference in differences:
        console.print(f"  {difference}")
    return False


def run(args: argparse.Namespace) -> int:
    """Read ``args.recording`` and print its summary; recover it if it is truncated."""
    console = Console(highlight=False, markup=False, soft_wrap=True)
    path = Path(args.recording)
    recording = read_recording(path)
    size = path.stat().st_size
    state = "complete" if recording.complete else "TRUNCATED"
    console.print(f"{path}: {state} MCAP recording, {len(recording.messages)} messages on "
                  f"{len(recording.channels)} topics, {size} bytes ({recording.library})")
    if not recording.complete:
        out = args.recover_to or path.with_name(path.stem + ".recovered.mcap")
        recovered = recover(path, out)
        console.print(f"recovered {recovered} messages into {out} "
                      f"({recording.dropped_bytes} bytes of an unfinished record dropped)")
    run_meta = recording.run
    if run_meta:
        console.print("run: " + ", ".join(f"{k} {run_meta[k]}" for k in _RUN_KEYS if k in run_meta))
    else:
        console.print(f"run: no {RUN_METADATA} metadata (not an adnmesh recording?)")
    if args.metadata:
        for name, data in recording.metadata_records:
            console.print(f"metadata {name}:")
            for key, value in data.items():
                console.print(f"  {key}: " + value.replace("\n", "\n    ").rstrip())
    run_data = extract(recording)
    span = recording.time_range_ns()
    if span is not None:
        console.print(f"time: {_s(span[0], run_data.t0_ns)} to {_s(span[1], run_data.t0_ns)} s "
                      f"(sim_time, send and delivery times)")
    console.print(topic_table(recording, run_data.t0_ns))
    _print_figures(console, run_data, settling_band_pct(recording), recording)
    ok = _check_counts(console, recording)
    if args.validate:
        problems = validate_recording(recording, limit=20)
        if problems:
            ok = False
            console.print(f"schema check: {len(problems)}{'+' if len(problems) == 20 else ''} "
                          "problems")
            for problem in problems:
                console.print(f"  {problem}")
        else:
            console.print(f"schema check: all {len(recording.messages)} messages valid")
    return 0 if ok else EXIT_PROBLEMS
