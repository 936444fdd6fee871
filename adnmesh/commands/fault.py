"""``adnmesh fault RUN KIND [TARGET]``: inject a fault into a running ``adnmesh up``.

The command connects to the run's router as a Zenoh client (127.0.0.1 unless told otherwise),
publishes a ``fault_request`` on ``adn/<grid>/control/fault`` and waits for ``up``'s answer, an
event on ``adn/<grid>/event/up`` that names the request: the fault injected (with the instant it
takes effect) or refused (why). RUN is the run's id (``logs/<run-id>.run.json``, which ``up``
writes while it runs), the path of that file or of the run's recording, or the router's
endpoint (``tcp/127.0.0.1:PORT``; the grid is then found from ``up``'s liveliness token).
Against a run of the secure profile it connects with the ``operator`` certificate (``--certs``,
by default the run's certificate directory named in its ``.run.json``): the only identity the
run's access control lets publish a fault request.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import zenoh

from adnmesh.errors import UsageError
from adnmesh.runtime.bus import client_config
from adnmesh.runtime.injector import new_request_id
from adnmesh.wire.envelope import MessageError, decode, encode
from adnmesh.names import FAULT_KINDS, ICT_LINKS, LAUNCHER, OPERATOR
from adnmesh.wire.keys import Keys
from adnmesh.wire.outbox import Outbox
from adnmesh.wire.units import ns

__all__ = ["EXIT_NO_ANSWER", "add_parser", "run", "run_file_path"]

EXIT_NO_ANSWER = 1
"""Exit code when the run did not answer within ``--timeout``."""

_TARGET = {"link_outage": "link", "link_loss": "link", "link_delay": "link",
           "der_offline": "der", "kill": "agent", "ict_outage": None}


def run_file_path(recording: Path) -> Path:
    """Where ``up`` describes a running run: beside its recording, suffix ``.run.json``."""
    return recording.with_suffix(".run.json")


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``fault`` subparser."""
    parser = subparsers.add_parser(
        "fault", help="inject a fault into a running `adnmesh up`",
        description="Inject a fault into a running `adnmesh up`: in sim time at --at (or, if "
        "the run has passed it, at the earliest instant it can still change), in real time at "
        "once. KIND and TARGET: link_outage|link_loss|link_delay LINK (" + ", ".join(ICT_LINKS)
        + "); der_offline DER; ict_outage; kill AGENT (cpfc, measurement, availability, "
        "der/<id>). Exit code 0 when the fault was injected (its line on stdout), 2 when "
        "refused (why, on stderr; a start after the end of the scenario is refused), 1 "
        "without answer.")
    parser.add_argument("run_ref", metavar="RUN",
                        help="run id, its .run.json or .mcap, or the router's endpoint")
    parser.add_argument("kind", choices=FAULT_KINDS, metavar="KIND")
    parser.add_argument("target", nargs="?", metavar="TARGET",
                        help="the link, DER or agent the fault concerns")
    parser.add_argument("--at", type=float, metavar="T", help="start, s of sim time "
                        "(default: as soon as possible)")
    parser.add_argument("--for", dest="duration", type=float, metavar="D",
                        help="length, s (a kill: restart after D; default: to the end)")
    parser.add_argument("--probability", type=float, metavar="P", help="link_loss: in [0, 1]")
    parser.add_argument("--delay", type=float, metavar="S", help="link_delay: extra delay, s")
    parser.add_argument("--timeout", type=float, default=10.0, metavar="S",
                        help="how long to wait for the run's answer (default 10 s)")
    parser.add_argument("--certs", metavar="DIR",
                        help="secure profile: the directory with the operator's certificate "
                        "(default: the run's, from its .run.json)")
    return parser


