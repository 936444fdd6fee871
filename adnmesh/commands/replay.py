"""``adnmesh replay RUN.mcap [--rrd OUT.rrd | --spawn | --web]``: a recording in Rerun."""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
from pathlib import Path

from adnmesh.commands import input_file, output_path
from adnmesh.errors import UsageError
from adnmesh.results.series import read_run

__all__ = ["add_parser", "run", "note_if_truncated"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``replay`` subparser."""
    parser = subparsers.add_parser(
        "replay",
        help="convert a recording to Rerun (.rrd file or a viewer)",
        description="Convert the MCAP recording RUN into Rerun data: scalars on a sim_time "
        "timeline at entity paths named after the bus keys, named series with their units "
        "(P_ref, P_IP, every DER's set-point and infeed in MW, P_Y, K_P in 1/MW, K_I in "
        "1/(MW s), availability, the grid with its band, Q_IP in Mvar), events as text logs, "
        "and a layout of the main plots. By default writes RUN with the suffix .rrd (no "
        "display needed); "
        "--spawn and --web write the same file and open it in a viewer bound to 127.0.0.1. "
        "Exit code 0 when written (with --web: the viewer's own when it ends; 130/143 after "
        "Ctrl-C/SIGTERM), 2 for a user error (no such file, not an MCAP file, a bad port).",
    )
    parser.add_argument("recording", metavar="RUN", help="recording (.mcap), e.g. logs/<run>.mcap")
    target = parser.add_mutually_exclusive_group()
    target.add_argument("--rrd", metavar="OUT", type=Path,
                        help="write the Rerun data to OUT (default: RUN with suffix .rrd)")
    target.add_argument("--spawn", action="store_true",
                        help="also open it in the native Rerun viewer")
    target.add_argument("--web", action="store_true",
                        help="also serve the Rerun web viewer at http://127.0.0.1:WEB_PORT "
                        "until Ctrl-C; prints the address that opens it on the data "
                        "(http://127.0.0.1:WEB_PORT/?url=...)")
    parser.add_argument("--web-port", type=int, default=9090,
                        help="HTTP port of the web viewer (default 9090)")
    return parser


def note_if_truncated(recording) -> None:
    """Tell the user (stderr) that a recording was cut short and read as far as it goes."""
    if not recording.complete:
        print(f"adnmesh: note: {recording.path} is truncated (killed run?): read the "
              f"{recording.recovered_messages} messages it holds; 'adnmesh inspect' writes a "
              f"recovered copy", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    """Convert ``args.recording``; write the .rrd and, if asked, start a viewer on it."""
    from adnmesh.results.rerun_export import export_rrd, viewer_command, web_viewer_url

    if not 0 < args.web_port < 65536:
        raise UsageError(f"--web-port must be a port number (1-65535), got {args.web_port}")
    out = output_path(args.rrd or Path(args.recording).with_suffix(".rrd"), "--rrd")
    found, _ = read_run(input_file(args.recording))
    recording, run_data = found.recording, found.run
    note_if_truncated(recording)
    series = len(run_data.series)
    export_rrd(recording, out, run=run_data, release=True)
    print(f"{out}: {series} series, {len(run_data.events)} events from "
          f"{recording.message_count} messages")
    if args.spawn:
        subprocess.Popen(viewer_command(out), start_new_session=True,  # noqa: S603
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        print(f"opened {out} in the Rerun viewer")
    elif args.web:
        from adnmesh.runtime.bus import free_port

        grpc_port = free_port()
        print(f"serving the Rerun web viewer: open {web_viewer_url(args.web_port, grpc_port)} "
              f"(Ctrl-C stops)", flush=True)
        return _serve(viewer_command(out, web=True, port=grpc_port, web_port=args.web_port))
    return 0


def _serve(command: list[str]) -> int:
    """Run the viewer ``command`` until it ends; stop it if we are interrupted or terminated."""

    def terminated(signum, frame):
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, terminated)
    viewer = subprocess.Popen(command)  # noqa: S603
    try:
        return viewer.wait()
    finally:
        signal.signal(signal.SIGTERM, previous)
        if viewer.poll() is None:
            viewer.terminate()
            viewer.wait(timeout=10)
