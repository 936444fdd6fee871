"""``adnmesh cascade HIERARCHY``: the upper table of an ADN hierarchy, certified as a cascade."""
from __future__ import annotations

import argparse
import contextlib
import csv
import sys
import time
from pathlib import Path

import yaml

from adnmesh.commands import output_path
from adnmesh.errors import ConfigError, GridError

__all__ = ["add_parser", "run", "hierarchy_sites", "upper_level", "SWEEP_ALL_UP_TO"]

#: ADNs of at most this many DERs have every subset swept by --switches
SWEEP_ALL_UP_TO = 11


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``cascade`` subparser."""
    parser = subparsers.add_parser(
        "cascade",
        help="tune and certify an upper controller over MV ADNs (docs/hierarchy.md)",
        description="Read a hierarchy file (an upper controller over MV ADNs, each with its own "
        "config), take each ADN's entry for all its DERs (from its table, or tuned now), fit "
        "the equivalent model of its closed loop, tune the upper table on those models and "
        "certify every entry on the exact cascade (upper PI over the ADNs' exact closed loops "
        "and delays), backing off the gains where needed and then tuning them on the cascade. "
        "Writes OUT/<name>.upper.yaml, its table in OUT/tables/, OUT/<name>.cascade.csv and "
        "OUT/<name>.cascade.png. Exit code 0 when written, 2 for a user error.",
    )
    parser.add_argument("hierarchy", metavar="HIERARCHY",
                        help="hierarchy file (YAML), e.g. configs/examples/hierarchy/hv.yaml")
    parser.add_argument("--out", type=Path,
                        help="output folder (default: <name>-upper next to the hierarchy file)")
    parser.add_argument("--switches", action="store_true",
                        help="also apply the lower-switch rule to every entry of each ADN's "
                        "table (all its subsets up to %d DERs, its scenario's beyond; tuned "
                        "now where it has no table) under the upper entry for all ADNs, and "
                        "write OUT/<name>.switches.csv" % SWEEP_ALL_UP_TO)
    parser.add_argument("--run", action="store_true", dest="run_levels",
                        help="then run the hierarchy on the sim clock in this process (every "
                        "level's agents, the hierarchy file's scenario and faults), write "
                        "OUT/<name>.run.mcap and OUT/<name>.run.png and say each upper step "
                        "against the constraints")
    return parser


@contextlib.contextmanager
def _progress(label: str):
    """A progress bar on stderr; yields the ``on_entry(done, total)`` callback."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=Console(stderr=True, highlight=False)) as bar:
        task = bar.add_task(label, total=None)
        yield lambda done, total: bar.update(task, completed=done, total=total)


def _lower_entry(config, say, path: Path | None = None):
    """The ADN's entry for all its DERs: its table's (``path``, default the config's own),
    else tuned now."""
    from adnmesh.tuning.ondemand import tune_subset
    from adnmesh.tuning.table import default_table_path, load_table

    ids = list(config.der_ids())
    path = path or default_table_path(config)
    if path.exists():
        entry = load_table(path, config).lookup(ids)
        if entry is not None:
            return entry, f"its table {path}"
    say(f"  {config.path}: no table entry for all {len(ids)} DERs; tuning it now")
    return tune_subset(config, ids), "tuned now"


