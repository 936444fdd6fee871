"""``adnmesh export RUN.mcap [--csv DIR] [--foxglove-layout FILE]``: a recording's time
series as CSV files, and a Foxglove layout for it."""

from __future__ import annotations

import argparse
from pathlib import Path

from adnmesh.commands.replay import note_if_truncated
from adnmesh.errors import UsageError

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``export`` subparser."""
    parser = subparsers.add_parser(
        "export",
        help="export a recording's time series to CSV, or a Foxglove layout for it",
        description="Export the recording RUN. --csv DIR writes one CSV file per bus key "
        "(time_s, then a column per series with its unit: P_IP [MW], P_ref [MW], P_Y, K_P "
        "[1/MW], K_I [1/(MW s)], every DER's infeed and set-point [MW], availability 0/1, the "
        "grid's extremes [p.u., %] and Q_IP [Mvar]), series.csv (which series is where) and "
        "events.csv; pandas reads each with pd.read_csv. --foxglove-layout FILE writes a "
        "Foxglove layout of the run's plots and event log (File > Import layout). Exit code "
        "0 when written, 2 for a user error (no such file, not a recording, nothing asked "
        "for).",
    )
    parser.add_argument("recording", metavar="RUN", help="recording (.mcap), e.g. logs/<run>.mcap")
    parser.add_argument("--csv", metavar="DIR", type=Path,
                        help="write the CSV files into DIR (made if missing)")
    parser.add_argument("--foxglove-layout", metavar="FILE", type=Path,
                        help="write a Foxglove layout (JSON) for the run's topics to FILE")
    return parser


def run(args: argparse.Namespace) -> int:
    """Read ``args.recording`` once and write what was asked for."""
    from adnmesh.results.csv_export import write_csv
    from adnmesh.results.foxglove_layout import foxglove_layout, layout_json
    from adnmesh.results.series import read_run

    if args.csv is None and args.foxglove_layout is None:
        raise UsageError("export: say what to write: --csv DIR and/or --foxglove-layout FILE")
    if args.csv is not None and args.csv.exists() and not args.csv.is_dir():
        raise UsageError(f"--csv {args.csv}: exists and is not a folder")
    found, _ = read_run(args.recording)
    note_if_truncated(found.recording)
    run_data = found.run
    if args.csv is not None:
        files = write_csv(run_data, args.csv)
        print(f"{args.csv}: {len(files) - 2} CSV files of {len(run_data.series)} series, "
              f"{files[0].name} (the list), {files[1].name} ({len(run_data.events)} events)")
    if args.foxglove_layout is not None:
        grid = _grid(found.recording, run_data)
        layout = foxglove_layout(grid, run_data.der_ids,
                                 grid_model=run_data.one("grid_v_min") is not None,
                                 events_topic=found.recording.run.get("events_topic") or None,
                                 reactive=run_data.one("q_ref") is not None)
        args.foxglove_layout.parent.mkdir(parents=True, exist_ok=True)
        args.foxglove_layout.write_text(layout_json(layout), encoding="utf-8")
        print(f"{args.foxglove_layout}: Foxglove layout for grid {grid} and "
              f"{len(run_data.der_ids)} DERs")
    return 0


def _grid(recording, run_data) -> str:
    """The grid name of the recording: the second level of its keys."""
    for topic in [*(s.topic for s in run_data.series.values()), *recording.channels]:
        parts = topic.split("/")
        if len(parts) > 2 and parts[0] == "adn":
            return parts[1]
    raise UsageError(f"{recording.path}: no adn/<grid>/... topics: not an adnmesh recording")