def _request(args: argparse.Namespace) -> dict:
    needed = _TARGET[args.kind]
    if needed is not None and not args.target:
        raise UsageError(f"{args.kind} needs a {needed}")
    if needed is None and args.target:
        raise UsageError(f"{args.kind} takes no target, got {args.target!r}")
    for name in ("at", "duration", "delay"):
        value = getattr(args, name)
        if value is not None and not 0 <= value <= 1e6:
            raise UsageError(f"--{'for' if name == 'duration' else name} must be in [0, 1e6] s, "
                             f"got {value:g}")
    if not 0 < args.timeout <= 3600:
        raise UsageError(f"--timeout must be in (0, 3600] s, got {args.timeout:g}")
    if args.probability is not None and not 0 <= args.probability <= 1:
        raise UsageError(f"--probability must be in [0, 1], got {args.probability:g}")
    body = {"kind": args.kind, "at_ns": None if args.at is None else ns(args.at),
            "for_ns": None if args.duration is None else ns(args.duration),
            "request_id": new_request_id()}
    if needed is not None:
        body[needed] = args.target
    if args.probability is not None:
        body["probability"] = args.probability
    if args.delay is not None:
        body["delay_ns"] = ns(args.delay)
    return body


def _locate(ref: str) -> tuple[str, str | None, str | None]:
    """``(endpoint, grid or None, certificate directory or None)`` of the run ``ref``."""
    if ref.startswith(("tcp/", "tls/")):
        return ref, None, None
    path = Path(ref)
    candidates = [path] if path.suffix == ".json" else \
        [run_file_path(path)] if path.suffix == ".mcap" else [Path("logs") / f"{ref}.run.json"]
    for candidate in candidates:
        try:
            info = json.loads(candidate.read_text())
            certs = info.get("certs")
            return (str(info["endpoint"]), str(info["grid"]),
                    None if certs is None else str(certs))
        except FileNotFoundError:
            raise UsageError(f"no running run {ref!r} ({candidate} does not exist; give the "
                             "run id, its .run.json or .mcap, or the router's endpoint)") from None
        except (OSError, ValueError, KeyError, TypeError):
            raise UsageError(f"{candidate}: not a run description of adnmesh up") from None
    raise UsageError(f"no running run {ref!r}")


def _grid_of(session: zenoh.Session, timeout_s: float) -> str:
    """The grid of the run behind ``session``'s router, from ``up``'s liveliness token (one
    per level of a hierarchy's run: then the run is to be named by its id, whose run file
    names its upper level)."""
    grids = sorted({str(reply.ok.key_expr).split("/")[1]
                    for reply in session.liveliness().get("adn/*/alive/up", timeout=timeout_s)
                    if reply.ok is not None})
    if not grids:
        raise UsageError("no adnmesh up answers at that endpoint")
    if len(grids) > 1:
        raise UsageError(f"the run at that endpoint has {len(grids)} grids ({', '.join(grids)}:"
                         " a hierarchy); name it by its run id, for its upper level")
    return grids[0]


def run(args: argparse.Namespace) -> int:
    """Send the request; print the run's answer; return the exit code."""
    body = _request(args)
    endpoint, grid, certs = _locate(args.run_ref)
    answer: list = []
    got = threading.Event()
    try:
        session = zenoh.open(client_config([endpoint], args.certs or certs, OPERATOR))
    except zenoh.ZError:
        print(f"adnmesh fault: error: cannot connect to the run at {endpoint}", file=sys.stderr)
        return EXIT_NO_ANSWER
    with session:
        keys = Keys(grid or _grid_of(session, args.timeout))

        def on_event(sample: zenoh.Sample) -> None:
            try:
                event = decode(str(sample.key_expr), sample.payload.to_bytes())
            except MessageError:
                return
            if getattr(event, "request_id", None) == body["request_id"]:
                answer.append(event)
                got.set()

        subscriber = session.declare_subscriber(keys.of("event", LAUNCHER), on_event)
        # seq: the wall clock, so that every request is newer than the last (the run rejects
        # a repeated (send time, seq) as a replay); the times are 0, the run's own start
        # seq: the wall clock, so that every request (each from a new process) comes after
        # the last one up accepted on the key
        key = keys.of("fault_request")
        session.put(key, encode(Outbox(OPERATOR).message(key, time.time_ns(), 0, 0, body)))
        got.wait(args.timeout)
        subscriber.undeclare()
    if not answer:
        print(f"adnmesh fault: error: no answer from the run at {endpoint} within "
              f"{args.timeout:g} s", file=sys.stderr)
        return EXIT_NO_ANSWER
    event = answer[0]
    injected = event.kind == "fault_injected"       # else refused: an error, on stderr
    print(f"adnmesh fault: {event.text}", file=sys.stdout if injected else sys.stderr)
    return 0 if injected else 2
