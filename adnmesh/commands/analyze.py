"""``adnmesh analyze CONFIG``: robustness, model-uncertainty and solution-space analyses.

Reads the scheduling table of CONFIG (``--table``, default :func:`adnmesh.tuning.table.default_table_path`)
and writes every output of one run into one folder (``--out``, default
``out/analyze-<config stem>-<timestamp>/``) with an ``index.md`` that links them all. The
numerics are in :mod:`adnmesh.analysis` and :mod:`adnmesh.dermodels`; this module only parses,
reports progress and writes. ``--der-models`` adds the detailed DER models' step responses beside
the reference PT1 (``--only der-models``: that part alone, which needs no table). ``--pq-region``
computes the feasible P-Q region at the interconnection point (:mod:`adnmesh.analysis.pq_region`;
no table; without ``--only`` the table analyses are left out).
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from datetime import datetime
from pathlib import Path

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn,
                           TimeElapsedColumn)
from rich.table import Table

from adnmesh import __version__
from adnmesh.analysis import plots, report
from adnmesh.analysis.robustness import METRICS, analyze_robustness
from adnmesh.analysis.solution_space import paper_path, solution_space
from adnmesh.analysis.subset_loops import subset_name
from adnmesh.analysis.uncertainty import MODELS, analyze_uncertainty
from adnmesh.commands import (add_config_argument, add_quantity_argument, comma_list,
                              der_id_list, load_loop_config, output_path)
import numpy as np
from adnmesh.errors import ConfigError, UsageError
from adnmesh.tuning.table import default_table_path, load_table

__all__ = ["add_parser", "run", "PARTS", "parse_subset", "default_out_dir"]

PARTS = ("robustness", "uncertainty", "solution-space", "der-models", "coupling", "pq-region")
_TABLE_PARTS = ("robustness", "uncertainty", "solution-space")


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``analyze`` subparser."""
    parser = subparsers.add_parser(
        "analyze",
        help="robustness, model-uncertainty and solution-space analyses of the table",
        description="Analyse the scheduling table of CONFIG (docs/method.md#analyses): figures of "
        "merit of every "
        "subset, adaptive vs static (box plots, CSV); stability and doubling limits of the "
        "actuator time-constant factor b for the PT1, PT2 and RHPZ models (table, JSON, "
        "figure); optionally the (K_P, K_I) solution space of one subset, or the feasible P-Q "
        "region at the interconnection point (--pq-region, no table). All outputs go to "
        "one folder with an index.md. Exit code 0 when written, 2 for a user error (config, "
        "table, options, an unwritable folder).",
    )
    add_config_argument(parser)
    add_quantity_argument(parser)
    parser.add_argument("--table", metavar="PATH",
                        help="scheduling table (default: the one 'adnmesh tune CONFIG' writes)")
    parser.add_argument("--out", metavar="DIR",
                        help="output folder (default: out/analyze-<config>-<timestamp>)")
    parser.add_argument("--outliers", action="store_true",
                        help="show outliers in the box plots (hidden by default, as in the paper)")
    parser.add_argument("--solution-space", metavar="IDS",
                        help="also map the (K_P, K_I) plane of this subset, e.g. SGen1,SGen5")
    parser.add_argument("--der-models", action="store_true",
                        help="also draw the detailed DER models' step responses beside the "
                        "reference PT1, with their rise times (der-models.png, .csv, .json)")
    parser.add_argument("--coupling", action="store_true",
                        help="reactive power control: the P and Q loops together, the coupled "
                        "2x2 loop on the power flow linearised at the DERs' schedules, exact "
                        "delays (coupling.md, .png, .json; both tables, tuned on demand where "
                        "they lack the set of all DERs)")
    parser.add_argument("--pq-region", action="store_true",
                        help="the feasible P-Q region at the interconnection point under the "
                        "grid limits and the DERs' capability, beside the region without grid "
                        "limits (pq-region.png, .csv; needs a grid_model and no table; without "
                        "--only it runs without the table analyses)")
    parser.add_argument("--available", metavar="IDS",
                        help="--pq-region for these DERs available, e.g. SGen5,SGen6 (the "
                        "others at their schedules; default all)")
    parser.add_argument("--directions", type=int, metavar="N",
                        help="--pq-region: evenly spread directions before the refinement "
                        "(default 24)")
    parser.add_argument("--grid", type=int, default=60, metavar="N",
                        help="solution-space grid points per axis (default 60)")
    parser.add_argument("--models", default=",".join(MODELS), metavar="LIST",
                        help=f"actuator models of the uncertainty analysis "
                        f"(default {','.join(MODELS)})")
    parser.add_argument("--only", metavar="PARTS",
                        help=f"run only these parts, comma-separated ({', '.join(PARTS)})")
    return parser


