"""``adnmesh up HIERARCHY``: a hierarchy of ADNs as processes around one router, on one sim
clock (docs/hierarchy.md#adnmesh-up).

What ``adnmesh cascade HIERARCHY --run`` runs in one process, this runs as ``up`` runs one
grid: every agent of every level its own process, a Zenoh client of the embedded router.

1. Each ADN's table: its own (``tables/`` next to its config), else the one an earlier ``up``
   tuned for its design and scenario, else its scenario's subsets tuned now and kept (as ``up``
   does for one grid). The upper level -- its config, its HV net and its table, tuned on the
   ADNs' equivalent models and certified on the exact cascade -- goes where ``adnmesh cascade``
   writes it (``<name>-upper/`` next to the hierarchy file); an upper table an earlier ``up``
   certified there on the very same ADN loops is used again.
2. The levels file (``<out stem>.levels.json`` beside ``--out``,
   :mod:`adnmesh.sim.hierarchy_levels`) tells every agent process the whole hierarchy: its
   topology, the site agents, the upper CPFC's rule for the ADNs' gain switches.
3. One launch per level (:func:`adnmesh.runtime.launcher.run_levels`): its own recording
   (``<out stem>.<level>.mcap`` beside ``--out``), roster, faults (the hierarchy file's for the
   upper level, each ADN's own), counts verified per level; one clock for all
   (:mod:`adnmesh.runtime.level_clock`).
4. The levels' recordings merged into ``--out`` (:mod:`adnmesh.recording.merge`: ``inspect``,
   ``plot``, ``export`` and ``replay`` take it, ``--grid`` for a level), each site's own
   (``<out stem>.<adn>.site.mcap``, what its agents published, recorded by its router:
   :mod:`adnmesh.runtime.site_recorder`) beside it, and a summary per level
   (``--summary-json``: ``{"run_id", "levels": {grid: summary}}``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import msgspec

from adnmesh.commands import output_path
from adnmesh.errors import ConfigError, UsageError

__all__ = ["run_hierarchy"]

_ONE_GRID_ONLY = (("clock", "realtime", "--clock realtime"), ("speed", None, "--speed"),
                  ("strict", True, "--strict"), ("rt_priority", None, "--rt-priority"),
                  ("external", None, "--external"), ("routers", None, "--routers"),
                  ("view", None, "--view"), ("table", None, "--table"),
                  ("q_table", None, "--q-table"),
                  ("print_zenoh_config", True, "--print-zenoh-config"))
"""``up`` options a hierarchy's run does not take (yet): (attribute, the value that uses it,
or None for any value given, flag)."""


def _check_options(args: argparse.Namespace) -> None:
    for name, value, flag in _ONE_GRID_ONLY:
        given = getattr(args, name, None)
        if given and (value is None or given == value):
            raise UsageError(f"{flag} is not for a hierarchy file (adnmesh up runs a hierarchy "
                             "on the sim clock, every site a router of its own; each level's "
                             "table is found or tuned as for one grid)")
    from adnmesh.commands import check_run_limits
    check_run_limits(args)
    if args.listen is not None:
        from adnmesh.runtime.bus import check_listen
        check_listen(args.listen)


def _secure(args: argparse.Namespace, hierarchy) -> Path | None:
    """The certificate directory of the secure profile, every identity of the hierarchy's
    run in it (:func:`~adnmesh.runtime.identity.hierarchy_identities`), or None (open)."""
    from adnmesh.commands import certificate_directory
    from adnmesh.config import load_config
    from adnmesh.runtime.identity import cert_files, hierarchy_identities

    certs = certificate_directory(args)
    if certs is None:
        return None
    for adn in hierarchy.adns:
        config = load_config(hierarchy.config_path(adn))
        if config.runtime.ders_per_process > 1:
            raise UsageError(f"{config.path}: runtime.ders_per_process "
                             f"{config.runtime.ders_per_process} is for the open profile: "
                             "in the secure profile every DER process has its own certificate")
    for identity in hierarchy_identities(hierarchy):     # each checked: one line if not one
        try:
            cert_files(certs, identity).check()
        except UsageError:
            raise UsageError(f"{certs}: no certificate of {identity}; create them with "
                             f"'adnmesh certs {certs} --config {hierarchy.path}'") from None
    return certs


@dataclass(frozen=True)
class Prepared:
    """Every level ready to run (see the module docstring, 1 and 2)."""

    levels: tuple
    """``(upper level, ADN id -> its level, ADN id -> offset link delay s)``
    (:func:`adnmesh.study.hierarchy.hierarchy_levels`)."""
    file: Path
    """The levels file."""
    upper_table: Path
    tables: dict
    """ADN id -> its table file."""
    available: dict
    """ADN id -> its DERs' available power, W."""


def _say():
    from rich.console import Console
    err = Console(stderr=True, highlight=False, markup=False, soft_wrap=True)
    return err, lambda line: err.print(f"adnmesh up: {line}")


