"""``adnmesh tune CONFIG``: compute the gain-scheduling table for every DER subset."""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from adnmesh.commands import add_config_argument, add_quantity_argument, load_loop_config, output_path
from adnmesh.errors import UsageError
from adnmesh.tuning.table import default_table_path
#: shown in --help; equals adnmesh.tuning.subset_selection.MAX_ALL_DERS (not imported: the CLI stays light)
MAX_ALL_DERS = 16
#: --workers at most (processes; more than the machine's CPUs only cost memory)
MAX_WORKERS = 1024

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``tune`` subparser."""
    parser = subparsers.add_parser(
        "tune",
        help="compute the gain-scheduling table (all DER subsets)",
        description="Tune a PI pair and weights for every non-empty DER subset of CONFIG "
        "(disk margin and overshoot constraints from the config) and write the table as JSON "
        "plus CSV. Default output: tables/<config>.<design hash[:12]>.json next to the config, where `adnmesh up` looks. "
        "Exit code 0 when the table is written, 2 for a user error (config, options, an "
        "unwritable output), 130 after Ctrl-C (the partial table is kept for --resume).",
    )
    add_config_argument(parser)
    add_quantity_argument(parser)
    parser.add_argument("--method", choices=("paper", "global"), default="paper",
                        help="the paper's path/area search (default) or the global search")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="worker processes (default: the number of CPUs, here %(default)s)")
    parser.add_argument("--out", type=Path, help="table path (JSON); the CSV goes beside it")
    parser.add_argument("--subsets", metavar="all|scenario|random:N|FILE",
                        help="which subsets: all (refused beyond %d DERs), those the "
                        "scenario meets, N random ones plus the set of all DERs, or those "
                        "listed in FILE (one subset per line, DER ids); default: all up to "
                        "%d DERs, the scenario's beyond (the CPFC tunes any other on demand)"
                        % (MAX_ALL_DERS, MAX_ALL_DERS))
    parser.add_argument("--resume", action="store_true",
                        help="continue an interrupted run's partial table at --out")
    parser.add_argument("--robust", action="store_true",
                        help="require the config's uncertainty set (constraints.robust, e.g. "
                        "from adnmesh identify --robust-out) and report each entry's worst "
                        "member; a config with a set is always tuned over it")
    parser.add_argument("--disk-margin-min", type=float, help="override the config's alpha limit")
    parser.add_argument("--overshoot-max-pct", type=float, help="override the overshoot limit, %%")
    return parser


def run(args: argparse.Namespace) -> int:
    """Tune, showing progress; Ctrl-C keeps the partial table (exit 130)."""
    from adnmesh.tuning import tune_table, write_csv
    from adnmesh.tuning.subset_selection import select_subsets

    if not 1 <= args.workers <= MAX_WORKERS:
        raise UsageError(f"--workers must be 1 to {MAX_WORKERS}, got {args.workers}")
    if args.disk_margin_min is not None and not 0 < args.disk_margin_min < 2:
        raise UsageError(f"--disk-margin-min must be in (0, 2), got {args.disk_margin_min:g}")
    if args.overshoot_max_pct is not None and not 0 < args.overshoot_max_pct <= 100:
        raise UsageError(f"--overshoot-max-pct must be in (0, 100] (as the config's "
                         f"overshoot_max_pct), got {args.overshoot_max_pct:g}")
    config = load_loop_config(args)
    if args.robust and config.constraints.robust is None:
        raise UsageError(f"--robust: {args.config} has no uncertainty set (constraints.robust; "
                         "adnmesh identify --robust-out writes one, docs/tuning.md#robust-tables)")
    spec = args.subsets
    if spec is None:
        spec = "all" if len(config.ders) <= MAX_ALL_DERS else "scenario"
    subsets = select_subsets(config, spec)
    if args.subsets is None and spec == "scenario":
        print(f"{len(config.ders)} DERs: 2^{len(config.ders)} - 1 subsets are more than a table "
              f"holds (all: up to {MAX_ALL_DERS} DERs); tuning the {len(subsets)} subset(s) the "
              "scenario meets, and the static pair; the CPFC tunes any other subset on demand "
              "at run time (--subsets chooses otherwise)", file=sys.stderr)
    out = args.out or default_table_path(config)
    if args.resume and not out.exists():
        raise UsageError(f"--resume: no partial table at {out}")
    output_path(out, "--out")
    output_path(out.with_suffix(".csv"), "--out (its CSV)")
    constraints = {k: v for k, v in (("disk_margin_min", args.disk_margin_min),
                                     ("overshoot_max_pct", args.overshoot_max_pct)) if v is not None}
    console = Console(stderr=True, highlight=False)
    t0 = time.perf_counter()
    with Progress(TextColumn("tuning ({task.fields[method]})"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("subsets"), TextColumn("{task.fields[rate]}"), TimeElapsedColumn(),
                  console=console, transient=False) as bar:
        task = bar.add_task("tune", total=None, method=args.method, rate="")

        def progress(done: int, total: int) -> None:
            dt = time.perf_counter() - t0
            bar.update(task, completed=done, total=total,
                       rate=f"{done / dt:.1f}/s" if dt > 1 and done else "")

        try:
            table = tune_table(config, args.method, args.workers, out, args.resume,
                               constraints or None, on_progress=progress, subsets=subsets)
        except KeyboardInterrupt:
            console.print(f"interrupted: partial table kept at {out} (continue with --resume)")
            return 130
    csv_path = out.with_suffix(".csv")
    write_csv(table, csv_path)
    entries = list(table.entries.values())
    infeasible = [e for e in entries if not e.feasible]
    dt = time.perf_counter() - t0
    print(f"wrote {out} and {csv_path}: {len(entries)} subsets "
          f"({len(infeasible)} infeasible) in {dt:.1f} s, method {table.method}")
    for e in infeasible[:5]:
        print(f"  infeasible {','.join(e.ders)}: {e.reason}")
    if config.constraints.robust is not None:
        _print_robust(config, entries)
    if table.static is not None and table.static.feasible:
        s = table.static
        u = config.unit
        print(f"static controller: K_P {s.kp:.4g} 1/{u}, K_I {s.ki:.4g} 1/({u} s), worst rise time "
              f"{s.figures['worst_rise_time_s']:.3g} s ({','.join(s.figures['worst_rise_time_subset'])})")
        if "verified_random_subsets" in s.figures:
            n = s.figures["verified_random_subsets"]
            sample = f"all {n}" if n == 2 ** len(s.ders) - 1 else f"{n} random"
            f = s.figures
            how = (f"lowered {f['lowered_on_exact_plant']} time(s) along its ray to pass on "
                   f"the exact plant" if f.get("lowered_on_exact_plant")
                   else f"{f['design_subsets_added_from_sample']} of them joined the design")
            print(f"  designed on the selection and the extreme plants, verified on them and "
                  f"{sample} subsets ({f.get('verified_plants', n)} plants; {how})")
    return 0


def _print_robust(config, entries) -> None:
    """The uncertainty set and the worst members the certificates found."""
    r = config.constraints.robust
    types = ", ".join(f"{t} b {u.lag_scale[0]:g}-{u.lag_scale[1]:g}, dead time "
                      f"{u.delay_add_s[0]:+g} to {u.delay_add_s[1]:+g} s"
                      for t, u in ((t, r.of_type(t)) for t in dict.fromkeys(
                          d.type for d in config.ders)))
    print(f"certified over the uncertainty set: {', '.join(r.models)}; {types}")
    done = [e for e in entries if e.feasible and e.figures.get("robust_disk_margin") is not None]
    if not done:
        return
    dm = min(done, key=lambda e: e.figures["robust_disk_margin"])
    os_ = max(done, key=lambda e: e.figures["robust_overshoot_pct"])
    backed = sum(1 for e in done if (e.figures.get("gain_back_off") or 1.0) < 1.0)
    print(f"  lowest disk margin {dm.figures['robust_disk_margin']:.4g} "
          f"({','.join(dm.ders)}: {dm.figures['robust_disk_margin_at']}); highest overshoot "
          f"{os_.figures['robust_overshoot_pct']:.4g} % ({','.join(os_.ders)}: "
          f"{os_.figures['robust_overshoot_at']}); {backed} of {len(done)} entries backed off")
