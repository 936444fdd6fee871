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
import sys
import time
from pathlib import Path

from rich.console import Console

from adnmesh.commands import add_config_argument, comma_list, output_path
from adnmesh.config import Config, load_config
from adnmesh.errors import ConfigError, GridError, UsageError
from adnmesh.reactive import reactive_view
from adnmesh.tuning.table import (SchedulingTable, default_table_path, load_table, new_table,
                                   save_table)

__all__ = ["MAX_SPEED", "MIN_SPEED", "add_parser", "operating_point", "run",
           "scenario_subsets", "tuned_table_path"]

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


def scenario_subsets(config: Config) -> list[frozenset[str]]:
    """The sets of available DERs the scenario goes through, in order (all DERs first): those
    ``adnmesh tune --subsets scenario`` tunes."""
    from adnmesh.control.operating_point import available_power_w
    from adnmesh.tuning.subset_selection import scenario_subsets as in_config_order

    return [frozenset(s) for s in in_config_order(config, available_power_w(config))]


def _tuner():
    """``tune(config, der_ids)`` for the subsets a missing table lacks: on-demand tuning
    (:class:`adnmesh.tuning.ondemand.OnDemandTuner`, each entry a starting point for the next;
    a subset too large is a one-line error)."""
    from adnmesh.tuning.ondemand import OnDemandTuner   # numba: only when there is no table

    tuners: dict[str, OnDemandTuner] = {}

    def tune(config: Config, der_ids):
        if config.sha256 not in tuners:
            tuners[config.sha256] = OnDemandTuner(config)
        return tuners[config.sha256].tune(der_ids)
    return tune


def tuned_table_path(config: Config, subsets) -> Path:
    """Where ``up`` keeps the table it tunes for itself: ``<cache>/tables/<config stem>.<key>.json``
    (``<cache>``: :func:`adnmesh.grid.cache.default_cache_dir`), the key the first 16 hex of the
    SHA-256 of the config's design (:mod:`adnmesh.tuning.design_key`) and the scenario's
    ``subsets``: exactly what the tuning depends on, so a run that finds it uses the table it
    would have tuned."""
    from adnmesh.grid.cache import default_cache_dir
    from adnmesh.tuning.design_key import design_sha256

    order = {d: i for i, d in enumerate(config.der_ids())}
    listed = sorted(sorted(subset, key=order.__getitem__) for subset in subsets)
    key = hashlib.sha256(json.dumps([design_sha256(config), listed]).encode()).hexdigest()
    return default_cache_dir() / "tables" / f"{Path(config.path).stem}.{key[:16]}.json"