def parse_subset(config, text: str) -> tuple[str, ...]:
    """DER ids from ``"SGen1,SGen5"`` in config order; one-line errors for bad input."""
    ids = der_id_list(config, text, "--solution-space")
    return tuple(d for d in config.der_ids() if d in ids)


def _parse_list(text: str, allowed, option: str) -> tuple[str, ...]:
    items = [x.lower() for x in comma_list(text)]
    bad = [x for x in items if x not in allowed]
    if not items or bad:
        raise UsageError(f"{option}: {'unknown value ' + repr(bad[0]) if bad else 'empty'} "
                         f"(choose from {', '.join(allowed)})")
    return tuple(dict.fromkeys(items))


def default_out_dir(config) -> Path:
    """``out/analyze-<config stem>-<YYYYmmdd-HHMMSS>`` relative to the working directory."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    loop = "-q" if config.quantity == "Q" else ""
    return Path("out") / f"analyze-{Path(config.path).stem}{loop}-{stamp}"


def _covers(config, table) -> str:
    """What a figure covers, for its title: the config file and its table."""
    name = Path(config.path).name + (", Q loop" if config.quantity == "Q" else "")
    if table is None:
        return f"{name}, no table"
    return f"{name}, {table.method} table of {len(table.entries)} entries"


def _progress(console: Console) -> Progress:
    return Progress(SpinnerColumn(), TextColumn("{task.description:<44}"), BarColumn(),
                    MofNCompleteColumn(), TimeElapsedColumn(), console=console)


def _write_csv(path: Path, header, rows) -> None:
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        writer.writerows(rows)


def _robustness(config, table, out: Path, outliers: bool, console: Console, err: Console):
    n = len(table.entries) * (2 if table.static is not None else 1)
    with _progress(err) as bar:
        task = bar.add_task("robustness: evaluating subsets", total=n)
        result = analyze_robustness(config, table, progress=lambda k: bar.advance(task, k))
    header, rows = result.csv_rows()
    _write_csv(out / "robustness.csv", header, rows)
    plots.plot_robustness(result, out / "robustness.png", outliers=outliers,
                          covers=_covers(config, table), unit=config.unit)
    md = report.robustness_markdown(result)
    (out / "robustness.md").write_text(md)
    t = Table(title=f"Robustness and performance over {len(result.subsets)} subsets "
              "(median; worst subset)")
    t.add_column("figure")
    for c in result.controllers:
        t.add_column(f"{c} median", justify="right")
        t.add_column(f"{c} worst", overflow="fold")
    summaries = {c: result.summary(c) for c in result.controllers}
    for m in METRICS:
        row = [m.label.replace("(band)", f"({result.band_pct:g} % band)")]
        for c in result.controllers:
            s = summaries[c][m.key]
            row += [report.fmt(s.median), report.worst_text(s)]
        t.add_row(*row)
    console.print(t)
    none = result.without_gains()
    if none:
        console.print(f"adaptive: {len(none)} subset(s) without a PI pair in the table (not "
                      f"evaluated), e.g. {{{none[0]}}}")
    for c in result.controllers:
        bad = result.unstable(c)
        if bad:
            console.print(f"{c}: {len(bad)} unstable subset(s), e.g. {{{bad[0]}}}")
    return result, md


def _uncertainty(config, table, rob, models, out: Path, console: Console, err: Console):
    from adnmesh.analysis.robustness import table_batches
    if rob is None:
        adaptive, static, _, _ = table_batches(config, table)
        jobs = [("adaptive", adaptive, None), ("static", static, None)]
    else:
        jobs = [("adaptive", rob.adaptive_batch, rob.adaptive),
                ("static", rob.static_batch, rob.static)]
    jobs = [j for j in jobs if j[1] is not None]
    band = config.constraints.settling_band_pct
    results = []
    with _progress(err) as bar:
        tasks = {name: bar.add_task(f"uncertainty ({name})", total=6 * len(models))
                 for name, _, _ in jobs}
        for name, batch, nominal in jobs:
            task = tasks[name]
            nom = None if nominal is None else (nominal["rise_time_s"],
                                                nominal["settling_time_s"])
            res = analyze_uncertainty(
                batch, band, name, models, nominal=nom,
                notify=lambda text, task=task, name=name: bar.update(
                    task, description=f"uncertainty ({name}): {text}"[:44]),
                scan_done=lambda task=task: bar.advance(task))
            bar.update(task, description=f"uncertainty ({name})")
            results.append(res)
    md = report.uncertainty_markdown(results)
    (out / "uncertainty.md").write_text(f"# Model uncertainty: {config.path}\n\n{md}")
    doc = {"config": str(config.path), "config_sha256": config.sha256,
           "settling_band_pct": band, "note": report.REFERENCE_NOTE.format(band=band),
           "controllers": {r.controller: r.to_json() for r in results}}
    (out / "uncertainty.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
    plots.plot_uncertainty(results, out / "uncertainty.png", covers=_covers(config, table))
    for res in results:
        header, values, who = report.uncertainty_rows(res)
        t = Table(title=f"Model uncertainty, {res.controller} controller: limits in b "
                  f"(first failing subset below)")
        for h in header:
            t.add_column(h, overflow="fold")
        for v, w in zip(values, who):
            t.add_row(*v)
            t.add_row("", *w[1:], style="dim")
        console.print(t)
    return results, md


def _solution_space(config, table, ids, grid: int, out: Path, console: Console, err: Console):
    path = paper_path(config, ids)
    entry = table.lookup(ids) if table is not None else None
    point = None
    if entry is not None and entry.kp > 0 and entry.ki > 0:     # NaN: entry without a PI pair
        point = (entry.kp, entry.ki)
    with _progress(err) as bar:
        task = bar.add_task(f"solution space {{{subset_name(ids)}}}", total=grid * grid)
        space = solution_space(config, ids, n=grid, path=path, table_point=point,
                               progress=lambda k: bar.advance(task, k))
    stem = "solution-space-" + "+".join(ids)
    plots.plot_solution_space(space, out / f"{stem}.png", covers=_covers(config, table),
                              unit=config.unit)
    rows = []
    for i, ki in enumerate(space.ki):
        for j, kp in enumerate(space.kp):
            rows.append([f"{kp:.6g}", f"{ki:.6g}", space.reason[i, j] or "feasible",
                         report.csv_number(space.disk_margin[i, j]),
                         report.csv_number(space.overshoot_pct[i, j]),
                         report.csv_number(space.rise_time_s[i, j])])
    _write_csv(out / f"{stem}.csv", ["kp_per_w", "ki_per_w_s", "class", "disk_margin",
                                      "overshoot_pct", "rise_time_s"], rows)
    best = space.best()
    doc = {"ders": list(ids), "p_inst_w": space.p_inst_w, "grid": grid,
           "kp_range_per_w": [float(space.kp[0]), float(space.kp[-1])],
           "ki_range_per_w_s": [float(space.ki[0]), float(space.ki[-1])],
           "counts": space.counts(), "constraints": space.constraints,
           "grid_optimum": None if best is None else
           {"kp": best[0], "ki": best[1], "rise_time_s": best[2]},
           "table_entry": None if point is None else {"kp": point[0], "ki": point[1]},
           "paper_path": None if path is None else
           [{"kp": kp, "ki": ki, "feasible": ok} for kp, ki, ok in path]}
    (out / f"{stem}.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
    counts = ", ".join(f"{k} {v}" for k, v in space.counts().items())
    line = f"solution space {{{subset_name(ids)}}}: {grid}x{grid} points ({counts})"
    if best is not None:
        line += f"; grid optimum K_P {best[0]:.4g} 1/{config.unit}, K_I {best[1]:.4g} " \
                f"1/({config.unit} s), " \
                f"rise time {best[2]:.4g} s"
    console.print(line)
    if path is None:
        console.print("  (no search path drawn: adnmesh.tuning.paper_path is not available)")
    else:
        console.print(f"  paper search path: {len(path)} points")
    return stem, space, path


def _der_models(config, out: Path, console: Console) -> str:
    """Step responses of every DER's default detailed model beside the reference PT1."""
    from adnmesh.dermodels.response_plot import distinct_reports, plot_der_models
    from adnmesh.dermodels.responses import der_model_report

    reports = [der_model_report(der) for der in config.ders]
    plot_der_models(reports, out / "der-models.png")
    _der_handover(config, out)
    rows = [[r.der_id, r.der_type, r.model_name, s.direction, f"{100 * s.step_fraction:g}",
             f"{s.rise_time_s:.6g}", f"{s.reaction_s:.6g}", f"{ref.rise_time_s:.6g}",
             f"{ref.reaction_s:.6g}"]
            for r in reports for s, ref in zip(r.responses, r.reference)]
    _write_csv(out / "der-models.csv", ["der", "type", "model", "direction", "step_pct",
                                        "rise_time_s", "reaction_s", "pt1_rise_time_s",
                                        "pt1_reaction_s"], rows)
    doc = {"config": str(config.path), "config_sha256": config.sha256,
           "note": "setpoint steps from 50 % of P_inst; rise time 10-90 %, exact to 1 ns; "
                   "reaction: first instant the infeed moved by 1e-9 of the step",
           "ders": [r.to_json() for r in reports]}
    (out / "der-models.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
    t = Table(title="DER models: 10-90 % rise time of setpoint steps from 50 % of P_inst, s")
    groups = distinct_reports(reports)
    steps = [s.label for s in groups[0][0].responses]
    for header in ["DERs", "model", *steps, "PT1"]:
        t.add_column(header, justify="left" if header in ("DERs", "model") else "right")
    lines = ["| DERs | model | " + " | ".join(steps) + " | PT1 |",
             "|---|---|" + "---:|" * (len(steps) + 1)]
    for report, ids in groups:
        cells = [f"{s.rise_time_s:.4g}" for s in report.responses]
        ref = f"{report.reference[0].rise_time_s:.4g}"
        t.add_row(", ".join(ids), report.model_name, *cells, ref)
        lines.append(f"| {', '.join(ids)} | {report.model_name} | " + " | ".join(cells)
                     + f" | {ref} |")
    console.print(t)
    return "\n".join(lines)


def _entry_of_all(config, table):
    """The entry of the set of all DERs of ``config``: the table's, else tuned now."""
    from adnmesh.tuning import tune_subset

    ids = list(config.der_ids())
    entry = None if table is None else table.lookup(ids)
    if entry is None or not entry.feasible:
        entry = tune_subset(config, ids)
    if not entry.feasible:
        raise ConfigError(f"{config.path}: no PI pair meets the constraints for the "
                          f"{config.quantity} loop of all DERs ({entry.reason})")
    return entry


def _coupling(config, table, out: Path, console: Console) -> str:
    """The coupled P-Q loop (:mod:`adnmesh.analysis.coupling`): coupling.md, .png, .json."""
    from adnmesh.analysis.coupling import coupled_loop, loop_side
    from adnmesh.analysis.plots import plot_coupling
    from adnmesh.control.operating_point import grid_label, grid_solver
    from adnmesh.grid.sensitivity import interface_sensitivities
    from adnmesh.reactive import reactive_view

    view = reactive_view(config)
    q_path = default_table_path(view)
    q_table = load_table(q_path, view) if q_path.exists() else None
    p_entry, q_entry = _entry_of_all(config, table), _entry_of_all(view, q_table)
    solver = grid_solver(config)
    if solver is None:
        grid = "no grid model: P_IP and Q_IP are the sums of the infeeds"
        rows = np.array([[1.0, 0.0, 0.0, 1.0]] * len(config.ders)).T
    else:
        grid = f"{grid_label(config)}, linearised at the DERs' schedules"
        rows = interface_sensitivities(solver, [d.p_sched_w for d in config.ders],
                                       [d.q_sched_var for d in config.ders])
    sens = {d.id: rows[:, i] for i, d in enumerate(config.ders)}
    result = coupled_loop(loop_side(config, p_entry), loop_side(view, q_entry), sens,
                          config.design_t_com_s, config.t_meas_s)
    plot_coupling(result, out / "coupling.png", covers=f"{Path(config.path).name}; {grid}")
    doc = {"config": str(config.path), "grid": grid, "mu": result.mu,
           "mu_omega_rad_s": result.mu_omega, "stable": result.stable,
           "p_loop": {"kp": p_entry.kp, "ki": p_entry.ki, "stable": result.p_stable,
                      "disk_margin_with_grid": result.p_disk_margin},
           "q_loop": {"kp": q_entry.kp, "ki": q_entry.ki, "stable": result.q_stable,
                      "disk_margin_with_grid": result.q_disk_margin},
           "q_into_p_max_w_per_var": float(result.q_into_p.max()),
           "p_into_q_max_var_per_w": float(result.p_into_q.max()),
           "sensitivities": {d: dict(zip(("dp_ip_dp", "dp_ip_dq", "dq_ip_dp", "dq_ip_dq"),
                                         map(float, v))) for d, v in sens.items()}}
    (out / "coupling.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
    verdict = ("stable: both loops stable with the grid's gains and max |M| < 1"
               if result.stable else "NOT shown stable: " + (
                   "max |M| >= 1 (the small-gain bound does not hold)"
                   if result.p_stable and result.q_stable else "a loop is unstable alone"))
    text = "\n".join([
        f"Grid: {grid}.", "",
        "| | P loop | Q loop |", "|---|---:|---:|",
        f"| K_P, K_I | {p_entry.kp:.4g} 1/W, {p_entry.ki:.4g} 1/(W s) | {q_entry.kp:.4g} "
        f"1/var, {q_entry.ki:.4g} 1/(var s) |",
        f"| stable with the grid's gains | {'yes' if result.p_stable else 'NO'} | "
        f"{'yes' if result.q_stable else 'NO'} |",
        f"| disk margin with the grid's gains | {result.p_disk_margin:.4g} | "
        f"{result.q_disk_margin:.4g} |", "",
        f"Coupling: max |M(jω)| = {result.mu:.3g} at {result.mu_omega:.3g} rad/s; {verdict}.",
        f"Largest |Q_ref → P_IP| {result.q_into_p.max():.3g} W/var, |P_ref → Q_IP| "
        f"{result.p_into_q.max():.3g} var/W (the other loop open)."])
    console.print(f"coupling: max |M| {result.mu:.3g} at {result.mu_omega:.3g} rad/s; "
                  f"{verdict}; disk margins with the grid's gains: P {result.p_disk_margin:.4g}, "
                  f"Q {result.q_disk_margin:.4g}")
    (out / "coupling.md").write_text(text + "\n")
    return text


def _pq_options(args: argparse.Namespace, parts: tuple[str, ...]) -> None:
    """``--available`` and ``--directions`` only with the P-Q region, N in range."""
    if "pq-region" not in parts:
        for option, value in (("--available", args.available),
                              ("--directions", args.directions)):
            if value is not None:
                raise UsageError(f"{option} is an option of --pq-region")
    if args.directions is not None and not 4 <= args.directions <= 360:
        raise UsageError(f"--directions must be between 4 and 360, got {args.directions}")


def _pq_config(config, args: argparse.Namespace) -> None:
    """The P-Q region is of the config as written and needs its grid model."""
    if config.quantity == "Q":
        raise UsageError("--pq-region is of the config as written (P and Q together); leave "
                         "out --quantity q")
    if config.grid_model is None:
        raise UsageError(f"--pq-region: {args.config} has no grid_model: the P-Q region "
                         "needs the grid (its voltages and loadings from the power flow)")
    if args.available is not None:
        der_id_list(config, args.available, "--available")


def _pq_region(config, args: argparse.Namespace, out: Path, console: Console,
               err: Console) -> str:
    """The feasible P-Q region (:mod:`adnmesh.analysis.pq_region`): pq-region.png, .csv."""
    from adnmesh.analysis.pq_region import DEFAULT_DIRECTIONS, edge_words, pq_region, q_range_var
    from adnmesh.control.operating_point import (available_power_w, grid_label, grid_solver,
                                                 initial_p_ip_w, initial_q_ip_var)

    ids = None if args.available is None else der_id_list(config, args.available,
                                                          "--available")
    directions = args.directions or DEFAULT_DIRECTIONS
    t0 = time.perf_counter()
    with _progress(err) as bar:
        task = bar.add_task("P-Q region: optimising directions", total=2 * directions)
        region = pq_region(grid_solver(config), config.ders, available_power_w(config),
                           config.grid_model.limits, config.reactive, available=ids,
                           directions=directions,
                           progress=lambda k, n: bar.update(task, completed=k, total=n))
    took = time.perf_counter() - t0
    point = (initial_p_ip_w(config), initial_q_ip_var(config))
    who = "all DERs" if ids is None else f"available: {', '.join(region.moving)}"
    plots.plot_pq_region(region, out / "pq-region.png", point,
                         covers=f"{Path(config.path).name}; {grid_label(config)}\n{who}")
    _write_csv(out / "pq-region.csv", *_pq_rows(region))
    lo, hi = region.p_span_w()
    span = q_range_var(region, point[0])
    at_point = ("outside the region" if span is None else
                f"{span[0] / 1e6:.3f} to {span[1] / 1e6:.3f} Mvar")
    qlo, qhi = region.q_span_var()
    lines = [f"P-Q region ({grid_label(config)}; {who}): P_IP {lo / 1e6:.3f} to "
             f"{hi / 1e6:.3f} MW, Q_IP {qlo / 1e6:.3f} to {qhi / 1e6:.3f} Mvar",
             f"Q_IP at the operating point (P_IP {point[0] / 1e6:.3f} MW, DERs at their "
             f"schedules): {at_point}",
             edge_words(region),
             f"{len(region.support)} support points, edges within "
             f"{region.boundary_error_w / 1e3:.2g} kW (kvar) of the region; "
             f"{region.power_flows:,} power flows in {took:.1f} s",
             *(f"note: {n}" for n in region.notes)]
    for line in lines:
        console.print(line)
    return "\n".join(f"- {line}" for line in lines)


def _pq_rows(region) -> tuple[list[str], list[list]]:
    """The CSV of a region and its comparison: one row per support point."""
    ids = region.der_ids
    header = (["region", "direction_deg", "p_ip_w", "q_ip_var", "vertex", "binding",
               "vm_min_pu", "vm_max_pu", "loading_max_pct"]
              + [f"p_{d}_w" for d in ids] + [f"q_{d}_var" for d in ids])
    rows = []
    for name, part in (("grid_limits", region), ("der_capability", region.without_limits)):
        corners = {(float(p), float(q)) for p, q in part.vertices}
        for s in part.support:
            rows.append([name, f"{np.degrees(s.direction_rad):.6g}", f"{s.p_ip_w:.6f}",
                         f"{s.q_ip_var:.6f}", int((s.p_ip_w, s.q_ip_var) in corners),
                         "; ".join(s.binding), f"{s.vm_min_pu:.8f}", f"{s.vm_max_pu:.8f}",
                         report.csv_number(s.loading_max_pct),
                         *(f"{v:.3f}" for v in s.der_p_w), *(f"{v:.3f}" for v in s.der_q_var)])
    return header, rows


def _der_handover(config, out: Path) -> None:
    """The re-entry transient of the detailed models, open loop (der-handover.png;
    docs/method.md#returning-ders-handover)."""
    import math

    from adnmesh.control.cpfc_controller import HANDOVER_RESPONSE_TIMES
    from adnmesh.dermodels.handover import handover_panels
    from adnmesh.dermodels.response_plot import plot_handover

    panels = handover_panels(config.ders, lambda d: d.t_delay_s + config.t_lag_s(d)
                             * math.log(9.0), HANDOVER_RESPONSE_TIMES)
    plot_handover(panels, out / "der-handover.png")


def _index(config, table_path: Path, table, out: Path, parts: dict, times: dict,
           total_s: float, outliers: bool) -> str:
    lines = [f"# adnmesh analyze: {config.path}", "",
             f"- config: `{config.path}` (sha256 {config.sha256[:12]})"]
    if table is not None:
        lines.append(f"- table: `{table_path}` (method {table.method}, {len(table.entries)} "
                     "entries" + ("" if table.complete else ", incomplete")
                     + ", static controller "
                     + ("yes" if table.static is not None else "none") + ")")
    lines += [f"- adnmesh {__version__}, {datetime.now().isoformat(timespec='seconds')}",
             f"- run time {total_s:.1f} s ("
             + ", ".join(f"{k} {v:.1f} s" for k, v in times.items()) + ")", ""]
    if "robustness" in parts:
        lines += ["## Robustness and performance", "",
                  "Every subset of the table as deployed (adaptive: its own K_P, K_I and "
                  "weights W; static: the one static pair), reference model (PT1) with exact "
                  "delays. Box plots with outliers " + ("shown" if outliers else "hidden") + ".",
                  "", "![robustness](robustness.png)", "",
                  "- [robustness.png](robustness.png) — box plots",
                  "- [robustness.csv](robustness.csv) — one row per subset",
                  "- [robustness.md](robustness.md) — summary table", "",
                  parts["robustness"], ""]
    if "uncertainty" in parts:
        lines += ["## Model uncertainty", "", "![uncertainty](uncertainty.png)", "",
                  "- [uncertainty.png](uncertainty.png) — ranges of b without failure",
                  "- [uncertainty.md](uncertainty.md) — the tables below",
                  "- [uncertainty.json](uncertainty.json) — limits, subsets and every "
                  "evaluation of the scans", "", parts["uncertainty"], ""]
    if "solution-space" in parts:
        stem, space, path = parts["solution-space"]
        best = space.best()
        lines += [f"## Solution space of {{{space.name}}}", "",
                  f"![solution space]({stem}.png)", "",
                  f"- [{stem}.png]({stem}.png) — feasibility and rise time over (K_P, K_I), "
                  "weights 1" + ("" if path else " (no search path: adnmesh.tuning.paper_path "
                                 "not available)"),
                  f"- [{stem}.csv]({stem}.csv) — every grid point",
                  f"- [{stem}.json]({stem}.json) — grid extent, counts, search path", ""]
        if best is not None:
            lines += [f"Grid optimum: K_P = {best[0]:.4g} 1/{config.unit}, K_I = "
                      f"{best[1]:.4g} 1/({config.unit} s), "
                      f"rise time {best[2]:.4g} s.", ""]
    if "der-models" in parts:
        lines += ["## DER models", "",
                  "Default detailed models (WT Type 4B-like, CHP second order with rate limit, "
                  "PV lag with processing delay) against the reference PT1: setpoint steps up "
                  "and down from 50 % of P_inst, responses normalised to the step. The "
                  "defaults match the config's T_delay and T_rise for the 10 % step.", "",
                  "![DER models](der-models.png)", "",
                  "- [der-models.png](der-models.png) — step responses",
                  "- [der-handover.png](der-handover.png) — re-entry transient (open loop: "
                  "a returning DER takes a share from another, at once and over the handover)",
                  "- [der-models.csv](der-models.csv) — rise and reaction time per DER and step",
                  "- [der-models.json](der-models.json) — the same with every model parameter",
                  "", parts["der-models"], ""]
    if "pq-region" in parts:
        lines += ["## Feasible P-Q region", "",
                  "The (P_IP, Q_IP) the DERs can reach under the grid limits and their "
                  "capability, beside the region without grid limits "
                  "(docs/method.md#feasible-p-q-region).", "",
                  "![P-Q region](pq-region.png)", "",
                  "- [pq-region.png](pq-region.png) — the regions, binding limits and the "
                  "operating point",
                  "- [pq-region.csv](pq-region.csv) — one row per support point: direction, "
                  "P_IP, Q_IP, binding limits, every DER's set-points", "",
                  parts["pq-region"], ""]
    if "coupling" in parts:
        lines += ["## P and Q together", "",
                  "The coupled 2×2 loop on the linearised grid, exact delays "
                  "(docs/method.md#coupling-of-p-and-q): M(jω) is the part of det(I + L) the "
                  "coupling adds; with both loops stable alone, max |M| < 1 proves the coupled "
                  "loop stable.", "", "![coupling](coupling.png)", "",
                  "- [coupling.png](coupling.png) — |M(jω)| and the cross transfers",
                  "- [coupling.json](coupling.json) — figures and the grid's sensitivities", "",
                  parts["coupling"], ""]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Run the analyses and write the output folder."""
    t_start = time.perf_counter()
    if args.grid < 5 or args.grid > 400:
        raise UsageError(f"--grid must be between 5 and 400, got {args.grid}")
    models = _parse_list(args.models, MODELS, "--models")
    parts = _parse_list(args.only, PARTS, "--only") if args.only else PARTS
    on_request = ("der-models", "coupling", "pq-region")
    parts = tuple(p for p in parts if p not in on_request or args.only)
    if args.pq_region and not args.only:     # the region alone: no table analyses
        parts = tuple(p for p in parts if p not in ("robustness", "uncertainty"))
    for flag, part in ((args.der_models, "der-models"), (args.coupling, "coupling"),
                       (args.pq_region, "pq-region")):
        if flag and part not in parts:       # these only on request
            parts += (part,)
    _pq_options(args, parts)
    config = load_loop_config(args)
    if "pq-region" in parts:
        _pq_config(config, args)
    if config.quantity == "Q" and ("der-models" in parts or "coupling" in parts):
        raise UsageError("--der-models and --coupling are of the config as written (the "
                         "coupling analysis takes both loops); leave out --quantity q")
    if "coupling" in parts and config.reactive is None:
        raise UsageError(f"--coupling: {args.config} has no reactive section (no Q loop)")
    ids = parse_subset(config, args.solution_space) if args.solution_space is not None else None
    if ids is None:
        if args.only and "solution-space" in parts:
            raise UsageError("--only solution-space needs --solution-space IDS")
        parts = tuple(p for p in parts if p != "solution-space")
    table_path = Path(args.table) if args.table else default_table_path(config)
    table = None
    if any(p in _TABLE_PARTS for p in parts):
        if not table_path.exists():
            option = " --quantity q" if config.quantity == "Q" else ""
            raise ConfigError(f"{table_path}: no scheduling table; run 'adnmesh tune "
                              f"{args.config}{option}' first (or give --table PATH)")
        table = load_table(table_path, config)
        if not table.entries:
            raise ConfigError(f"{table_path}: the table has no entries")
    out = output_path(Path(args.out) if args.out else default_out_dir(config), "--out",
                      directory=True)
    # wide tables when the output is a file or pipe (rich assumes 80 columns there)
    console = Console(highlight=False, width=None if sys.stdout.isatty() else 160)
    err = Console(stderr=True, highlight=False)
    n_all = 2 ** len(config.ders) - 1
    if table is not None:
        console.print(f"analyze {config.path}: table {table_path} ({len(table.entries)} of "
                      f"{n_all} subsets, method {table.method}"
                      + ("" if table.static is not None else ", no static controller") + ")")
    else:
        console.print(f"analyze {config.path}: {', '.join(parts)} (no table needed)")
    done, times, rob = {}, {}, None
    if "robustness" in parts:
        t0 = time.perf_counter()
        rob, done["robustness"] = _robustness(config, table, out, args.outliers, console, err)
        times["robustness"] = time.perf_counter() - t0
    if "uncertainty" in parts:
        t0 = time.perf_counter()
        _, done["uncertainty"] = _uncertainty(config, table, rob, models, out, console, err)
        times["uncertainty"] = time.perf_counter() - t0
    if "solution-space" in parts:
        t0 = time.perf_counter()
        done["solution-space"] = _solution_space(config, table, ids, args.grid, out, console,
                                                 err)
        times["solution space"] = time.perf_counter() - t0
    if "der-models" in parts:
        t0 = time.perf_counter()
        done["der-models"] = _der_models(config, out, console)
        times["DER models"] = time.perf_counter() - t0
    if "coupling" in parts:
        t0 = time.perf_counter()
        done["coupling"] = _coupling(config, table, out, console)
        times["coupling"] = time.perf_counter() - t0
    if "pq-region" in parts:
        t0 = time.perf_counter()
        done["pq-region"] = _pq_region(config, args, out, console, err)
        times["P-Q region"] = time.perf_counter() - t0
    total = time.perf_counter() - t_start
    index = _index(config, table_path, table, out, done, times, total, args.outliers)
    (out / "index.md").write_text(index)
    console.print(f"wrote {out / 'index.md'} ({total:.1f} s: "
                  + ", ".join(f"{k} {v:.1f} s" for k, v in times.items()) + ")")
    return 0
