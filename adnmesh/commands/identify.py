"""``adnmesh identify CONFIG RUN.mcap | --csv FILE``: each DER's reaction and rise time fitted
from its set-point and measured infeed (:mod:`adnmesh.identify.model_fit`)."""

from __future__ import annotations

import argparse
import csv
import json
import os
from contextlib import contextmanager
from pathlib import Path

from adnmesh.commands import add_config_argument, input_file, output_path
from adnmesh.errors import UsageError

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``identify`` subparser."""
    parser = subparsers.add_parser(
        "identify",
        help="fit each DER's reaction and rise time from a recording or a CSV",
        description="Fit each DER's model (a dead time, then the reference first-order lag, "
        "or the analyses' pt2 or rhpz) to its set-point and measured infeed: from a recording "
        "of CONFIG (the DERs' state messages) or from a CSV a SCADA exports (--csv with --time, "
        "--setpoint, --measured and --der). Prints T_delay and T_rise = T ln 9 with 95 %% "
        "intervals and the fit's RMSE and R², writes a config that extends CONFIG with the "
        "fitted reference model (-o) and a figure of the data against each fit (--plot). Exit "
        "code 0 when every DER asked for was fitted, 2 for a user error (no such file, a column "
        "or DER that is not there, nothing to fit).",
    )
    add_config_argument(parser)
    parser.add_argument("recording", metavar="RUN", nargs="?",
                        help="recording (.mcap) of a run of CONFIG")
    parser.add_argument("--der", metavar="ID[,ID...]",
                        help="the DERs to fit (default: every DER of CONFIG in the recording; "
                        "with --csv: the one DER the file is of)")
    parser.add_argument("--model", choices=("pt1", "pt2", "rhpz", "all"), default="pt1",
                        help="the model fitted: pt1 (the reference model, default), pt2, rhpz "
                        "(docs/method.md#model-uncertainty) or all three, side by side")
    parser.add_argument("--from", dest="start_s", type=float, metavar="S",
                        help="fit from this time on, s of the run (default: its start)")
    parser.add_argument("--to", dest="stop_s", type=float, metavar="S",
                        help="fit up to this time, s of the run (default: its end)")
    parser.add_argument("--steps", metavar="auto|S,S,...",
                        help="also fit each window from one step to the next apart and say "
                        "whether the DER's set-point went up or down in it: auto (the "
                        "recording's P_ref steps) or the times, s")
    parser.add_argument("--csv", metavar="FILE", help="read time, set-point and measured "
                        "power from this CSV instead of a recording")
    parser.add_argument("--time", metavar="COL", help="--csv: the column of the time, s")
    parser.add_argument("--setpoint", metavar="COL", help="--csv: the set-point column, W")
    parser.add_argument("--measured", metavar="COL", help="--csv: the measured power column, W")
    parser.add_argument("-o", "--out", metavar="CONFIG2", type=Path,
                        help="write a config extending CONFIG with the fitted t_delay_s and "
                        "t_rise_s")
    parser.add_argument("--robust-out", metavar="CONFIG2", type=Path,
                        help="write a config extending CONFIG with the uncertainty set the "
                        "fits imply (constraints.robust: per DER type, the time-constant "
                        "factor and added dead time covering the configured model and every "
                        "fit's 95 %% interval, --steps windows included), for tune")
    parser.add_argument("--plot", metavar="FIG", type=Path,
                        help="write the data and each fit as a figure (png, pdf, svg, ...)")
    return parser


def run(args: argparse.Namespace) -> int:
    """Fit, print, write what was asked for."""
    from adnmesh.config import load_config
    from adnmesh.identify.model_fit import MODELS, fit_model
    from adnmesh.identify.resample import on_grid, sample_period

    config = load_config(args.config)
    known = [d.id for d in config.ders]
    wanted = None if args.der is None else [d.strip() for d in args.der.split(",") if d.strip()]
    for der in wanted or []:
        if der not in known:
            raise UsageError(f"--der {der}: not a DER of {args.config} "
                             f"(its DERs: {', '.join(known)})")
    for path, flag in ((args.out, "-o"), (args.plot, "--plot"),
                       (args.robust_out, "--robust-out")):
        if path is not None:
            output_path(path, flag)
    if args.plot is not None:
        _check_format(args.plot)
    if args.out is not None and args.model != "pt1":
        raise UsageError("-o writes the reference model (t_delay_s, t_rise_s): it needs "
                         "--model pt1")
    if (args.csv is None) == (args.recording is None):
        raise UsageError("give a recording RUN or --csv FILE (one of them)")
    if args.csv is not None and args.steps == "auto":
        raise UsageError("--steps auto takes the P_ref steps of a recording: with --csv, give "
                         "the step times (--steps S,S,...)")
    steps = None if args.steps in (None, "auto") else _times(args.steps)
    if args.csv:
        series = _from_csv(args, wanted)
    else:
        series, p_ref_steps = _from_recording(args, wanted, known)
        steps = p_ref_steps if args.steps == "auto" else steps
    models = MODELS if args.model == "all" else (args.model,)
    fits, grids, skipped = {}, {}, []
    with _progress(len(series) * len(models)) as advance:
        for der, (ts, u, tm, y) in series.items():
            try:
                period = sample_period(tm)
                t, held, measured = on_grid(ts, u, tm, y, period, args.start_s, args.stop_s)
                fits[der] = []
                for model in models:
                    fits[der].append(fit_model(period, held, measured, model))
                    advance(f"{der} {model}")
            except ValueError as exc:
                if wanted is not None:
                    raise UsageError(f"{der}: {exc}") from None
                skipped.append(f"{der} ({exc})")
                fits.pop(der, None)
                continue
            grids[der] = (t, held, measured, period)
    if not fits:
        raise UsageError(f"no DER could be fitted: {'; '.join(skipped)}")
    _print(fits, config)
    print(_implied(fits, config))
    if skipped:
        print(f"not fitted: {'; '.join(skipped)}")
    windows = _by_step(grids, steps, models) if steps is not None else []
    if steps is not None:
        _print_steps(windows)
    if args.out is not None:
        args.out.write_text(_overlay(config, fits, args.out))
        print(f"{args.out}: written (extends {args.config})")
    if args.robust_out is not None:
        found = [(der, fit) for der, each in fits.items() for fit in each]
        found += [(der, fit) for der, _, _, _, each in windows for fit in each]
        args.robust_out.write_text(_robust_overlay(config, found, args.robust_out))
        print(f"{args.robust_out}: written (extends {args.config} with the uncertainty set; "
              f"tune it, then up)")
    if args.plot is not None:
        _plot(fits, grids, args.plot)
        print(f"{args.plot}: written")
    return 0


@contextmanager
def _progress(total: int):
    """A bar on stderr while the fits run (gone when they are done); yields ``advance(what)``."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    with Progress(TextColumn("fitting"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[what]}"), console=Console(stderr=True),
                  transient=True) as bar:
        task = bar.add_task("fit", total=total, what="")
        yield lambda what: bar.update(task, advance=1, what=what)