def _table(given: str | None, config: Config, run_dir: Path, run_id: str, log) -> Path:
    """The table file the CPFC will use: ``given`` (``--table``; for the Q loop, whose
    ``config`` is the reactive view, ``--q-table``), else the config's own
    (:func:`default_table_path`, next to the config), else the one an earlier run tuned for
    this design and scenario (:func:`tuned_table_path`), else the scenario's subsets tuned now
    and kept there (beside the recording if the cache cannot be written)."""
    q = config.quantity == "Q"
    what, option = ("Q gain table", " --quantity q") if q else ("gain table", "")
    path = Path(given) if given else default_table_path(config)
    subsets = scenario_subsets(config)
    if path.exists():
        table = load_table(path, config)  # a bad table: one line now, not in the CPFC later
        _check_gains(config, table, subsets, path)
        return path                     # subsets it lacks: the CPFC tunes them on demand
    if given:
        raise UsageError(f"no {what} {path}; run 'adnmesh tune {config.path}{option} --out "
                         f"{path}' first, or leave out --{'q-' if q else ''}table to have the "
                         "scenario's subsets tuned now")
    cached = tuned_table_path(config, subsets)
    if cached.exists():
        try:
            table = load_table(cached, config)
            _check_gains(config, table, subsets, cached)
        except (ConfigError, UsageError) as exc:
            log(f"not using the tuned {what} an earlier run kept: {exc}; tuning again")
        else:
            log(f"{what} {cached}: tuned by an earlier run for this design and scenario")
            return cached
    tune = _tuner()
    log(f"no {what} at {path}: tuning the {len(subsets)} subset(s) the scenario needs")
    table = new_table(config, config.constraints.model_dump(), "on-demand")
    ordered = [tuple(d for d in config.der_ids() if d in subset) for subset in subsets]
    for subset in ordered:
        entry = tune(config, list(subset))
        if not entry.feasible:      # the CPFC would have no gains for it: refused now
            names = ", ".join(subset) if len(subset) <= 6 else f"{len(subset)} DERs"
            raise ConfigError(f"{config.path}: constraints: no PI pair meets them for the "
                              f"scenario's DERs {names} ({entry.reason}); relax them or "
                              "change the DERs")
        table.add(entry)
    table.static = _static(config, ordered, log)
    try:
        cached.parent.mkdir(parents=True, exist_ok=True)
        save_table(table, cached)
        path = cached
    except OSError as exc:
        path = run_dir / f"{run_id}.table.json"
        log(f"cannot keep the tuned table in {cached.parent} ({exc.strerror or exc}); "
            "writing it beside the recording")
        save_table(table, path)
    log(f"tuned {what} written to {path}")
    return path


def _check_gains(config: Config, table: SchedulingTable, subsets, path: Path) -> None:
    """Refuse a table with gains the CPFC could use that are not certified stable, in one
    line, before anything starts (:mod:`adnmesh.tuning.table_check`)."""
    from adnmesh.tuning.table_check import unstable_gains

    bad = unstable_gains(config, table, subsets)
    if bad:
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        raise UsageError(f"{path}: gains not certified stable, refusing to run them: "
                         f"{bad[0].describe()}{more}; retune with 'adnmesh tune {config.path} "
                         f"--out {path}'")


def _static(config: Config, subsets, log):
    """The static controller (``subsets``: tuples of DER ids in config order) of the table ``up`` tunes for itself (None where it is not
    designed): what the CPFC uses at once when it meets a subset the table lacks, while that
    subset is tuned. Designed on the scenario's subsets and the extreme plants and verified on
    random subsets (:func:`adnmesh.tuning.build.static_entry`; ~5 s for SimBench). Configs with
    more dynamics classes than the on-demand tuner's exact limit are left without one here:
    for the 100-DER example (70 classes) the design takes ~80 s, which ``adnmesh tune
    --subsets scenario`` spends once (its table, given with ``--table``, has the pair)."""
    from adnmesh.tuning.build import static_entry
    from adnmesh.tuning.problem import MAX_EXACT_CLASSES
    from adnmesh.tuning.problem import TuningProblem

    problem = TuningProblem(config)
    if len(problem.actuators) > MAX_EXACT_CLASSES:
        log(f"no static controller: {len(problem.actuators)} dynamics classes (more than "
            f"{MAX_EXACT_CLASSES}); a subset the table lacks waits for its on-demand tuning "
            f"('adnmesh tune {config.path} --subsets scenario' makes a table with one)")
        return None
    t0 = time.perf_counter()
    entry = static_entry(problem, list(config.der_ids()), subsets)
    if not entry.feasible:
        log(f"no static controller: {entry.reason}")
        return None
    u = config.unit
    log(f"static controller: K_P {entry.kp:.4g} 1/{u}, K_I {entry.ki:.4g} 1/({u} s), verified on "
        f"{entry.figures.get('verified_random_subsets', 0)} random subsets "
        f"({time.perf_counter() - t0:.1f} s)")
    return entry