def hierarchy_sites(hierarchy, say=lambda text: None, tables=None):
    """Each ADN of ``hierarchy`` as a :class:`~adnmesh.cascade.upper_table.Site`: its entry for
    all its DERs (its table's -- ``tables[adn id]``, default the config's own --, else tuned
    now), its closed loop and equivalent model; ``say`` gets a line per ADN."""
    from adnmesh.cascade.equivalent import equivalent
    from adnmesh.cascade.upper_table import Site, lower_adn
    from adnmesh.config import load_config
    from adnmesh.control.operating_point import initial_p_ip_w, initial_q_ip_var

    sites = []
    for adn in hierarchy.adns:
        try:
            config = load_config(hierarchy.config_path(adn))
        except ConfigError as exc:
            raise ConfigError(f"{hierarchy.path}: adns {adn.id}: {exc}") from None
        entry, source = _lower_entry(config, say, (tables or {}).get(adn.id))
        if not entry.feasible:
            raise ConfigError(f"{hierarchy.path}: adns {adn.id}: no PI pair meets its own "
                              f"constraints for all its DERs ({entry.reason})")
        lower = lower_adn(config, entry, adn.id)
        try:
            eq = equivalent(lower, config.constraints.settling_band_pct)
        except ValueError as exc:      # delays the exact simulation cannot take
            raise ConfigError(f"{hierarchy.path}: adns {adn.id}: {exc}") from None
        say(f"  {adn.id}: {len(entry.ders)} DERs, {lower.capacity_w / 1e6:.3f} MW, entry from "
            f"{source}; closed loop rise {eq.rise_time_s:.3g} s, overshoot "
            f"{eq.overshoot_pct:.3g} %; equivalent dead time {eq.delay_s:.3g} s, lag "
            f"{eq.lag_s:.3g} s")
        sites.append(Site(adn.id, lower, adn.t_com_s, eq,
                          p_sched_w=sum(d.p_sched_w for d in config.ders_by_id(entry.ders)),
                          p_ip0_w=initial_p_ip_w(config), q_ip0_var=initial_q_ip_var(config)))
    return sites


def _hv_base(hierarchy):
    """The HV grid's net at its operating point, each ADN's bus and what it replaces checked
    (before any tuning); None without an HV grid."""
    from adnmesh.grid.hv_attach import hv_base, locate

    hv = hierarchy.hv_grid
    if hv is None:
        return None
    source, name = (("simbench", hv.simbench_code) if hv.simbench_code is not None else
                    ("pandapower", str(hierarchy.hv_net_path())))
    try:
        net = hv_base(source, name, hv.study_case)
        for adn in hierarchy.adns:
            locate(net, adn.hv_bus, adn.replaces)
    except GridError as exc:
        said = str(exc).removeprefix("grid: ").removeprefix("HV grid: ")
        raise ConfigError(f"{hierarchy.path}: hv_grid: {said}") from None
    return net


def _write_hv_net(hierarchy, sites, net, out: Path, say) -> str | None:
    """With an HV grid (``net``, :func:`_hv_base`): attach the ADNs, write it
    (OUT/<name>.hv.json) and say where each ADN hangs; return the file's name (relative to
    OUT), else None."""
    from adnmesh.grid.hv_attach import Attachment, attach_adns, write_net

    if net is None:
        return None
    by_id = {a.id: a for a in hierarchy.adns}
    attachments = [Attachment(s.id, by_id[s.id].hv_bus, s.adn.capacity_w,
                              s.p_ip0_w - s.p_sched_w, s.q_ip0_var, by_id[s.id].replaces)
                   for s in sites]
    replaced = attach_adns(net, attachments)
    path = output_path(out / f"{hierarchy.name}.hv.json", "--out")
    write_net(net, path)
    for a in attachments:
        instead = ", ".join(replaced[a.adn]) or "nothing"
        say(f"  {a.adn}: at HV bus {a.bus!r} in place of {instead}")
    return path.name


def _with_grid_gains(sites, upper, say):
    """With an HV grid: each site with ``∂P_IP/∂P`` of the upper grid at its bus, at the
    operating point (the cascade's ``K_i`` carry it); without one, the sites as they are."""
    import dataclasses

    from adnmesh.control.operating_point import grid_solver
    from adnmesh.grid.sensitivity import interface_sensitivities

    try:
        solver = grid_solver(upper)
        if solver is None:
            return sites
        p_w = [d.p_sched_w for d in upper.ders]
        gains = interface_sensitivities(solver, p_w, [0.0] * len(p_w))[0]
    except GridError as exc:
        raise ConfigError(f"{upper.path}: hv_grid with the ADNs attached: {exc}") from None
    say("  the HV grid's dP_IP/dP at each ADN's bus: " + ", ".join(
        f"{d.id} {g:.4f}" for d, g in zip(upper.ders, gains)))
    by_id = dict(zip(upper.der_ids(), gains))
    return [dataclasses.replace(s, grid_gain=float(by_id[s.id])) for s in sites]