def _times(text: str) -> list[float]:
    try:
        times = sorted(float(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise UsageError(f"--steps {text!r}: auto or times in s, e.g. 20,100") from None
    if not times:
        raise UsageError(f"--steps {text!r}: no time given")
    return times


def _by_step(grids: dict, steps: list[float], models) -> list[tuple]:
    """``(der, start, stop, up/down, fits)`` for each window from a step to the next (the
    last to the end) in which the DER's set-point moved. A window begins with the last sample
    before its step, where each fit starts at rest."""
    import numpy as np

    from adnmesh.identify.model_fit import fit_model
    rows = []
    for der, (t, held, measured, period) in grids.items():
        inside = [s for s in steps if t[0] < s <= t[-1]]
        first = [int(np.searchsorted(t, s - 1e-6 * period)) - 1 for s in inside] + [len(t)]
        for start, i0, i1 in zip(inside, first, first[1:]):
            u, y = held[i0:i1], measured[i0:i1]
            try:
                found = [fit_model(period, u, y, model) for model in models]
            except ValueError:
                continue                                 # it did not move in this window
            direction = "up" if u[-1] >= u[0] else "down"
            rows.append((der, start, float(t[i1 - 1]), direction, found))
    return rows


def _print_steps(rows: list[tuple]) -> None:
    from rich.table import Table
    table = Table(title="each window from a step to the next (the model starts at rest there)")
    for name in ("DER", "window [s]", "set-point", "model", "T_delay [s]", "T_rise [s]",
                 "RMSE [kW]", "R²"):
        table.add_column(name, justify="left" if name in ("DER", "set-point", "model")
                         else "right")
    for der, start, stop, direction, found in rows:
        for fit in found:
            table.add_row(der, f"{start:g}-{stop:g}", direction, fit.model,
                          f"{fit.delay_s:.4g}", f"{fit.rise_s:.4g}", f"{fit.rmse_w / 1e3:.3g}",
                          f"{fit.r2:.5f}")
    _console().print(table)


def _implied(fits: dict, config) -> str:
    """The uncertainty the fits imply against the config, as the analyses take it: the factor
    ``b`` of each DER's lag (fitted T_rise over the configured) and the dead times' shift; of
    the reference model if it was fitted, else of the first model."""
    given = {d.id: d for d in config.ders}
    models = [f.model for f in next(iter(fits.values()))]
    model = "pt1" if "pt1" in models else models[0]
    chosen = {der: next(f for f in found if f.model == model) for der, found in fits.items()}
    b = {der: fit.rise_s / given[der].t_rise_s for der, fit in chosen.items()}
    shift = {der: fit.delay_s - given[der].t_delay_s for der, fit in chosen.items()}
    low, high = min(b, key=b.get), max(b, key=b.get)
    early, late = min(shift, key=shift.get), max(shift, key=shift.get)
    return (f"implied uncertainty ({model}): b = fitted T_rise / configured from "
            f"{b[low]:.3g} ({low}) to {b[high]:.3g} ({high}); dead time "
            f"{shift[early]:+.3g} s ({early}) to {shift[late]:+.3g} s ({late}) from the "
            f"configured (analyze: docs/method.md#model-uncertainty)")


def _console():
    """A console as wide as the terminal, at least 100 columns (120 when not a terminal)."""
    from rich.console import Console
    return Console(width=max(100, os.get_terminal_size(1).columns if os.isatty(1) else 120))


def _check_format(path: Path) -> None:
    from matplotlib.figure import Figure
    formats = Figure().canvas.get_supported_filetypes()
    if path.suffix.lstrip(".").lower() not in formats:
        raise UsageError(f"--plot {path}: unknown figure format {path.suffix or '(none)'!r}")


def _from_recording(args, wanted, known) -> dict:
    """``({der: (set-point t, set-point, infeed t, infeed)}, P_ref step times)`` from the
    recording, s and W."""
    from adnmesh.results.series import read_run
    found, _ = read_run(input_file(args.recording))
    run = found.run
    out: dict = {}
    for role, slot in (("der_setpoint", 0), ("der_infeed", 1)):
        for s in run.by_role(role):
            if s.der in known and (wanted is None or s.der in wanted):
                out.setdefault(s.der, [None, None])[slot] = (run.seconds(s.t_ns), s.values)
    p_ref = run.one("p_ref")
    steps = [] if p_ref is None else [float(run.seconds(t)) for t, change in
                                      zip(p_ref.t_ns[1:], p_ref.values[1:] != p_ref.values[:-1])
                                      if change]
    missing = [d for d in (wanted or []) if d not in out or None in out[d]]
    if missing:
        raise UsageError(f"{args.recording}: no set-point and infeed of {', '.join(missing)}")
    series = {d: (*v[0], *v[1]) for d, v in out.items() if None not in v}
    if not series:
        raise UsageError(f"{args.recording}: no DER of {args.config} with a set-point and an "
                         f"infeed in it")
    return dict(sorted(series.items(), key=lambda item: known.index(item[0]))), steps


def _from_csv(args, wanted) -> dict:
    """``{der: (t, set-point, t, measured)}`` from the CSV, s and W."""
    import numpy as np
    if wanted is None or len(wanted) != 1:
        raise UsageError("--csv needs --der with the one DER the file is of")
    columns = {"--time": args.time, "--setpoint": args.setpoint, "--measured": args.measured}
    for flag, name in columns.items():
        if not name:
            raise UsageError(f"--csv needs {flag} COL")
    path = input_file(args.csv)
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            rows = list(csv.DictReader(handle))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise UsageError(f"--csv {args.csv}: cannot read it: {exc}") from None
    header = list(rows[0]) if rows else []
    values = {}
    for flag, name in columns.items():
        if name not in header:
            raise UsageError(f"--csv {args.csv}: no column {name!r} ({flag}; its columns: "
                             f"{', '.join(header) or 'none'})")
        try:
            values[flag] = np.array([float(row[name]) for row in rows])
        except (TypeError, ValueError):
            bad = next(i for i, row in enumerate(rows) if not _is_number(row[name]))
            raise UsageError(f"--csv {args.csv}: row {bad + 2}, column {name!r}: "
                             f"{rows[bad][name]!r} is not a number") from None
    t = values["--time"]
    return {wanted[0]: (t, values["--setpoint"], t, values["--measured"])}


def _is_number(text) -> bool:
    try:
        float(text)
    except (TypeError, ValueError):
        return False
    return True


def _print(fits: dict, config) -> None:
    from rich.table import Table
    given = {d.id: d for d in config.ders}
    table = Table(title="the models fitted (95 % intervals from the fit's Jacobian)")
    for name in ("DER", "model", "T_delay [s]", "T_rise = T ln 9 [s]",
                 "config: T_delay / T_rise [s]", "RMSE [kW]", "R²", "samples"):
        table.add_column(name, justify="left" if name in ("DER", "model") else "right")
    for der, found in fits.items():
        for fit in found:
            table.add_row(der, fit.model,
                          f"{fit.delay_s:.4g} ({fit.delay_ci_s[0]:.4g}-{fit.delay_ci_s[1]:.4g})",
                          f"{fit.rise_s:.4g} ({fit.rise_ci_s[0]:.4g}-{fit.rise_ci_s[1]:.4g})",
                          f"{given[der].t_delay_s:g} / {given[der].t_rise_s:g}",
                          f"{fit.rmse_w / 1e3:.3g}", f"{fit.r2:.5f}", str(fit.samples))
    _console().print(table)


def _overlay(config, fits: dict, out: Path) -> str:
    """A config extending ``config`` with the fitted values (every DER, the list is replaced)."""
    base = os.path.relpath(Path(config.path).resolve(), out.resolve().parent)
    lines = [f"# adnmesh identify: the reference model fitted to {len(fits)} DER(s) "
             f"({', '.join(fits)}); the others as in {Path(config.path).name}",
             f"extends: {json.dumps(base)}", "ders:"]
    for der in config.ders:
        entry = der.model_dump(mode="json", exclude_defaults=True)
        if der.id in fits:
            fit = fits[der.id][0]
            entry["t_delay_s"] = float(f"{fit.delay_s:.6g}")
            entry["t_rise_s"] = float(f"{max(fit.rise_s, 1e-6):.6g}")
        lines.append(f"  - {json.dumps(entry)}")
    return "\n".join(lines) + "\n"


def _robust_overlay(config, found: list, out: Path) -> str:
    """A config extending ``config`` with ``constraints.robust`` covering ``found``."""
    from adnmesh.identify.implied_set import implied_set
    base = os.path.relpath(Path(config.path).resolve(), out.resolve().parent)
    robust = implied_set(config, found)
    lines = [f"# adnmesh identify: the uncertainty set {len(found)} fit(s) imply (the configured "
             f"model and every fit's 95 % interval); the DERs as in {Path(config.path).name}",
             f"extends: {json.dumps(base)}", "constraints:", "  robust:",
             f"    models: {json.dumps(robust['models'])}", "    types:"]
    for t, box in robust["types"].items():
        lines.append(f"      {t}: {json.dumps(box)}")
    return "\n".join(lines) + "\n"


def _plot(fits: dict, grids: dict, path: Path) -> None:
    from matplotlib.figure import Figure
    rows = len(fits)
    figure = Figure(figsize=(10, 2.4 * rows), layout="constrained")
    axes = figure.subplots(rows, 1, squeeze=False)[:, 0]
    for ax, (der, found) in zip(axes, fits.items()):
        t, held, measured, period = grids[der]
        ax.plot(t, held / 1e6, drawstyle="steps-post", color="0.6", lw=1, label="set-point")
        ax.plot(t, measured / 1e6, color="C0", lw=1.2, label="measured")
        for i, fit in enumerate(found):
            ax.plot(t, fit.response(period, held, float(measured[0])) / 1e6, color=f"C{3 + i}",
                    lw=1, ls="--", label=f"{fit.model}: T_delay {fit.delay_s:.3g} s, "
                    f"T_rise {fit.rise_s:.3g} s, R² {fit.r2:.4f}")
        ax.set_ylabel(f"{der} [MW]")
        ax.legend(loc="best", fontsize=8)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    figure.savefig(path, dpi=110)
