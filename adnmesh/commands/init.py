"""``adnmesh init --simbench CODE | --pandapower NET.json -o OUT.yaml``: a complete, commented
config for a SimBench grid or a pandapower net — its actuators by rules, their dynamics from the documented default table, schedules and
a scenario sized to what they can deliver (docs/configuration.md#adnmesh-init)."""

from __future__ import annotations

import argparse
import math
import os
import re
import shlex
import sys
from pathlib import Path

from adnmesh.commands import comma_list, output_path
from adnmesh.errors import UsageError

__all__ = ["add_parser", "run", "parse_dynamics"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``init`` subparser."""
    from adnmesh.adn.dynamics import DEFAULT_DYNAMICS

    defaults = ", ".join(f"{t} {d:g}/{r:g} s" for t, (d, r, _) in DEFAULT_DYNAMICS.items())
    parser = subparsers.add_parser(
        "init",
        help="write a config for a SimBench grid or a pandapower net: actuators by rules, "
        "dynamics, a scenario",
        description="Write a complete, commented config for SimBench grid CODE or the pandapower "
        "net file NET.json at a study case (or a time step of its profiles). "
        "Actuators are the static generators that pass the rules (--actuators, --types, "
        "--min-size-w, or an explicit --sgens list); the others stay constant injections. "
        f"Dynamics (T_delay/T_rise) per DER type by default: {defaults} "
        "(docs/models.md#der-types); --dynamics and --der-dynamics override them. Each "
        "actuator is scheduled at half its study-case infeed; the scenario's steps are sized "
        "to the controllable range. Prints the ADN in a few lines. The file passes check, tune "
        "and up as written. Exit code 0 when written, 2 for a user error (unknown code or "
        "study case or time step, a file that is not a pandapower net, a net without an external grid, "
        "no generator matching the rules, an output that exists without --force).",
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--simbench", metavar="CODE",
                        help="SimBench code, e.g. 1-MV-semiurb--0-no_sw")
    source.add_argument("--pandapower", metavar="NET.json", type=Path,
                        help="a pandapower net file, as pandapower.to_json writes it (or "
                        "to_sqlite: .sqlite, .sqlite3, .db)")
    parser.add_argument("-o", "--out", metavar="FILE", required=True, type=Path,
                        help="the config to write (.yaml)")
    point = parser.add_mutually_exclusive_group()
    point.add_argument("--study-case",
                       help="study case giving the infeeds (default lW; a pandapower net "
                       "without study cases is used as saved)")
    point.add_argument("--time-step", metavar="N", type=_time_step,
                       help="instead: quarter hour N of the net's year of profiles (0 = 1 "
                       "January 00:00; SimBench: 0 to 35135)")
    parser.add_argument("--actuators", default="mv", metavar="mv|all",
                        help="mv (default): generators on >= 1 kV buses that are plants, not "
                        "SimBench's aggregated LV feeders (lv_RES); all: every generator")
    parser.add_argument("--types", metavar="T,..",
                        help="only these DER types (WT, CHP, PV, HYDRO, GEN)")
    parser.add_argument("--min-size-w", type=float, default=0.0, metavar="W",
                        help="only generators of at least this installed power, W")
    parser.add_argument("--sgens", metavar="NAME,..",
                        help="exactly these sgens (names as in the net), instead of --actuators")
    parser.add_argument("--dynamics", action="append", default=[], metavar="TYPE=DELAY,RISE",
                        help="T_delay and T_rise (s) of a DER type, e.g. HYDRO=0.5,12 "
                        "(repeatable)")
    parser.add_argument("--der-dynamics", action="append", default=[], metavar="ID=DELAY,RISE",
                        help="T_delay and T_rise (s) of one DER by its id in the written "
                        "config, e.g. WT1=0.02,0.6 (repeatable)")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    return parser


def parse_dynamics(items, known, option: str) -> dict[str, tuple[float, float]]:
    """``["KEY=DELAY,RISE", ...]`` -> ``{KEY: (delay_s, rise_s)}``; one-line errors."""
    out = {}
    for item in items:
        key, sep, values = item.partition("=")
        parts = values.split(",")
        if not sep or len(parts) != 2:
            raise UsageError(f"{option} {item!r}: expected KEY=DELAY,RISE (seconds)")
        if key not in known:
            raise UsageError(f"{option} {item!r}: unknown {key!r} (known: "
                             f"{', '.join(sorted(known)[:20])})")
        try:
            delay, rise = (float(p) for p in parts)
        except ValueError:
            raise UsageError(f"{option} {item!r}: DELAY and RISE must be numbers") from None
        if not (math.isfinite(delay) and math.isfinite(rise) and delay >= 0 and rise > 0):
            raise UsageError(f"{option} {item!r}: DELAY >= 0 and RISE > 0 (finite), s")
        out[key] = (delay, rise)
    return out


def _time_step(text: str) -> int:
    try:
        step = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a whole number >= 0, got {text!r}") from None
    if step < 0:
        raise argparse.ArgumentTypeError(f"a whole number >= 0, got {text!r}")
    return step


def _command_line(args: argparse.Namespace) -> str:
    """The command that writes this file again (``-o`` by the file's name: the line does not
    depend on where it was written)."""
    argv = ["--simbench", args.simbench] if args.simbench else \
        ["--pandapower", str(args.pandapower)]
    if args.study_case:
        argv += ["--study-case", args.study_case]
    if args.time_step is not None:
        argv += ["--time-step", str(args.time_step)]
    if args.sgens:
        argv += ["--sgens", args.sgens]
    elif args.actuators != "mv":
        argv += ["--actuators", args.actuators]
    if args.types:
        argv += ["--types", args.types]
    if args.min_size_w:
        argv += ["--min-size-w", f"{args.min_size_w:g}"]
    for item in args.dynamics:
        argv += ["--dynamics", item]
    for item in args.der_dynamics:
        argv += ["--der-dynamics", item]
    return "adnmesh init " + shlex.join([*argv, "-o", args.out.name])


def _schema_ref(out: Path) -> str | None:
    """``config.schema.json`` in the output's folder or the one above (``configs/`` of a
    checkout), relative to the output; None if neither has it."""
    folder = out.resolve().parent
    for candidate in (folder / "config.schema.json", folder.parent / "config.schema.json"):
        if candidate.is_file():
            return os.path.relpath(candidate, folder)
    return None


def run(args: argparse.Namespace) -> int:
    """Survey the net, apply the rules, write the config, print the ADN."""
    from adnmesh.adn.config_text import config_text
    from adnmesh.adn.dynamics import DEFAULT_DYNAMICS
    from adnmesh.adn.selection import select_actuators
    from adnmesh.adn.survey import survey_pandapower, survey_simbench
    from adnmesh.adn.template import ranges_w, scenario_template, schedule_w
    from adnmesh.errors import GridError
    from adnmesh.grid.simbench_net import case_words, time_step_case
    from adnmesh.tuning.problem import MAX_EXACT_CLASSES
    from adnmesh.tuning.subset_selection import MAX_ALL_DERS

    types = comma_list(args.types) if args.types else None
    if types is not None:
        unknown = [t for t in types if t not in DEFAULT_DYNAMICS]
        if unknown:
            raise UsageError(f"--types: unknown DER type {unknown[0]!r} (one of "
                             f"{', '.join(DEFAULT_DYNAMICS)})")
    by_type = parse_dynamics(args.dynamics, DEFAULT_DYNAMICS, "--dynamics")
    if not (math.isfinite(args.min_size_w) and args.min_size_w >= 0):
        raise UsageError(f"--min-size-w must be >= 0 W, got {args.min_size_w:g}")
    if args.out.exists() and not args.force:
        raise UsageError(f"{args.out} exists; --force overwrites it")
    output_path(args.out, "--out")
    what = f"SimBench {args.simbench}" if args.simbench else f"pandapower net {args.pandapower}"
    case = time_step_case(args.time_step) if args.time_step is not None else args.study_case
    print(f"adnmesh init: loading {what} (a few seconds)", file=sys.stderr)
    try:
        if args.simbench:
            survey = survey_simbench(args.simbench, case or "lW")
        else:
            survey = survey_pandapower(args.pandapower, case)
    except GridError as exc:
        raise UsageError(str(exc)) from None
    selection = select_actuators(survey.generators, args.actuators, types, args.min_size_w,
                                 comma_list(args.sgens) if args.sgens else None)
    counts: dict[str, int] = {}
    ids = []
    for act in selection.actuators:
        counts[act.der_type] = counts.get(act.der_type, 0) + 1
        ids.append(f"{act.der_type}{counts[act.der_type]}")
    per_der = parse_dynamics(args.der_dynamics, dict.fromkeys(ids), "--der-dynamics")
    dynamics = {}
    for der_id, act in zip(ids, selection.actuators):
        delay, rise, source = DEFAULT_DYNAMICS[act.der_type]
        if act.der_type in by_type:
            (delay, rise), source = by_type[act.der_type], "--dynamics"
        if der_id in per_der:
            (delay, rise), source = per_der[der_id], "--der-dynamics"
        dynamics[der_id] = (delay, rise, source)
    schedules = [schedule_w(a.generator.p_case_w) for a in selection.actuators]
    rows = [(i, a.der_type, a.generator.p_inst_w, a.generator.p_case_w, s)
            for i, a, s in zip(ids, selection.actuators, schedules)]
    planned = scenario_template(rows)
    rules = (f"{len(comma_list(args.sgens))} named sgens" if args.sgens else
             f"level {args.actuators}") + (f", types {','.join(types)}" if types else "") + \
        (f", at least {args.min_size_w:g} W" if args.min_size_w else "")
    command = _command_line(args)
    net_file = grid = None
    if args.pandapower:
        net_file = os.path.relpath(args.pandapower.resolve(), args.out.resolve().parent)
        grid = "net-" + (re.sub(r"[^A-Za-z0-9_-]+", "-", args.pandapower.stem).strip("-")
                         or "adn")
    text = config_text(survey, selection, dynamics, ids, schedules, planned, command, rules,
                       _schema_ref(args.out), net_file, grid)
    from adnmesh.files import write_atomic
    write_atomic(args.out, text)
    up, down = ranges_w((c, s) for *_, c, s in rows)
    by_kind = ", ".join(f"{n} {t}" for t, n in counts.items())
    print(f"{args.out}: {what}, {case_words(survey.case)}{survey.when}: {survey.buses} buses, "
          f"{len(survey.generators)} static generators")
    print(f"actuators ({rules}): {len(ids)} ({by_kind}), "
          f"{sum(a.generator.p_inst_w for a in selection.actuators) / 1e6:.3f} MW installed"
          + (f"; {len(selection.idle)} produce nothing at {survey.case}, left out"
             if selection.idle else ""))
    print(f"P_IP there: {survey.p_ip_w / 1e6:.3f} MW (positive into the upper grid); "
          f"controllable range at the schedules: +{up / 1e6:.3f} / -{down / 1e6:.3f} MW")
    steps = ", ".join(f"{d / 1e6:+g} MW at {t:g} s" for t, d in planned.steps)
    drop = (f"; the {planned.dropped_type}s unavailable at {planned.unavailable[0][0]:g} s"
            if planned.unavailable else "")
    print(f"scenario: {planned.duration_s:g} s, steps {steps}{drop}")
    if len(ids) > MAX_ALL_DERS:
        classes = len({dynamics[i][:2] for i in ids})
        print(f"large ADN: {len(ids)} actuators ({classes} dynamics classes"
              + (f", more than {MAX_EXACT_CLASSES}: the searches run on one design plant per "
                 "type" if classes > MAX_EXACT_CLASSES else "")
              + f"); tune and up take the scenario's subsets, the CPFC tunes any other on "
              "demand at run time")
    print(f"next: adnmesh check {args.out} && adnmesh up {args.out}")
    return 0
