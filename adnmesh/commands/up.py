"""``adnmesh up CONFIG``: run the scenario as a mesh of processes around an embedded Zenoh router.

Starts the CPFC, one DER agent per DER, the measurement and the availability monitor as separate
processes (:mod:`adnmesh.runtime.launcher`), records every message to ``logs/<run-id>.mcap`` and
prints a summary (:mod:`adnmesh.results.summary`). Progress lines and problems go to stderr, the
summary to stdout.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import time
from pathlib import Path

from rich.console import Console

from adnmesh.commands import (add_config_argument, certificate_directory, check_run_limits,
                              comma_list, output_path)
from adnmesh.config import Config, load_config
from adnmesh.errors import UsageError
from adnmesh.reactive import reactive_view
from adnmesh.commands.up_summary import print_and_write_summary
from adnmesh.commands.up_tables import operating_point, table_for

__all__ = ["MAX_SPEED", "MIN_SPEED", "add_parser", "run"]

MIN_SPEED, MAX_SPEED = 1e-3, 1e6
"""The range of ``--speed``, simulated s per wall s: slower than 1e-3 a second of sim time
takes 17 minutes, and sim-to-wall times overflow (``--speed 1e-300`` killed an agent)."""


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``up`` subparser."""
    parser = subparsers.add_parser(
        "up",
        help="run the scenario: CPFC, DER, measurement and availability agents as processes",
        description="Start every agent of CONFIG as its own process around an embedded Zenoh "
        "router (listening on 127.0.0.1), run the scenario on the chosen clock, record every "
        "message to MCAP and print a summary. Exit code 0 on success, 1 if the run failed "
        "(an agent died, the recording is incomplete), 2 for a user error, 3 if --strict "
        "stopped a realtime run that could not keep up, 130/143 after Ctrl-C/SIGTERM.",
    )
    add_config_argument(parser)
    parser.add_argument("--clock", choices=["sim", "realtime"], default="sim",
                        help="sim (default): deterministic simulated time, as fast as the agents "
                        "allow; realtime: the wall clock")
    parser.add_argument("--speed", type=float, metavar="X",
                        help="realtime only: X simulated seconds per wall second, 0.001 to "
                        "1e6 (default 1)")
    parser.add_argument("--strict", action="store_true",
                        help="realtime only: stop the run (exit code 3) as soon as an agent "
                        "falls behind the scaled wall clock by more than the tolerance "
                        "(runtime.realtime_tolerance_s); without it the run goes on and its "
                        "summary says it was not real time")
    parser.add_argument("--rt-priority", choices=["off", "nice", "fifo"],
                        help="realtime only: scheduling priority of up and its agents (default "
                        "off; nice: nice -10; fifo: SCHED_FIFO); refused by the OS (no root or "
                        "CAP_SYS_NICE), the run goes on at the ordinary priority and says so")
    parser.add_argument("--seed", type=int, metavar="N",
                        help="seed of the ICT random streams (default: runtime.seed of CONFIG)")
    parser.add_argument("--table", metavar="PATH",
                        help="gain-scheduling table (default: tables/<name>.<design "
                             "hash[:12]>.json next to the config, else the one an earlier up "
                             "kept in its cache)")
    parser.add_argument("--q-table", metavar="PATH",
                        help="reactive power control: the Q table (default: as --table, for "
                        "the config's reactive view: 'adnmesh tune CONFIG --quantity q')")
    parser.add_argument("--out", metavar="PATH",
                        help="MCAP recording to write (default: logs/<run-id>.mcap)")
    parser.add_argument("--summary-json", metavar="PATH",
                        help="also write the summary as JSON to PATH")
    parser.add_argument("--listen", metavar="ENDPOINT",
                        help="endpoint of the embedded router (default: tcp/127.0.0.1:<free "
                        "port>; tls/ with --secure)")
    security = parser.add_argument_group("secure profile and agents on other hosts")
    security.add_argument("--secure", action="store_true",
                          help="mutual TLS on every link and Zenoh access control derived from "
                          "the topology (certificates from --certs)")
    security.add_argument("--certs", metavar="DIR",
                          help="certificate directory of 'adnmesh certs' (default: certs; "
                          "implies --secure)")
    security.add_argument("--external", metavar="KIND[:ID],...",
                          help="agents started elsewhere ('adnmesh agent'), e.g. "
                          "der:SGen2,measurement; up waits for them")
    security.add_argument("--routers", metavar="NAME,...",
                          help="site routers ('adnmesh router --name NAME') that may link to "
                          "this one")
    security.add_argument("--print-zenoh-config", action="store_true",
                          help="print the router's Zenoh configuration (JSON: mode, endpoints, "
                          "TLS, access control) and exit")
    security.add_argument("--startup-timeout", type=float, default=None, metavar="S",
                          help="how long to wait for every agent to be ready (default 60 s "
                          "plus 1 s per DER: 103 agents took 85 s on a loaded 2-core machine)")
    view = parser.add_argument_group("live view")
    view.add_argument("--view", nargs="?", const="native", metavar="web|FILE.rrd",
                      help="stream the run's series, events and layout (those of 'adnmesh "
                      "replay') to Rerun while it goes: alone, the native viewer; 'web', the "
                      "web viewer (its URL is printed); FILE.rrd, a file (no viewer, headless). "
                      "Viewers bind 127.0.0.1 and stay open after the run. Put it after CONFIG")
    view.add_argument("--progress", action="store_true",
                      help="show the progress bar (sim time, speed factor) and the events as "
                      "they happen even when stderr is not a terminal")
    parser.add_argument("--stall-timeout", type=float, default=60.0, metavar="S",
                        help="sim clock: stop the run when it made no progress for S wall "
                        "seconds (default 60; 0: never)")
    return parser