def _write_upper_config(hierarchy, sites, out: Path, say, hv) -> Path:
    from adnmesh.cascade.upper_table import upper_config_document

    hv_net = _write_hv_net(hierarchy, sites, hv, out, say)
    path = output_path(out / f"{hierarchy.name}.upper.yaml", "--out")
    header = (f"# The upper level of {hierarchy.path.name}, written by adnmesh cascade: one actuator "
              "per ADN,\n# its equivalent closed-loop model (docs/hierarchy.md). Not for editing: "
              "written again by the command.\n")
    path.write_text(header + yaml.safe_dump(upper_config_document(hierarchy, sites, hv_net),
                                            sort_keys=False))
    return path


def _plot(hierarchy, upper, table, sites, out: Path) -> Path | None:
    """The entry for all ADNs and each ADN alone, exact against equivalent (a PNG; None if
    none of them is certified)."""
    from adnmesh.cascade.figure import plot_entries
    from adnmesh.cascade.upper_table import cascade_of
    from adnmesh.loopmodel.plant import plant_from_ders

    ids = [a.id for a in hierarchy.adns]
    wanted = [ids] + ([[i] for i in ids] if len(ids) > 1 else [])
    panels = []
    for subset in wanted:
        entry = table.lookup(subset)
        if entry is None or not entry.feasible:
            continue
        plant = plant_from_ders(upper.ders_by_id(entry.ders), upper.design_t_com_s,
                                upper.t_meas_s, entry.w, rise_per_lag=upper.rise_per_lag)
        settle = entry.figures.get("settling_time_s") or 60.0
        title = (f"{' + '.join(entry.ders)}: rise {_seconds(entry.figures['rise_time_s'])}, "
                 f"alpha {entry.figures['disk_margin']:.3g}")
        panels.append((title, cascade_of(sites, entry, hierarchy.t_meas_s), plant, entry.kp,
                       entry.ki, 2.5 * settle))
    if not panels:
        return None
    return plot_entries(panels, hierarchy.constraints.overshoot_max_pct,
                        out / f"{hierarchy.name}.cascade.png")


def _seconds(value) -> str:
    return "not reached" if value is None else f"{value:.3g} s"


def _write_rows(rows, path: Path) -> None:
    keys = ("adns", "back_off", "backed_off_rise_time_s", "stable", "disk_margin",
            "overshoot_pct", "rise_time_s", "settling_time_s", "equivalent_rise_time_s",
            "equivalent_overshoot_pct", "equivalent_disk_margin")
    with path.open("w", newline="") as f:
        out = csv.writer(f)
        out.writerow(keys)
        for r in rows:
            c = r.cascade
            out.writerow([" ".join(r.adns), r.back_off, r.backed_off_rise_time_s, c.stable,
                          c.disk_margin,
                          c.overshoot_pct, c.rise_time_s, c.settling_time_s,
                          r.equivalent_rise_time_s, r.equivalent_overshoot_pct,
                          r.equivalent_disk_margin])


def run(args: argparse.Namespace) -> int:
    """Tune the upper table and certify it on the exact cascade."""
    from adnmesh.config import load_hierarchy

    hierarchy = load_hierarchy(args.hierarchy)
    out = args.out or hierarchy.path.parent / f"{hierarchy.name}-upper"
    output_path(out, "--out", directory=True)
    with numerics_said(hierarchy):
        return _run(args, hierarchy, out)


@contextlib.contextmanager
def numerics_said(hierarchy):
    """A cascade the numerics cannot take (delays without a common unit, a loop that does not
    rise) as one line naming the hierarchy file."""
    try:
        yield
    except ValueError as exc:
        raise ConfigError(f"{hierarchy.path}: {exc}") from None


def upper_level(hierarchy, out: Path, say=lambda text: None, tables=None):
    """``(sites, upper config)`` of ``hierarchy``: its HV grid checked (before any tuning),
    each ADN's entry and loop (:func:`hierarchy_sites`, with ``tables``), the upper config (and
    the HV net) written to ``out``, each site with the HV grid's gain at its bus."""
    from adnmesh.config import load_config

    hv = _hv_base(hierarchy)
    sites = hierarchy_sites(hierarchy, say, tables)
    written = _write_upper_config(hierarchy, sites, out, say, hv)
    try:
        upper = load_config(written)
    except ConfigError as exc:
        raise ConfigError(f"{hierarchy.path}: the upper level as a config: {exc}") from None
    return _with_grid_gains(sites, upper, say), upper


