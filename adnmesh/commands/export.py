"""``adnmesh export RUN.mcap [--csv DIR] [--foxglove-layout FILE] [--grid NAME]``: a
recording's time series as CSV files, and a Foxglove layout for it."""

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
    parser.add_argument("--grid", metavar="NAME",
                        help="a recording of several grids (a hierarchy's): this grid's series "
                        "and layout (default: every grid's series, the layout of the "
                        "recording's own grid, the upper level's)")
    return parser


def run(args: argparse.Namespace) -> int:
    """Read ``args.recording`` once and write what was asked for."""
    from adnmesh.results.csv_export import write_csv
    from adnmesh.results.foxglove_layout import foxglove_layout, layout_json
    from adnmesh.results.series import grid_of_topic, grids_of, read_grid, read_run

    if args.csv is None and args.foxglove_layout is None:
        raise UsageError("export: say what to write: --csv DIR and/or --foxglove-layout FILE")
    if args.csv is not None and args.csv.exists() and not args.csv.is_dir():
        raise UsageError(f"--csv {args.csv}: exists and is not a folder")
    if args.grid is not None:                # that grid's series only
        found, _, grids, grid = read_grid(args.recording, args.grid)
    else:                                    # every grid's; the layout of the recording's own
        found, _ = read_run(args.recording)
        grids = grids_of(found.recording.channels)
        own = found.recording.run.get("grid")
        grid = own if own in grids else next(iter(grids), None)
    note_if_truncated(found.recording)
    run_data = found.run
    if args.csv is not None:
        files = write_csv(run_data, args.csv)
        print(f"{args.csv}: {len(files) - 2} CSV files of {len(run_data.series)} series, "
              f"{files[0].name} (the list), {files[1].name} ({len(run_data.events)} events)")
    if args.foxglove_layout is not None:
        if grid is None:
            raise UsageError(f"{args.recording}: no adn/<grid>/... topics: not an adnmesh "
                             "recording")
        mine = [s for s in run_data.series.values() if grid_of_topic(s.topic) == grid]
        ders = sorted({s.der for s in mine if s.der is not None})
        layout = foxglove_layout(grid, ders,
                                 grid_model=any(s.role == "grid_v_min" for s in mine),
                                 events_topic=_events_topic(found.recording, grid),
                                 reactive=any(s.role == "q_ref" for s in mine))
        args.foxglove_layout.parent.mkdir(parents=True, exist_ok=True)
        args.foxglove_layout.write_text(layout_json(layout), encoding="utf-8")
        print(f"{args.foxglove_layout}: Foxglove layout for grid {grid} and {len(ders)} DERs")
    return 0


def _events_topic(recording, grid: str) -> str | None:
    """The log of the run's events of ``grid``: that grid's log if recorded, else the
    recording's own if it is of that grid or of none (a file another tool wrote), else None."""
    from adnmesh.results.series import grid_of_topic

    log = f"adn/{grid}/log"
    if log in recording.channels:
        return log
    own = recording.run.get("events_topic")
    return own if own and grid_of_topic(own) in (grid, None) else None
