"""``adnmesh study CONFIG``: what the ADN can deliver over a year of profiles (docs/study.md)."""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from rich.console import Console

from adnmesh.commands import add_config_argument, output_path
from adnmesh.errors import UsageError

__all__ = ["add_parser", "run", "interval_range", "parse_when", "TABLE_DERS", "OUTPUTS"]

#: without a table, every subset is tuned first up to this many DERs (4,095 subsets, seconds
#: with the global search); beyond, the subsets the year meets are tuned on demand
TABLE_DERS = 12


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``study`` subparser."""
    parser = subparsers.add_parser(
        "study",
        help="a year of profiles: range, speed, margins and limits per interval",
        description="Go through the grid's year of quarter-hour profiles (SimBench's): per "
        "interval each DER's available power and availability (config: study), the table "
        "entry of the available DERs and its figures, P_IP and Q_IP from the power flow, the "
        "extreme voltages and loadings and the directions the grid guard would block; the "
        "controllable range up and down and whether the service (study.service_w within "
        "study.service_s) is deliverable. Writes intervals.csv, ders.csv, summary.json and "
        "PNG figures to --out. Exit code 0 when they are written, 2 for a user error.",
    )
    add_config_argument(parser)
    parser.add_argument("--profiles", metavar="FILE",
                        help="your own time series of the net's generators and loads (CSV or "
                        "Parquet: a time column and one per series, docs/study.md); default: "
                        "the grid's own profiles (SimBench's year)")
    parser.add_argument("--start", help="first day or time (e.g. 2016-03-01); default: the "
                        "profiles' first interval")
    parser.add_argument("--end", help="day or time to stop before (exclusive); default: "
                        "after the last interval")
    parser.add_argument("--table", help="gain table (JSON); default: the config's "
                        "(tables/ beside it), tuned now for every subset if there is none")
    parser.add_argument("--service-mw", type=float,
                        help="service size both ways, MW (default: study.service_w)")
    parser.add_argument("--service-s", type=float,
                        help="within this settling time, s (default: study.service_s)")
    parser.add_argument("--out", help="folder of the results (default: logs/study-<config>)")
    parser.add_argument("--no-figures", action="store_true", help="write no PNG figures")
    parser.add_argument("--verify", type=int, metavar="N", default=0,
                        help="run the distributed system on the sim clock for the N most "
                        "demanding intervals with a step of the service size and compare "
                        "its step figures with the study's")
    return parser


def parse_when(text: str | None, option: str):
    """``--start`` / ``--end`` as datetime64[m] (None for None): a date ``2016-03-01`` or a
    time ``2016-03-01T12:00`` (or with a space) that exists, no time zone; one-line error
    otherwise."""
    from adnmesh.study.availability import parse_time

    if text is None:
        return None
    try:
        return parse_time(text)
    except ValueError:
        raise UsageError(f"{option} {text!r}: not a date or time (e.g. 2016-03-01 or "
                         "2016-03-01T12:00)") from None


def interval_range(times: np.ndarray, start: str | None, end: str | None) -> tuple[int, int]:
    """``(first, stop)`` indices of ``times`` in ``[start, end)``; one-line error for a bad
    date or an empty range."""
    first, stop = 0, len(times)
    if start is not None:
        first = int(np.searchsorted(times, parse_when(start, "--start"), side="left"))
    if end is not None:
        stop = int(np.searchsorted(times, parse_when(end, "--end"), side="left"))
    if stop <= first:
        raise UsageError(f"--start/--end: no interval of the profiles ({times[0]} to "
                         f"{times[-1]}) lies in [{start or times[0]}, {end or 'end'})")
    return first, stop


#: the files the study writes into --out
OUTPUTS = ("intervals.csv", "ders.csv", "summary.json", "duration.png", "heatmap_rise.png",
           "heatmap_range.png", "limits.png", "contribution.png")


def _not_an_output(profiles: str | None, out_dir: Path) -> None:
    """Refuse a ``--profiles`` file that the study would overwrite with its results."""
    if profiles is None:
        return
    given = Path(profiles).resolve()
    if any(given == (out_dir / name).resolve() for name in OUTPUTS):
        raise UsageError(f"--profiles {profiles}: is one of the files the study writes into "
                         f"--out {out_dir}; keep it elsewhere or choose another --out")


def _config(args):
    from adnmesh.config import load_config

    config = load_config(args.config)
    if config.grid_model is None:
        raise UsageError(f"{args.config}: the study needs a grid model (grid_model: with a "
                         "SimBench code) for its profiles")
    update = {}
    if args.service_mw is not None:
        if not 0 < args.service_mw <= 1e4:
            raise UsageError(f"--service-mw must be in (0, 10000], got {args.service_mw:g}")
        update["service_w"] = args.service_mw * 1e6
    if args.service_s is not None:
        if not 0 < args.service_s <= 3600:
            raise UsageError(f"--service-s must be in (0, 3600], got {args.service_s:g}")
        update["service_s"] = args.service_s
    if not 0 <= args.verify <= 20:
        raise UsageError(f"--verify must be 0 to 20, got {args.verify}")
    if update:
        config = config.model_copy(update={"study": config.study.model_copy(update=update)})
    return config


def _table(args, config, console):
    """The table the study looks subsets up in (see ``--table``) and its path."""
    from adnmesh.tuning.table import default_table_path, load_table

    if args.table:
        return load_table(args.table, config), Path(args.table)
    path = default_table_path(config)
    if path.exists():
        return load_table(path, config), path
    from adnmesh.tuning import tune_table
    if len(config.ders) > TABLE_DERS:
        console.print(f"no gain table at {path}: {len(config.ders)} DERs are too many for a "
                      "table of every subset; tuning the subsets the year meets on demand")
        return None, None
    output_path(path, "the gain table")
    console.print(f"no gain table at {path}: tuning every subset now (adnmesh tune)")
    return tune_table(config, "global", os.cpu_count() or 1, path), path


def _year(config, profile_file: str | None):
    """``(profiles, grid data, grid name)``: SimBench's year of the config's grid (cached),
    or a user's time series (``--profiles``) of the config's net at its operating point; a
    pandapower net file without ``--profiles`` uses the profiles it carries (a SimBench net
    saved to a file), if any."""
    from adnmesh.control.operating_point import grid_source
    from adnmesh.grid.cache import load_grid, load_net_grid
    from adnmesh.grid.profiles import load_profiles, profiles_of_net, profiles_of_table

    source, name, case = grid_source(config)
    load_model = config.grid_model.load_model
    if source == "simbench" and profile_file is None:
        return (load_profiles(name, load_model), load_grid(name, "time step 0", load_model),
                name)
    if profile_file is not None:                  # the file's problems first: no net loaded
        from adnmesh.grid.profile_file import read_profile_table
        times, series = read_profile_table(profile_file)
    if source == "simbench":
        from adnmesh.grid.simbench_net import apply_operating_point, load_simbench_net
        net = load_simbench_net(name)
        apply_operating_point(net, case)
        data = load_grid(name, case, load_model)
    else:
        from adnmesh.grid.net_file import net_at_case, read_net
        net, _ = read_net(name)
        used = net_at_case(net, case, "power")      # loads as they are; the model turns them
        data = load_net_grid(name, case, load_model)
        name = f"{Path(name).name} ({used})"
    if profile_file is not None:
        return profiles_of_table(net, times, series, load_model), data, name
    from adnmesh.grid.simbench_net import time_steps
    if not time_steps(net):
        raise UsageError(f"{config.path}: the net {name} carries no profiles: give its time "
                         "series with --profiles FILE (CSV or Parquet; docs/study.md)")
    return profiles_of_net(net, load_model), data, name


def run(args: argparse.Namespace) -> int:
    """Study the year, write the files, print the headline figures."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, \
        TimeElapsedColumn

    from adnmesh.control.operating_point import available_power_w
    from adnmesh.study.figures import write_figures
    from adnmesh.study.outputs import summary, write_ders, write_intervals, write_summary
    from adnmesh.study.year import study_year

    parse_when(args.start, "--start")             # the command line's problems first
    parse_when(args.end, "--end")
    config = _config(args)
    out_dir = output_path(Path(args.out) if args.out else
                          Path("logs") / f"study-{Path(config.path).stem}", "--out",
                          directory=True)
    _not_an_output(args.profiles, out_dir)
    if args.verify:
        output_path(out_dir / "verify", "--out (its verify folder)", directory=True)
    console = Console(stderr=True, highlight=False)
    load_model = config.grid_model.load_model
    t0 = time.perf_counter()
    profiles, data, code = _year(config, args.profiles)   # a bad profile file: before a table
    first, stop = interval_range(profiles.times, args.start, args.end)
    profiles = profiles.window(first, stop)
    table, table_path = _table(args, config, console)
    if args.verify and table_path is None:        # before the study writes anything
        raise UsageError("--verify: needs a gain table (--table; a config of more than "
                         f"{TABLE_DERS} DERs has none of its own)")
    power = available_power_w(config)
    p_op = np.array([power[d] for d in config.der_ids()], dtype=float)
    t1 = time.perf_counter()
    with Progress(TextColumn("studying"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("intervals"), TimeElapsedColumn(), console=console,
                  transient=False) as bar:
        task = bar.add_task("study", total=len(profiles))
        result = study_year(config, profiles, data, p_op, table, first,
                            lambda done, total: bar.update(task, completed=done))
    t2 = time.perf_counter()
    files = [write_intervals(result, out_dir / "intervals.csv"),
             write_ders(result, out_dir / "ders.csv")]
    if not args.no_figures:
        files += write_figures(result, config, out_dir)
    figures = summary(result, config, {"config": str(config.path), "grid": code,
                                       "load_model": load_model,
                                       "seconds": {"setup": round(t1 - t0, 3),
                                                   "study": round(t2 - t1, 3)}})
    files.append(write_summary(figures, out_dir / "summary.json"))
    if args.verify:                              # the summary again, with the runs' figures
        from adnmesh.study.verify import verify
        figures["verify"] = verify(config, result, args.verify, out_dir, table_path, console)
        write_summary(figures, out_dir / "summary.json")
    _print(figures, config, files, console)
    return 0


def _num(value) -> str:
    return "—" if value is None or value != value else f"{value:.3g}"


def _print(s: dict, config, files, console) -> None:
    out = Console(highlight=False, markup=False, soft_wrap=True)
    svc = s["service"]
    up, down = s["linear_up_mw"], s["linear_down_mw"]
    out.print(f"{s['intervals']} intervals ({s['first']} to {s['last']}) of {s['grid']} in "
              f"{s['seconds']['study']:.1f} s (+{s['seconds']['setup']:.1f} s setup); "
              f"{s['subsets']} subsets, {s['tuned_on_demand']} tuned on demand")
    out.print(f"service ±{svc['size_mw']:g} MW within {svc['within_s']:g} s: deliverable in "
              f"{svc['share'] * 100:.1f} % of the intervals (up {svc['share_up'] * 100:.1f} %, "
              f"down {svc['share_down'] * 100:.1f} %)")
    if up and down:
        out.print(f"linear range up   MW p5/p50/p95: {up['p5']:.3f} / {up['p50']:.3f} / "
                  f"{up['p95']:.3f}")
        out.print(f"linear range down MW p5/p50/p95: {down['p5']:.3f} / {down['p50']:.3f} / "
                  f"{down['p95']:.3f}")
    if s["rise_s"]:
        out.print(f"rise time s p5/p50/p95: {s['rise_s']['p5']:.3g} / {s['rise_s']['p50']:.3g} "
                  f"/ {s['rise_s']['p95']:.3g}")
    out.print(f"grid: limited (guard acts) in {s['limited_share'] * 100:.2f} %, a limit "
              f"violated in {s['violated_share'] * 100:.2f} % of the intervals"
              + (f"; {s['not_converged']} power flows did not converge"
                 if s["not_converged"] else ""))
    if "verify" in s:
        for row in s["verify"]["rows"]:
            out.print(f"verify {row['time']} ({row['available']}): rise / settling / "
                      f"overshoot predicted {_num(row['predicted_rise_s'])} s / "
                      f"{_num(row['predicted_settling_s'])} s / "
                      f"{_num(row['predicted_overshoot_pct'])} %, measured "
                      f"{_num(row['measured_rise_s'])} s / {_num(row['measured_settling_s'])} s"
                      f" / {_num(row['measured_overshoot_pct'])} %")
    out.print(f"wrote {len(files)} files to {Path(files[0]).parent}")
    sys.stdout.flush()