def external_agents(text: str | None, config: Config) -> frozenset[str]:
    """The agent ids of ``--external`` (``cpfc``, ``der:SGen1`` or ``der/SGen1``, ...)."""
    from adnmesh.sim.topology import Topology

    agents = Topology.from_config(config).agents
    items = comma_list(text)
    if text is not None and not items:
        raise UsageError(f"--external {text!r}: names no agent (KIND[:ID],..., e.g. "
                         "der:SGen2,measurement)")
    found = set()
    for item in items:
        item = item.replace(":", "/", 1)
        if item not in agents:
            raise UsageError(f"--external: no agent {item!r} in {config.path} (agents: "
                             f"{', '.join(agents)})")
        found.add(item)
    return frozenset(found)


def _check_arguments(args: argparse.Namespace) -> None:
    if args.speed is not None and args.clock != "realtime":
        raise UsageError("--speed needs --clock realtime")
    if args.strict and args.clock != "realtime":
        raise UsageError("--strict needs --clock realtime")
    if args.rt_priority is not None and args.clock != "realtime":
        raise UsageError("--rt-priority needs --clock realtime")
    if args.speed is not None and not MIN_SPEED <= args.speed <= MAX_SPEED:
        raise UsageError(f"--speed must be in [{MIN_SPEED:g}, {MAX_SPEED:g}], got "
                         f"{args.speed:g}")
    check_run_limits(args)
    if args.view is not None:
        from adnmesh.runtime.liveview import parse_view

        view = parse_view(args.view)
        if view.path is not None:
            output_path(view.path, "--view")
    if args.routers and not (args.secure or args.certs):
        raise UsageError("--routers is for the secure profile (--secure); in the open profile "
                         "any router may link")


def _check_devices(args: argparse.Namespace, config: Config) -> None:
    """A DER behind a plant device runs on the wall clock: only ``--clock realtime`` at
    speed 1 can drive it."""
    device = next((d for d in config.ders if d.plant is not None), None)
    if device is None:
        return
    if args.clock != "realtime" or (args.speed or 1.0) != 1.0:
        raise UsageError(f"{config.path}: {device.id}'s plant is a {device.plant.protocol} "
                         "device, which runs on the wall clock: run with --clock realtime "
                         "(at --speed 1)")


