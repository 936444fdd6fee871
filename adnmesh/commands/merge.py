"""``adnmesh merge OUT.mcap RUN.mcap RUN.mcap ...``: one run's recordings as one recording."""

from __future__ import annotations

import argparse
from pathlib import Path

from adnmesh.commands import input_file, output_path

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``merge`` subparser."""
    parser = subparsers.add_parser(
        "merge",
        help="merge one run's recordings (its levels, its sites) into one",
        description="Write the messages of the recordings RUN (two or more, of one run: the "
        "levels of a hierarchy's run, the sites of a run) into OUT, in delivery-time order, "
        "a message recorded in several of them once, with the agents' published counts of "
        "all of them, so that 'adnmesh inspect OUT' checks that every message was recorded "
        "somewhere and 'adnmesh replay OUT' shows them together. A truncated RUN is read as "
        "far as it was written. Exit code 0 when written, 2 for a user error (no such file, "
        "not an MCAP file, recordings of different runs, OUT one of the RUNs).",
    )
    parser.add_argument("out", metavar="OUT", type=Path, help="the merged recording (.mcap)")
    parser.add_argument("recordings", metavar="RUN", nargs="+",
                        help="the recordings to merge (.mcap), two or more")
    return parser


def run(args: argparse.Namespace) -> int:
    """Merge ``args.recordings`` into ``args.out``."""
    from adnmesh.errors import UsageError
    from adnmesh.recording.merge import describe, merge_recordings

    if len(args.recordings) < 2:
        raise UsageError("merge: give two or more recordings to merge")
    inputs = [input_file(p) for p in args.recordings]
    out = output_path(args.out, "OUT")
    result = merge_recordings(inputs, out)
    print(describe(result, out))
    return 0