def _prepare(hierarchy, work: Path, out: Path, run_id: str, log) -> Prepared:
    """Every level ready to run (see the module docstring, 1 and 2)."""
    from adnmesh.commands.cascade import upper_level
    from adnmesh.commands.up_tables import operating_point, table_for
    from adnmesh.config import load_config
    from adnmesh.study.hierarchy import hierarchy_levels, levels_file
    from adnmesh.sim.hierarchy_levels import on_bus, save_levels

    tables, available = {}, {}
    for adn in hierarchy.adns:
        try:
            config = load_config(hierarchy.config_path(adn))
            available[adn.id] = operating_point(on_bus(config, adn.id, adn.keep_steps), log)
            tables[adn.id] = table_for(None, config, work, f"{run_id}.{adn.id}", log)
        except ConfigError as exc:
            raise ConfigError(f"{hierarchy.path}: adns {adn.id}: {exc}") from None
    sites, upper = upper_level(hierarchy, work, log, tables)
    table, path = _upper_table(hierarchy, sites, upper, log)
    levels = hierarchy_levels(hierarchy, upper, table, sites, tables)
    file = save_levels(out.with_name(f"{out.stem}.levels.json"),
                       levels_file(hierarchy, levels, path, tables))
    return Prepared(levels, file, path, tables, available)


def _upper_table(hierarchy, sites, upper, log):
    """``(table, its file)``: the upper table an earlier run certified on these very ADN
    loops (the SHA-256 of what the certificate depends on, beside the table), else tuned and
    certified now."""
    from adnmesh.commands.cascade import certified_upper_table
    from adnmesh.sim.hierarchy_levels import LoopFields
    from adnmesh.tuning.table import default_table_path, load_table

    on = [[msgspec.to_builtins(LoopFields.of(s.adn)), s.t_com_s, s.grid_gain] for s in sites]
    key = hashlib.sha256(json.dumps([on, hierarchy.t_meas_s,
                                     hierarchy.constraints.model_dump()]).encode()).hexdigest()
    path = default_table_path(upper)
    stamp = path.with_suffix(".cascade.sha256")
    if path.exists() and stamp.exists() and stamp.read_text().strip() == key:
        try:
            table = load_table(path, upper)
        except ConfigError as exc:
            log(f"not using the upper table of an earlier run: {exc}; certifying again")
        else:
            log(f"upper table {path}: certified on these ADNs' loops by an earlier run")
            return table, path
    table, _, path = certified_upper_table(hierarchy, sites, upper, log)
    stamp.write_text(key + "\n")
    log(f"upper table certified on the exact cascade: {path}")
    return table, path


def _level_options(hierarchy, prepared, out: Path, args, run_id: str, log,
                   certs: Path | None):
    """The :class:`~adnmesh.runtime.launcher.UpOptions` of every level, the upper first, and
    the site routers (secure profile with ``certs``: mutual TLS on every link, the access
    control of every level on every router, each router's certificate its own)."""
    from adnmesh.commands.fault import run_file_path
    from adnmesh.runtime import acl
    from adnmesh.runtime.launcher import UpOptions
    from adnmesh.runtime.level_clock import SharedClock
    from adnmesh.sim.hierarchy_levels import load_levels
    from adnmesh.sim.hierarchy_topology import HIERARCHY
    from adnmesh.wire.units import ns

    file, tables = prepared.file, prepared.tables
    upper, adns, _ = prepared.levels
    wake = threading.Event()
    levels = load_levels(file)
    topology = levels.topology
    clock = SharedClock(topology, ns(upper.config.scenario.duration_s), wake)
    ders = sum(len(level.config.ders) for level in (upper, *adns.values()))
    sites = _sites(hierarchy, prepared.levels, certs, file)
    for site in sites:
        site.record_to, site.run_id = out, run_id
    routers = [f"router/{site.name}" for site in sites]
    behind = {f"router/{s.name}": levels.site_members(s.name) for s in sites}
    at_up = [a for a in topology.agents if not any(a in b for b in behind.values())]
    access = acl.access_control(topology, routers, clients=at_up, carries=behind)
    common = dict(clock="sim", listen=args.listen, log=log, run_id=run_id, wake=wake,
                  shared_clock=clock, features=HIERARCHY, stall_timeout_s=args.stall_timeout,
                  startup_timeout_s=(60.0 + ders if args.startup_timeout is None
                                     else args.startup_timeout), certs=certs,
                  access_control=None if certs is None else access)
    endpoints = {a: s.endpoint for s in sites for a in s.members[upper.config.grid]}
    options = []
    for grid, level in ((upper.config.grid, upper), *adns.items()):
        config = level.config
        if level is not upper:
            endpoints = {a: site.endpoint for site in sites if site.name == grid
                         for a in site.members[grid]}
        table = prepared.upper_table if level is upper else Path(tables[grid])
        options.append(UpOptions(
            config=config, table_path=table, out=out.with_name(f"{out.stem}.{grid}.mcap"),
            seed=config.runtime.seed if args.seed is None else args.seed,
            available_w={} if level is upper else prepared.available[grid],
            agent_args=("--levels", str(file), "--level", grid),
            run_file=run_file_path(out) if level is upper else None, endpoints=endpoints,
            watch_sessions=level is upper, identities=(*at_up, *routers),
            metadata={"run_id": run_id, "grid": grid, "hierarchy": str(hierarchy.path),
                      "table_sha256": hashlib.sha256(table.read_bytes()).hexdigest()},
            **common))
    return options, sites