def operating_point(config: Config, log) -> dict[str, float]:
    """The DERs' available power (loading the grid model once, before any agent starts: the
    first time it builds its disk cache, which takes tens of seconds); checks every DER's
    model parameters and that the power flow at the schedules converges. ``adnmesh check``
    runs the same checks.

    Raises
    ------
    ConfigError
        An unknown SimBench code or study case, an sgen the net does not have, a ``p_inst_w``
        above the sgen's rating, a ``type`` that is not the sgen's, a schedule
        above what the DER can deliver, a bad model override, a power flow that does not
        converge; with reactive power control what :func:`adnmesh.reactive.reactive_view`
        refuses (a reactive schedule outside its range, reactive dynamics the numerics cannot
        hold, no DER with a reactive range); a tap changer the net does not have.
    """
    from adnmesh.control.der_model import check_der_models
    from adnmesh.control.operating_point import (available_power_w, initial_p_ip_w,
                                                 sgen_problem)

    if config.grid_model is not None:
        from adnmesh.control.operating_point import grid_label, grid_source
        from adnmesh.grid.cache import is_cached
        source, name, case = grid_source(config)
        building = "" if source != "simbench" or is_cached(
            name, case, config.grid_model.load_model) else \
            " (not cached yet: tens of seconds to build its cache)"
        log(f"grid model: {grid_label(config)}{building}")
    try:
        available = available_power_w(config)
    except GridError as exc:
        raise GridError(f"{config.path}: {exc}") from None
    problem = sgen_problem(config)
    if problem is not None:
        raise ConfigError(f"{config.path}: {problem}")
    check_der_models(config, available)
    if config.reactive is not None:
        reactive_view(config)
    from adnmesh.control.operating_point import tap_changer_words
    try:
        tap = tap_changer_words(config)
    except GridError as exc:
        raise ConfigError(f"{config.path}: {exc}") from None
    if tap is not None:
        log(tap)
    try:
        p_ip_w = initial_p_ip_w(config)
    except ValueError as exc:
        raise ConfigError(f"{config.path}: grid_model: {exc}") from None
    if config.grid_model is not None:
        log(f"grid model ready: P_IP {p_ip_w / 1e6:.4f} MW at the schedules")
    return available


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
    if args.seed is not None and not 0 <= args.seed < 2**63:
        raise UsageError(f"--seed must be in [0, 2**63), got {args.seed}")
    if args.startup_timeout is not None and not 0 < args.startup_timeout <= 86400:
        raise UsageError(f"--startup-timeout must be in (0, 86400] s, got "
                         f"{args.startup_timeout:g}")
    if not 0 <= args.stall_timeout <= 86400:
        raise UsageError(f"--stall-timeout must be in [0, 86400] s, got {args.stall_timeout:g}")
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


def _certs(args: argparse.Namespace) -> Path | None:
    """The certificate directory of the secure profile (checked), or None (open profile);
    the ``--listen`` endpoint must fit the profile."""
    from adnmesh.runtime.identity import cert_files
    from adnmesh.runtime.security import check_endpoints

    secure = bool(args.secure or args.certs)
    check_endpoints([args.listen] if args.listen else [], secure, flag="--listen")
    if not secure:
        return None
    certs = Path(args.certs or "certs")
    if not certs.is_dir():
        raise UsageError(f"{certs}: no certificate directory; create it with 'adnmesh certs "
                         f"{certs} --config {args.config}'")
    cert_files(certs, "up").check()
    return certs.resolve()


def run(args: argparse.Namespace) -> int:
    """Run the scenario; print the summary (also of a run that stopped early); return the
    exit code."""
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
    certs = _certs(args)
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
    table_path = _table(args.table, config, out.parent, run_id, log)
    q_table_path = None
    if config.reactive is not None:
        q_table_path = _table(args.q_table, reactive_view(config), out.parent, run_id, log)
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
    unwritten = _print_summary(args, config, run_id, result,
                               None if result.recording_failed else out)
    if unwritten:
        log(unwritten)
        return result.exit_code or 1
    return result.exit_code