def certified_upper_table(hierarchy, sites, upper, say=lambda text: None):
    """``(table, rows, path)``: the upper table tuned on the ADNs' equivalent models, each
    entry certified (and backed off) on the exact cascade, written to its default path beside
    the upper config; ``rows``: each entry's figures (:func:`~adnmesh.cascade.upper_table.
    certify_entries`)."""
    from adnmesh.cascade.upper_table import certify_entries
    from adnmesh.tuning import tune_table
    from adnmesh.tuning.table import default_table_path, save_table

    t0 = time.perf_counter()
    table = tune_table(upper, "paper")
    say(f"upper table tuned on the equivalent models: {len(table.entries)} entries in "
        f"{time.perf_counter() - t0:.1f} s; certifying each on the exact cascade")
    with _progress("certifying") as step:
        rows = certify_entries(table, {s.id: s for s in sites}, hierarchy.t_meas_s,
                               upper.constraints, on_entry=step)
    table_path = output_path(default_table_path(upper), "--out (the table)")
    save_table(table, table_path)
    return table, rows, table_path


def _run(args: argparse.Namespace, hierarchy, out: Path) -> int:
    say = lambda text: print(text, file=sys.stderr)  # noqa: E731
    t0 = time.perf_counter()
    say(f"{hierarchy.name}: {len(hierarchy.adns)} ADNs")
    sites, upper = upper_level(hierarchy, out, say)
    table, rows, table_path = certified_upper_table(hierarchy, sites, upper, say)
    csv_path = out / f"{hierarchy.name}.cascade.csv"
    _write_rows(rows, csv_path)
    png = _plot(hierarchy, upper, table, {s.id: s for s in sites}, out)
    _report(rows, table, time.perf_counter() - t0, out, table_path, csv_path)
    print(f"  figure: {png}" if png else "  no figure: neither the entry for all ADNs nor one "
          "for a single ADN is certified")
    if args.switches:
        _sweep(hierarchy, sites, table, out, say)
    if args.run_levels:
        return _simulate(hierarchy, sites, upper, table, out)
    return 0


def _simulate(hierarchy, sites, upper, table, out: Path) -> int:
    """``--run``: the hierarchy in this process on the sim clock, its recording, figure and
    steps."""
    from adnmesh.study.hierarchy import hierarchy_levels, simulate
    from adnmesh.study.hierarchy_outputs import (plot_run, step_lines, switch_lines,
                                                 write_recording)

    levels = hierarchy_levels(hierarchy, upper, table, sites)
    with _progress(f"running {hierarchy.name} (sim s)") as step:
        end_s = upper.scenario.duration_s
        result = simulate(*levels, on_progress=lambda t_ns: step(round(t_ns / 1e9), end_s))
    mcap = write_recording(result, out / f"{hierarchy.name}.run.mcap", hierarchy)
    png = plot_run(result, levels, out / f"{hierarchy.name}.run.png")
    agents = len(result.run.nodes)
    print(f"ran {hierarchy.name}: {len(levels[1])} ADNs, {agents} agents, {result.end_s:g} s in "
          f"{result.wall_s:.1f} s ({result.speed:.1f}x real time), "
          f"{len(result.run.messages)} messages")
    for line in step_lines(result) + switch_lines(result, upper.grid):
        print(line)
    print(f"  recording: {mcap} (every level; each alone beside it, "
          f"{mcap.stem}.<level>.mcap)\n  figure: {png}")
    return 0


def _lower_entries(config, name: str):
    """Every entry of the ADN's table to sweep: ``[(ders, LowerAdn)]``."""
    from adnmesh.cascade.upper_table import lower_adn
    from adnmesh.tuning import tune_table
    from adnmesh.tuning.subset_selection import select_subsets
    from adnmesh.tuning.table import default_table_path, load_table

    spec = "all" if len(config.ders) <= SWEEP_ALL_UP_TO else "scenario"
    subsets = select_subsets(config, spec)
    path = default_table_path(config)
    table = load_table(path, config) if path.exists() else None
    wanted = subsets if subsets is not None else None
    if table is None or any(table.lookup(s) is None for s in (wanted or [])) or (
            wanted is None and not table.complete):
        with _progress(f"tuning {name}'s table ({spec} subsets, global search)") as step:
            table = tune_table(config, "global", subsets=wanted, on_progress=step)
    rows = []
    for entry in table.entries.values():
        if entry.feasible:
            rows.append((entry.ders, lower_adn(config, entry, name)))
    return rows