def run(args: argparse.Namespace) -> int:
    """Run the scenario; print the summary (also of a run that stopped early); return the
    exit code. A hierarchy file runs its levels (:mod:`adnmesh.commands.up_levels`)."""
    from adnmesh.config import is_hierarchy_file

    if is_hierarchy_file(args.config):
        from adnmesh.commands.up_levels import run_hierarchy
        return run_hierarchy(args)
    config = load_config(args.config)
    _check_arguments(args)
    _check_devices(args, config)
    from adnmesh.commands.fault import run_file_path
    from adnmesh.runtime.bus import check_listen
    from adnmesh.runtime.launcher import UpOptions
    from adnmesh.runtime.launcher import run as launch

    err = Console(stderr=True, highlight=False, markup=False, soft_wrap=True)

    def log(line: str) -> None:
        err.print(f"adnmesh up: {line}")

    if (args.secure or args.certs) and config.runtime.ders_per_process > 1:
        raise UsageError(f"runtime.ders_per_process {config.runtime.ders_per_process} is for "
                         "the open profile: in the secure profile every DER process has its "
                         "own certificate (set it to 1, or run without --secure/--certs)")
    certs = certificate_directory(args)
    external = external_agents(args.external, config)
    routers = tuple(comma_list(args.routers))
    if args.print_zenoh_config:
        return _print_zenoh_config(args, config, certs, routers)
    if args.listen is not None:
        check_listen(args.listen)
    run_id = f"{Path(config.path).stem}-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    out = output_path(Path(args.out) if args.out else Path("logs") / f"{run_id}.mcap", "--out")
    if args.summary_json:
        output_path(args.summary_json, "--summary-json")
    available = operating_point(config, log)
    table_path = table_for(args.table, config, out.parent, run_id, log)
    q_table_path = None
    if config.reactive is not None:
        q_table_path = table_for(args.q_table, reactive_view(config), out.parent, run_id, log)
    options = UpOptions(
        config=config, table_path=table_path, q_table_path=q_table_path, out=out,
        clock=args.clock,
        speed=args.speed or 1.0,
        seed=config.runtime.seed if args.seed is None else args.seed,
        listen=args.listen, log=log, run_id=run_id, run_file=run_file_path(out),
        certs=certs, external=external, routers=routers,
        startup_timeout_s=(60.0 + len(config.ders) if args.startup_timeout is None
                           else args.startup_timeout), stall_timeout_s=args.stall_timeout,
        available_w=available, strict=args.strict, rt_priority=args.rt_priority or "off",
        metadata={"run_id": run_id, "table_sha256":
                  hashlib.sha256(table_path.read_bytes()).hexdigest(),
                  **({} if q_table_path is None else {"q_table_sha256": hashlib.sha256(
                      q_table_path.read_bytes()).hexdigest()})},
    )
    result = _launch_with_view(args, options, launch, err, log)
    for problem in result.problems:
        log(problem)
    if result.recording_failed:
        messages, last_ns = result.on_disk
        log(f"recording: {out} INCOMPLETE: it keeps the {messages} messages to "
            f"{last_ns / 1e9:g} s of sim time written before it failed ('adnmesh inspect "
            f"{out} --recover-to FILE' completes them into FILE)")
    else:
        log(f"recording: {out} ({sum(result.recorded.values())} messages)")
    unwritten = print_and_write_summary(args, config, run_id, result,
                               None if result.recording_failed else out)
    if unwritten:
        log(unwritten)
        return result.exit_code or 1
    return result.exit_code


def _launch_with_view(args, options, launch, err: Console, log):
    """Run ``launch(options)`` with the live view and the progress bar asked for."""
    from adnmesh.runtime.liveview import open_view, parse_view
    from adnmesh.runtime.progress import RunProgress
    from adnmesh.wire.units import ns

    target = parse_view(args.view)
    bar = RunProgress(err, ns(options.config.scenario.duration_s)) \
        if args.progress or err.is_terminal else None
    on_events = bar.events if bar is not None else None
    view = None
    if target is not None or bar is not None:     # without a target: the bar's events only
        grid = options.config.grid_model
        view = open_view(target, options.run_id, log, on_events=on_events,
                         limits=grid.limits if grid is not None else None)
    options.view = view
    options.progress = bar.update if bar is not None else None
    try:
        with bar if bar is not None else contextlib.nullcontext():
            return launch(options)
    finally:
        if view is not None:
            view.close()
            if view.error:
                log(view.error)


def _print_zenoh_config(args: argparse.Namespace, config: Config, certs, routers) -> int:
    """Print the parts of the router's Zenoh config that adnmesh sets; return 0."""
    from adnmesh.runtime.bus import DEFAULT_HOST
    from adnmesh.runtime.launcher import UpOptions, embedded_router_config

    scheme = "tcp" if certs is None else "tls"
    endpoint = args.listen or f"{scheme}/{DEFAULT_HOST}:7447"
    options = UpOptions(config=config, table_path=Path(), out=Path(), certs=certs,
                        routers=routers)
    full = json.loads(str(embedded_router_config(options, endpoint)))
    link = full["transport"]["link"]
    shown = {"mode": full["mode"], "listen": {"endpoints": full["listen"]["endpoints"]},
             "scouting": {"multicast": {"enabled": full["scouting"]["multicast"]["enabled"]}},
             "transport": {"link": {"protocols": link["protocols"], "tls": {
                 k: v for k, v in link["tls"].items() if v is not None}}},
             "access_control": full["access_control"]}
    print(json.dumps(shown, indent=2))
    return 0