def _robust_hint(args, config: Config, checks, out) -> str | None:
    """Where a step broke the overshoot its entry was certified for and the config has no
    uncertainty set: the commands that certify a table for plants like the ones just run
    (docs/tuning.md#robust-tables); else None."""
    if config.constraints.robust is not None or out is None:
        return None
    over = [c for c in checks if "overshoot" in c.over]
    if not over:
        return None
    robust = Path(args.config).with_name(Path(args.config).stem + "-robust.yaml")
    during = ("" if config.runtime.model_watch == "retune" else
              " With runtime.model_watch: retune the CPFC tunes such a subset again during the "
              "run (docs/method.md#model-watch).")
    return (f"{len(over)} step(s) broke the overshoot their entry was certified for: the DERs "
            f"do not behave as the reference model. A table certified for plants like these: "
            f"adnmesh identify {args.config} {out} --steps auto --robust-out {robust}; adnmesh "
            f"tune {robust} --robust; adnmesh up {robust} (docs/tuning.md#robust-tables).{during}")


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


def _print_summary(args: argparse.Namespace, config: Config, run_id: str, result,
                   recording: Path | None = None) -> str | None:
    """The summary on stdout (and as JSON with ``--summary-json``), with the way to a robust
    table where a step broke its certified overshoot (``recording``: the run's, if complete);
    return the line that says the JSON could not be written (a full disk, say), or None."""
    from adnmesh.results.realtime_report import realtime_figures
    from adnmesh.results.summary import format_summary, summarize

    byes = result.byes.values()
    extra = {
        "run_id": run_id,
        "clock": args.clock,
        "ended": result.reason,
        "agents": len(byes),
        "messages_recorded": sum(result.recorded.values()),
        "messages_received_by_agents": sum(int(b.stats.get("received", 0)) for b in byes),
        "rejected_by_agents": sum(sum(r.values()) for b in byes for r in b.rejected.values()),
        "rejected_by_recorder": sum(sum(r.values()) for r in result.rejected.values()),
        "lost_on_links": sum(b.lost for b in byes),
        "startup_s": round(result.startup_s, 3),
        "profile": "secure" if args.secure or args.certs else "open",
        "links_accepted": sum(result.sessions.opened.values()),
        "unexpected_sessions": len(result.sessions.unexpected),
    }
    if result.recording_failed:
        extra["recording_failed"] = result.recording_failed
        extra["messages_on_disk"] = result.on_disk[0]
    if args.clock == "sim":
        extra["clock_grants"] = result.grants
        extra["grants_per_s"] = round(result.grants / result.wall_time_s, 1) \
            if result.wall_time_s else None
    realtime = None
    if args.clock == "realtime":
        realtime = realtime_figures(byes, result.series.alarms, result.series.faults.values(),
                                    config, speed=args.speed or 1.0,
                                    tolerance_ns=result.tolerance_ns)
    summary = summarize(result.series, end_ns=result.reached_ns,
                        band_pct=config.constraints.settling_band_pct,
                        wall_time_s=result.wall_time_s, extra=extra, realtime=realtime,
                        planned_steps=[(s.t_s, s.delta_w) for s in config.scenario.p_ref_steps],
                        sample_s=config.runtime.pi_period_s)
    # piped into a file or another program: wide enough that no table cell is cut
    console = Console(highlight=False, markup=False, soft_wrap=True,
                      width=None if sys.stdout.isatty() else 200)
    for item in format_summary(summary):
        console.print(item)
    hint = _robust_hint(args, config, summary.design_checks, recording)
    if hint:
        console.print(hint)
    sys.stdout.flush()
    if args.summary_json:
        from adnmesh.files import write_atomic

        try:         # atomic: a full disk leaves no half file (and an earlier one as it was)
            write_atomic(args.summary_json, json.dumps(summary.to_json(), indent=1) + "\n")
        except OSError as exc:
            return (f"--summary-json {args.summary_json}: not written ({exc.strerror or exc}); "
                    "the summary above is the whole of it")
    return None