def _sweep(hierarchy, sites, table, out: Path, say) -> None:
    """The lower-switch rule over every ADN's entries, under the upper entry for all ADNs."""
    from adnmesh.cascade.switches import switch_sweep
    from adnmesh.cascade.upper_table import cascade_of
    from adnmesh.config import load_config

    full = table.lookup(s.id for s in sites)
    if full is None or not full.feasible:
        say("--switches: the upper table has no certified entry for all ADNs; nothing to sweep")
        return
    cascade = cascade_of({s.id: s for s in sites}, full, hierarchy.t_meas_s)
    path = out / f"{hierarchy.name}.switches.csv"
    constraints = hierarchy.constraints
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(("adn", "ders", "back_off", "stable", "disk_margin", "overshoot_pct",
                         "rise_time_s", "settling_time_s"))
        for position, (adn, site) in enumerate(zip(hierarchy.adns, sites)):
            config = load_config(hierarchy.config_path(adn))
            entries = _lower_entries(config, adn.id)
            with _progress(f"switches of {adn.id}") as step:
                rows = switch_sweep(cascade, position, full.kp, full.ki,
                                    entries, constraints, on_entry=step)
            for r in rows:
                c = r.figures
                writer.writerow((r.adn, " ".join(r.ders), r.back_off, c.stable, c.disk_margin,
                                 c.overshoot_pct, c.rise_time_s, c.settling_time_s))
            kept = sum(r.back_off == 1.0 for r in rows)
            factors = [r.back_off for r in rows if r.back_off is not None]
            lost = sum(r.back_off is None for r in rows)
            strongest = f" (strongest x{min(factors):.3g})" if factors else ""
            print(f"  switches of {adn.id}: {len(rows)} entries; the upper gains hold for {kept}, "
                  f"back off for {len(factors) - kept}{strongest}"
                  + (f", no factor for {lost}" if lost else ""))
    print(f"wrote {path}")


def _report(rows, table, seconds: float, out: Path, table_path: Path, csv_path: Path) -> None:
    backed = [r for r in rows if r.back_off is not None and r.back_off < 1.0]
    gained = [r.backed_off_rise_time_s / r.cascade.rise_time_s for r in backed]
    failed = [r for r in rows if r.back_off is None]
    certified = [r for r in rows if r.back_off is not None]
    print(f"wrote {out}: the upper config, {table_path.name} ({len(table.entries)} entries) and "
          f"{csv_path.name}, in {seconds:.1f} s")
    print(f"  certified on the exact cascade: {len(certified)} of {len(rows)} entries; "
          f"{len(backed)} needed a back-off, {len(failed)} none that meets the constraints"
          + (f"; tuned on the cascade after it, {min(gained):.2g}-{max(gained):.2g}x faster "
             "than backed off" if gained else ""))
    if certified:
        low = min(certified, key=lambda r: r.cascade.disk_margin)
        high = max(certified, key=lambda r: r.cascade.overshoot_pct)
        worst = min(r.back_off for r in certified)
        print(f"  lowest disk margin {low.cascade.disk_margin:.3f} ({' '.join(low.adns)}), "
              f"highest overshoot {high.cascade.overshoot_pct:.3g} % "
              f"({' '.join(high.adns)}), strongest back-off x{worst:.3g}")
    for r in failed[:5]:
        print(f"  not certified {' '.join(r.adns)}: {table.lookup(r.adns).reason}")
    if not (table.static and table.static.feasible):
        return
    s = table.static
    print(f"  static pair over every subset: K_P {s.kp:.4g} 1/W, K_I {s.ki:.4g} 1/(W s), back-off "
          f"x{s.figures['cascade_back_off']:.3g}")
