"""``adnmesh plot RUN.mcap [-o FIG.png]``: the paper-style time plot of a recorded run."""

from __future__ import annotations

import argparse
from pathlib import Path

from adnmesh.commands import input_file, output_path
from adnmesh.commands.replay import note_if_truncated
from adnmesh.errors import UsageError
from adnmesh.results.series import read_grid

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``plot`` subparser."""
    parser = subparsers.add_parser(
        "plot",
        help="draw P_IP, P_ref, the DERs, P_Y, the gains and the grid of a recording",
        description="Draw the time plot of the recording RUN: P_IP and P_ref in MW, with "
        "changes of the available DERs and faults shaded; below, every DER's infeed and "
        "set-point (MW), P_Y, the active gains K_P (1/MW) and K_I (1/(MW s)) and, with a grid "
        "model, the bus voltage extremes and the loadings with the configured band, and Q_IP "
        "(Mvar). The format follows the suffix of FIG (png, pdf, svg, ...). Exit code 0 when "
        "written, 2 for a user error (no such file, not an MCAP file, an unknown format).",
    )
    parser.add_argument("recording", metavar="RUN", help="recording (.mcap), e.g. logs/<run>.mcap")
    parser.add_argument("-o", "--out", metavar="FIG", type=Path,
                        help="figure to write (default: RUN with suffix .png)")
    parser.add_argument("--grid", metavar="NAME",
                        help="a recording of several grids (a hierarchy's): this grid's plot "
                        "(default: the recording's own grid, the upper level's)")
    return parser


def run(args: argparse.Namespace) -> int:
    """Draw ``args.recording`` into ``args.out``."""
    from matplotlib.figure import Figure

    from adnmesh.results.series import recorded_grid_limits
    from adnmesh.results.time_plot import save_plot

    out = args.out or Path(args.recording).with_suffix(".png")
    formats = Figure().canvas.get_supported_filetypes()
    if out.suffix.lstrip(".").lower() not in formats:
        raise UsageError(f"{out}: unknown figure format {out.suffix or '(no suffix)'!r} "
                         f"(known: {', '.join(sorted(formats))})")
    output_path(out, "-o")
    found, _, grids, grid = read_grid(input_file(args.recording), args.grid)
    recording = found.recording
    note_if_truncated(recording)
    title = recording.run.get("run_id") or Path(args.recording).stem
    if len(grids) > 1:
        title = f"{title}, grid {grid} of {len(grids)}"
    clock = recording.run.get("clock")
    save_plot(found.run, out, title=f"{title} ({clock} clock)" if clock else title,
              limits=recorded_grid_limits(recording.run))
    print(f"{out}: written")
    return 0