def _sites(hierarchy, levels, certs: Path | None, file: Path):
    """Each ADN's :class:`~adnmesh.runtime.site_router.SiteRouter`: its agents and the upper
    level's site agent of it behind it, its planned restarts (secure profile: ``certs``, the
    levels ``file`` for its access control)."""
    from adnmesh.names import der_agent_id
    from adnmesh.runtime.bus import DEFAULT_HOST, free_port
    from adnmesh.runtime.site_router import PlannedRestart, SiteRouter
    from adnmesh.sim.hierarchy_topology import HIERARCHY
    from adnmesh.sim.topology import Topology
    from adnmesh.wire.units import ns

    upper, adns, _ = levels
    sites = []
    for adn in hierarchy.adns:
        agents = Topology.from_config(adns[adn.id].config, HIERARCHY).agents
        restarts = [PlannedRestart(ns(r.t_s), r.down_s) for r in hierarchy.site_restarts
                    if r.adn == adn.id]
        scheme = "tcp" if certs is None else "tls"
        sites.append(SiteRouter(adn.id, hierarchy.config_path(adn),
                                f"{scheme}/{DEFAULT_HOST}:{free_port()}",
                                {adn.id: tuple(agents),
                                 upper.config.grid: (der_agent_id(adn.id),)}, restarts,
                                certs, file))
    return sites


def run_hierarchy(args: argparse.Namespace) -> int:
    """``adnmesh up HIERARCHY`` (see the module docstring); return the exit code."""
    from adnmesh.commands.cascade import numerics_said
    from adnmesh.config import load_hierarchy

    hierarchy = load_hierarchy(args.config)
    _check_options(args)
    certs = _secure(args, hierarchy)
    err, log = _say()
    run_id = f"{hierarchy.name}-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    out = output_path(Path(args.out) if args.out else Path("logs") / f"{run_id}.mcap", "--out")
    if args.summary_json:
        output_path(args.summary_json, "--summary-json")
    work = hierarchy.path.parent / f"{hierarchy.name}-upper"
    output_path(work, "the upper level's directory", directory=True)
    log(f"{hierarchy.name}: {len(hierarchy.adns)} ADNs under one upper level"
        + ("" if certs is None else " (secure: mutual TLS, access control, a certificate per "
           "agent and site router)"))
    with numerics_said(hierarchy):
        prepared = _prepare(hierarchy, work, out, run_id, log)
    options, sites = _level_options(hierarchy, prepared, out, args, run_id, log, certs)
    log(f"sites: {', '.join(f'{s.name} on {s.endpoint}' for s in sites)}, linked to up's "
        "router")
    results = _launch(options, sites, err, args.progress)
    return _report(args, options, results, sites, out, run_id, log)


def _launch(options, sites, err, progress: bool):
    """Run the levels, with the progress bar on a terminal (or ``--progress``)."""
    import contextlib

    from adnmesh.runtime.launcher import run_levels
    from adnmesh.runtime.progress import RunProgress
    from adnmesh.wire.units import ns

    bar = RunProgress(err, ns(options[0].config.scenario.duration_s)) \
        if progress or err.is_terminal else None
    if bar is not None:
        options[0] = replace(options[0], progress=bar.update)
    with bar if bar is not None else contextlib.nullcontext():
        return run_levels(options, sites)


def _report(args, options, results, sites, out: Path, run_id: str, log) -> int:
    """Problems, the merged recording (every level's, and what each site recorded) and each
    level's summary; return the exit code."""
    from adnmesh.commands.up_summary import print_summary, run_summary, write_summary_json
    from adnmesh.recording.merge import describe, merge_recordings

    exit_code = next((r.exit_code for r in results if r.exit_code), 0)
    for o, result in zip(options, results):
        for problem in result.problems:
            log(f"{o.config.grid}: {problem}")
    written = [o.out for o, r in zip(options, results) if not r.recording_failed]
    recorded = [path for site in sites for path in site.recordings if path.exists()]
    if recorded:
        log(f"the sites' own recordings: {', '.join(p.name for p in recorded)} (what each "
            "site's agents published; 'adnmesh merge' takes them with the levels')")
    if len(written) == len(options):
        try:
            log(describe(merge_recordings(written, out), out))
        except (ConfigError, UsageError, OSError, ValueError) as exc:
            log(f"the levels' recordings are not merged: {exc}")
            exit_code = exit_code or 1
    summaries = {}
    for o, result in zip(options, results):
        print(f"\n== {o.config.grid} ==")
        summary = run_summary(args, o.config, run_id, result)
        print_summary(args, o.config, summary)      # (a robust table: per ADN config)
        summaries[o.config.grid] = summary.to_json()
    sys.stdout.flush()
    unwritten = write_summary_json(args.summary_json, {"run_id": run_id, "levels": summaries})
    if unwritten:
        log(unwritten)
        return exit_code or 1
    return exit_code
