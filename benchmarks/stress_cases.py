"""Stress cases: which SimBench MV operating points let the DERs drive the grid out of its band.

For every SimBench MV grid asked for (default the four of ``configs/grids/`` at SimBench
scenarios 0, 1 and 2: ``1-MV-rural--0-no_sw`` ... ``1-MV-comm--2-no_sw``), every study case
(hL, n1, hW, hPV, lW, lPV) and a few quarter hours of the year (``--time-steps``), this takes
the actuators ``adnmesh init`` would pick there (its own rules, :mod:`adnmesh.adn.selection`:
the MV plants, for 1-MV-urban every generator of at least 100 kW, as ``configs/grids/`` does)
at their schedules (half their infeed there, as init writes them) and moves them

- all up to their available power (their infeed there) and all down to 0;
- along P_Y as the CPFC would with unit weights (each DER ``p_sched + P_Y * P_inst``, clipped
  to ``[0, P_avail]``), to find the smallest change of P_IP from the schedules that leaves the
  band ``--v-min``/``--v-max``/``--loading-max`` (default the config's 0.9 / 1.1 p.u., 100 %),
  up (more export) and down;
- one at a time from schedule to available, to say which DERs move the critical element most.

Every power flow is the repo's own (:func:`adnmesh.grid.load_grid`, the disk cache, and
:class:`adnmesh.grid.GridSolver`), the same model ``adnmesh up``'s measurement solves at every
sample: loads as constant impedances, every other generator a constant injection, the DERs'
reactive power at its operating-point value. simbench is read once per grid for names, the
actuator rules and the profiles (the time steps); pandapower's ``runpp`` only runs with
``--validate``.

Output, one row per grid and operating point (stdout; progress on stderr):

- ``P_IP 0/sch/av``: P_IP (MV -> HV positive) with the actuators at 0, at the schedules, at
  their available power, MW;
- ``v_max sch>av @bus``: highest bus voltage at the schedules and at available power, and its
  bus at available power; ``v_min @bus``: the lowest voltage over the three points and its bus;
- ``load sch>av @branch``: highest line or transformer loading at the schedules and at available
  power, and the branch at available power (the worst of the three points if that is elsewhere);
- ``out``: which limits are broken at 0 / schedules / available (``V+`` above v_max, ``V-``
  below v_min, ``L`` loading; ``-`` none);
- ``dP up``/``dP dn``: for each limit broken on the way, the change of P_IP from the schedules
  along P_Y at which it first is (``V+ +4.64 L +5.98``: MW), ``in`` if none is within the DERs'
  range, ``OUT`` if the schedules already are outside;
- ``key DERs``: for the element closest to (or furthest beyond) its limit at available power,
  the three DERs that move it most alone from schedule to available, with that change (mpu:
  1e-3 p.u.; %: loading points), by the ids ``adnmesh init`` gives them (listed below the
  table).

Time steps (``--time-steps``): ``auto`` takes, per grid, the quarter hour of the year with the
largest surplus of generation over load and the one at 11:00-13:00 with the largest surplus
(the year's noon peak of PV export); a list of numbers takes those. At a time step the slack
voltage stays as the net saves it (SimBench: 1.025 p.u.), while study cases set their own
(1.015 at lW/lPV, 1.035 at the others). The first run builds the grid cache of each grid and
operating point (about 4 s each; 72 study-case builds for the default grids, plus the time
steps); later runs read it in milliseconds.

``--validate CODE@POINT`` solves the first out-of-band point of that grid (the ``dP up``
point, else the available power) with pandapower's ``runpp`` on the SimBench net built
independently (simbench, the study case or time step, loads as constant impedances) and prints
the largest voltage and loading differences from the solver.

    .venv/bin/python benchmarks/stress_cases.py                      # 4 grids x scenarios 0-2
    .venv/bin/python benchmarks/stress_cases.py --grids rural --scenarios 1 --time-steps none
    .venv/bin/python benchmarks/stress_cases.py --grids rural --scenarios 1 --cases lW \\
        --time-steps none --validate 1-MV-rural--1-no_sw@lW
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

GRIDS = ("rural", "semiurb", "urban", "comm")
CASES = ("hL", "n1", "hW", "hPV", "lW", "lPV")
#: init's rules per grid, as configs/grids/ was written (level, min size W)
RULES = {"urban": ("all", 1e5)}
NOON = ("11:00", "11:15", "11:30", "11:45", "12:00", "12:15", "12:30", "12:45", "13:00")


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


@dataclass
class Net:
    """What the scan needs of a SimBench net besides the solver's cache: names, installed
    powers and profiles."""

    code: str
    bus_names: list
    line_names: list
    trafo_names: list
    sgen_p_inst_w: dict
    sgen_profile: dict
    sgen_bus_kv: dict
    times: list
    surplus_mw: np.ndarray          # generation - load per time step, MW


def read_net(code: str) -> Net:
    """The SimBench net's names, installed powers and profile surplus (simbench, once)."""
    import simbench

    net = simbench.get_simbench_net(code)
    values = simbench.get_absolute_values(net, profiles_instead_of_study_cases=True)
    gen = values[("sgen", "p_mw")].to_numpy(dtype=float).sum(axis=1)
    load = values[("load", "p_mw")].to_numpy(dtype=float).sum(axis=1)
    times = net.profiles["load"]["time"].astype(str).tolist()
    kv = net.bus.vn_kv
    return Net(code=code, bus_names=net.bus.name.astype(str).tolist(),
               line_names=net.line.name.astype(str).tolist(),
               trafo_names=net.trafo.name.astype(str).tolist(),
               sgen_p_inst_w={str(n): float(p) * 1e6 for n, p in zip(net.sgen.name, net.sgen.p_mw)},
               sgen_profile={str(n): str(p) for n, p in zip(net.sgen.name, net.sgen.profile)},
               sgen_bus_kv={str(n): float(kv.at[b]) for n, b in zip(net.sgen.name, net.sgen.bus)},
               times=times, surplus_mw=gen - load)


def auto_time_steps(net: Net) -> list[int]:
    """The year's largest surplus, and the largest at noon (11:00-13:00)."""
    steps = [int(np.argmax(net.surplus_mw))]
    noon = np.array([t[-5:] in NOON for t in net.times])
    if noon.any():
        masked = np.where(noon, net.surplus_mw, -np.inf)
        steps.append(int(np.argmax(masked)))
    return sorted(set(steps))


@dataclass
class Point:
    """One power flow: P_IP and the arrays of voltages and loadings."""

    p_ip_w: float
    vm: np.ndarray
    line: np.ndarray
    trafo: np.ndarray

    def broken(self, lim) -> str:
        out = ""
        if self.vm.max() > lim.v_max:
            out += "V+"
        if self.vm.min() < lim.v_min:
            out += "V-"
        if max(_top(self.line), _top(self.trafo)) > lim.loading_max:
            out += "L"
        return out


def _top(a: np.ndarray) -> float:
    return float(a.max()) if a.size else -math.inf


@dataclass
class Limits:
    v_min: float = 0.9
    v_max: float = 1.1
    loading_max: float = 100.0


@dataclass
class Row:
    code: str
    point: str
    when: str
    actuators: list
    ids: list
    p_inst_w: np.ndarray
    avail_w: np.ndarray
    sched_w: np.ndarray
    at: dict = field(default_factory=dict)             # "0" / "sched" / "avail" -> Point
    d_up: dict = field(default_factory=dict)           # limit -> (dP_IP W, powers W)
    d_dn: dict = field(default_factory=dict)
    critical: str = ""
    key: list = field(default_factory=list)


def actuators(data, net: Net, grid: str):
    """init's actuators of this operating point: (sgen names, init's ids, P_inst W,
    available W)."""
    from adnmesh.adn.selection import select_actuators
    from adnmesh.adn.survey import Generator
    from adnmesh.errors import UsageError

    level, min_size = RULES.get(grid, ("mv", 0.0))
    generators = [Generator(name=n, bus=0, vn_kv=net.sgen_bus_kv[n], kind=t,
                            profile=net.sgen_profile.get(n, ""), p_inst_w=net.sgen_p_inst_w[n],
                            p_case_w=float(p) * 1e6)
                  for n, t, p in zip(data.sgen_names, data.sgen_types, data.sgen_p_mw)]
    try:
        chosen = select_actuators(generators, level, None, min_size).actuators
    except UsageError:
        return [], [], np.zeros(0), np.zeros(0)
    names = [a.generator.name for a in chosen]
    counts: dict[str, int] = {}
    ids = []
    for a in chosen:                                # init's ids: WT1, WT2, CHP1, ...
        counts[a.der_type] = counts.get(a.der_type, 0) + 1
        ids.append(f"{a.der_type}{counts[a.der_type]}")
    return (names, ids,
            np.array([a.generator.p_inst_w for a in chosen]),
            np.array([a.generator.p_case_w for a in chosen]))


def solve(solver, p_w) -> Point:
    sample = solver.solve(p_w)
    if not sample.converged:
        raise RuntimeError("power flow did not converge")
    return Point(sample.p_ip_w, solver.bus_vm_pu(), solver.line_loading_pct(),
                 solver.trafo_loading_pct())


def along(row: Row, p_y: float) -> np.ndarray:
    """The DERs' powers at P_Y with unit weights, clipped to [0, available], W."""
    return np.clip(row.sched_w + p_y * row.p_inst_w, 0.0, row.avail_w)


def first_out(solver, row: Row, lim: Limits, sign: int, n: int = 40):
    """Along P_Y in direction ``sign`` from the schedules, for each limit that is broken on
    the way (``V+``, ``V-``, ``L``), the change of P_IP at which it first is, W, and the DERs'
    powers there: ``{"V+": (dP_IP, p), ...}``; ``{"OUT": ...}`` if the schedules already are
    outside the band."""
    base = row.at["sched"]
    if base.broken(lim):
        return {"OUT": (0.0, row.sched_w)}
    # the P_Y at which every DER is at its end of the range in this direction
    with np.errstate(divide="ignore", invalid="ignore"):
        ends = (row.avail_w - row.sched_w) / row.p_inst_w if sign > 0 else \
            row.sched_w / row.p_inst_w
    reach = float(np.nanmax(ends)) if ends.size else 0.0
    found: dict = {}
    if reach <= 0:
        return found
    inside = 0.0
    for y in np.linspace(0.0, reach, n + 1)[1:]:
        broken = solve(solver, along(row, sign * y)).broken(lim)
        for kind in ("V+", "V-", "L"):
            if kind in broken and kind not in found:
                lo, hi = inside, y
                for _ in range(30):                 # bisection to ~1e-9 of the range
                    mid = 0.5 * (lo + hi)
                    if kind in solve(solver, along(row, sign * mid)).broken(lim):
                        hi = mid
                    else:
                        lo = mid
                p = along(row, sign * hi)
                found[kind] = (solve(solver, p).p_ip_w - base.p_ip_w, p)
        inside = y
    return found


def key_ders(solver, row: Row, net: Net, lim: Limits, top: int = 3):
    """The element nearest to (or furthest beyond) its limit at available power, and the DERs
    that move it most alone from schedule to available."""
    av = row.at["avail"]
    zero = row.at["0"]
    # headroom used, as a share: voltage rise over the band's upper half, loading over its max
    use_v = (av.vm.max() - 1.0) / (lim.v_max - 1.0)
    use_vlow = (1.0 - zero.vm.min()) / (1.0 - lim.v_min)
    branches = np.concatenate([av.line, av.trafo])
    use_l = _top(branches) / lim.loading_max
    kind = max((use_v, "v"), (use_l, "l"), (use_vlow, "vlow"))[1]
    if kind == "v":
        idx = int(np.argmax(av.vm))
        label = f"v {bus_name(net, solver, idx)}"
        value = lambda pt: pt.vm[idx]
    elif kind == "vlow":
        idx = int(np.argmin(zero.vm))
        label = f"v_min {bus_name(net, solver, idx)}"
        value = lambda pt: pt.vm[idx]
    else:
        idx = int(np.argmax(branches))
        label = branch_name(net, av, idx)
        value = lambda pt: np.concatenate([pt.line, pt.trafo])[idx]
    base = value(row.at["sched"])
    moves = []
    for d in range(len(row.actuators)):
        if row.avail_w[d] <= row.sched_w[d]:
            continue
        p = row.sched_w.copy()
        p[d] = row.avail_w[d]
        moves.append((value(solve(solver, p)) - base, d))
    moves.sort(key=lambda m: -abs(m[0]))
    out = [f"{row.ids[d]} {delta:+.1f}%" if kind == "l" else f"{row.ids[d]} {delta * 1e3:+.1f}mpu"
           for delta, d in moves[:top]]
    return label, out


def bus_name(net: Net, solver, idx: int) -> str:
    """Name of the ``idx``-th reported bus (report order = the net's supplied buses, the
    slack's left out)."""
    data = solver.data
    slack_bus = solver.model.get_generators()[data.slack_gen].bus_id
    keep = np.flatnonzero(data.report_bus != slack_bus)
    if len(data.report_bus) == len(net.bus_names) and idx < len(keep):
        return net.bus_names[int(keep[idx])]
    return f"model bus {int(solver.reported_buses[idx])}"


def branch_name(net: Net, pt: Point, idx: int) -> str:
    if idx < pt.line.size:
        return net.line_names[idx] if len(net.line_names) == pt.line.size else f"line {idx}"
    t = idx - pt.line.size
    return net.trafo_names[t] if len(net.trafo_names) == pt.trafo.size else f"trafo {t}"


def scan_point(code: str, grid: str, case: str, when: str, net: Net, lim: Limits,
               cache_dir=None) -> tuple[Row, object]:
    from adnmesh.grid import GridSolver, load_grid

    data = load_grid(code, case, cache_dir=cache_dir)
    names, ids, p_inst, avail = actuators(data, net, grid)
    sched = np.array([float(round(a / 2.0)) for a in avail])
    row = Row(code, case, when, names, ids, p_inst, avail, sched)
    solver = GridSolver(data, names)
    if not names:
        pt = solve(solver, np.zeros(0))
        row.at = {"0": pt, "sched": pt, "avail": pt}
        return row, solver
    row.at = {"0": solve(solver, 0 * avail), "sched": solve(solver, sched),
              "avail": solve(solver, avail)}
    row.d_up = first_out(solver, row, lim, +1)
    row.d_dn = first_out(solver, row, lim, -1)
    row.critical, row.key = key_ders(solver, row, net, lim)
    return row, solver


def short(code: str) -> str:
    """``1-MV-rural--1-no_sw`` -> ``rural-1``."""
    parts = code.split("-")
    return f"{parts[2]}-{parts[4]}"


def fmt_dp(found: dict) -> str:
    if not found:
        return "in"
    if "OUT" in found:
        return "OUT"
    return " ".join(f"{k} {dp / 1e6:+.2f}" for k, (dp, _) in
                    sorted(found.items(), key=lambda kv: abs(kv[1][0])))


def columns(row: Row, net: Net, solver) -> list[str]:
    z, s, a = row.at["0"], row.at["sched"], row.at["avail"]
    where_vmax = bus_name(net, solver, int(np.argmax(a.vm)))
    vmins = [(p.vm.min(), int(np.argmin(p.vm)), k) for k, p in row.at.items()]
    vmin, vmin_idx, _ = min(vmins)
    # the highest loading of the three points, and where
    loads = [(max(_top(p.line), _top(p.trafo)), k) for k, p in row.at.items()]
    worst_l, worst_k = max(loads)
    pw = row.at[worst_k]
    b = np.concatenate([pw.line, pw.trafo])
    where_l = branch_name(net, pw, int(np.argmax(b))) + ("" if worst_k == "avail" else
                                                         f" (at {worst_k})")
    out = "/".join(p.broken(LIM) or "-" for p in (z, s, a))
    return [short(row.code), row.point + row.when, str(len(row.actuators)),
            f"{row.avail_w.sum() / 1e6:.2f}",
            f"{z.p_ip_w / 1e6:.1f}/{s.p_ip_w / 1e6:.1f}/{a.p_ip_w / 1e6:.1f}",
            f"{s.vm.max():.4f}>{a.vm.max():.4f} {where_vmax}",
            f"{vmin:.4f} {bus_name(net, solver, vmin_idx)}",
            f"{max(_top(s.line), _top(s.trafo)):.1f}>{max(_top(a.line), _top(a.trafo)):.1f}"
            f" {where_l}" + (f" max {worst_l:.1f}" if worst_k != "avail" else ""),
            out, fmt_dp(row.d_up), fmt_dp(row.d_dn),
            (f"{row.critical}: " + ", ".join(row.key)) if row.key else "-"]


HEAD = ["grid", "point", "act", "avail MW", "P_IP 0/sch/av MW", "v_max sch>av @bus",
        "v_min @bus", "load % sch>av @branch", "out 0/sch/av", "dP up MW", "dP dn MW",
        "key DERs (alone sched>avail)"]
LIM = Limits()


def validate(code: str, point: str, row: Row, solver, lim: Limits) -> None:
    """runpp on the SimBench net built independently at ``point``, the DERs at the first
    out-of-band point (else at available power), against the solver."""
    import pandapower as pp

    from adnmesh.grid.simbench_net import grid_net

    firsts = [v for k, v in row.d_up.items() if k != "OUT"]
    p = min(firsts, key=lambda v: abs(v[0]))[1] if firsts else row.avail_w
    mine = solve(solver, p)
    net = grid_net(code, point, "impedance")        # simbench + the case, loads as shunts
    index = {str(n): i for i, n in zip(net.sgen.index, net.sgen.name)}
    for name, p_w in zip(row.actuators, p):
        i = index[name]
        net.sgen.at[i, "p_mw"] = p_w * 1e-6
        net.sgen.at[i, "scaling"] = 1.0
    t0 = time.perf_counter()
    pp.runpp(net)
    wall = time.perf_counter() - t0
    slack = set(net.ext_grid.bus.tolist())
    res = net.res_bus[~net.res_bus.index.isin(slack)].sort_index()
    vm_pp = res.vm_pu.to_numpy()
    diff = np.abs(vm_pp - mine.vm) if vm_pp.size == mine.vm.size else np.array([np.nan])
    top = int(np.argmax(vm_pp))
    line_pp = net.res_line.loading_percent.to_numpy()
    trafo_pp = net.res_trafo.loading_percent.to_numpy()
    p_ip_pp = -net.res_ext_grid.p_mw.sum() * 1e6
    print(f"\nvalidate {code} @ {point} (P_IP {p_ip_pp / 1e6:.4f} MW, DERs "
          f"{', '.join(f'{i} {w / 1e6:.3f}' for i, w in zip(row.ids, p))} MW):")
    print(f"  runpp ({wall:.2f} s): v_max {vm_pp.max():.6f} p.u. at {res.index[top]} "
          f"{net.bus.name.at[res.index[top]]}, v_min {vm_pp.min():.6f}, line max "
          f"{line_pp.max():.4f} % ({net.line.name.iat[int(np.argmax(line_pp))]}), trafo max "
          f"{trafo_pp.max():.4f} %")
    print(f"  solver:       v_max {mine.vm.max():.6f} p.u., v_min {mine.vm.min():.6f}, line max "
          f"{mine.line.max():.4f} %, trafo max {mine.trafo.max():.4f} %, P_IP "
          f"{mine.p_ip_w / 1e6:.4f} MW")
    print(f"  largest |dv| over {vm_pp.size} buses {np.nanmax(diff):.2e} p.u.; |d line| "
          f"{np.max(np.abs(line_pp - mine.line)):.2e} %; |d trafo| "
          f"{np.max(np.abs(trafo_pp - mine.trafo)):.2e} %; |dP_IP| "
          f"{abs(p_ip_pp - mine.p_ip_w):.3f} W")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--grids", default=",".join(GRIDS),
                        help="comma list of rural, semiurb, urban, comm, or full SimBench codes")
    parser.add_argument("--scenarios", default="0,1,2",
                        help="SimBench scenarios (0: today, 1 and 2: DER expansion)")
    parser.add_argument("--cases", default=",".join(CASES), help="study cases; 'none': none")
    parser.add_argument("--time-steps", default="auto",
                        help="'auto', 'none' or a comma list of quarter hours (0-35135)")
    parser.add_argument("--v-min", type=float, default=0.9)
    parser.add_argument("--v-max", type=float, default=1.1)
    parser.add_argument("--loading-max", type=float, default=100.0)
    parser.add_argument("--csv", type=Path, help="also write the table as CSV")
    parser.add_argument("--validate", metavar="CODE@POINT",
                        help="check one point of the scan with pandapower's runpp")
    parser.add_argument("--cache-dir", type=Path, help="grid cache folder (default adnmesh's)")
    args = parser.parse_args(argv)
    LIM.v_min, LIM.v_max, LIM.loading_max = args.v_min, args.v_max, args.loading_max
    from adnmesh.grid.simbench_net import time_step_case

    codes = []
    for g in args.grids.split(","):
        if g.startswith("1-"):
            codes.append((g, g.split("-")[2]))
        else:
            codes += [(f"1-MV-{g}--{s}-no_sw", g) for s in args.scenarios.split(",")]
    cases = [] if args.cases == "none" else args.cases.split(",")
    rows, wanted, legend, findings = [], None, {}, []
    if args.validate:
        wanted = tuple(args.validate.split("@", 1))
    t_start = time.perf_counter()
    for code, grid in codes:
        t0 = time.perf_counter()
        log(f"{code}: reading the net (names, profiles)")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            net = read_net(code)
        steps = [] if args.time_steps == "none" else auto_time_steps(net) \
            if args.time_steps == "auto" else [int(s) for s in args.time_steps.split(",")]
        points = [(c, "") for c in cases] + \
            [(time_step_case(s), f" ({net.times[s]})") for s in steps]
        for case, when in points:
            t1 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                row, solver = scan_point(code, grid, case, when, net, LIM, args.cache_dir)
            rows.append(columns(row, net, solver))
            findings.append((short(code), case + when, row))
            used = [row.ids.index(k.split()[0]) for k in row.key]
            mapping = legend.setdefault(short(code), {})
            for d in used:
                if mapping.get(row.ids[d], row.actuators[d]) != row.actuators[d]:
                    mapping[f"{row.ids[d]} at {case}"] = row.actuators[d]
                else:
                    mapping[row.ids[d]] = row.actuators[d]
            log(f"  {case}{when}: {len(row.actuators)} actuators, "
                f"{time.perf_counter() - t1:.1f} s")
            if wanted and wanted == (code, case):
                wanted = (row, solver, code, case)
        log(f"{code}: {time.perf_counter() - t0:.1f} s")
    widths = [max(len(r[i]) for r in [HEAD, *rows]) for i in range(len(HEAD))]
    print(f"band: v {LIM.v_min:g}-{LIM.v_max:g} p.u., loading <= {LIM.loading_max:g} %; "
          "DERs per adnmesh init, schedules at half their infeed")
    print("  ".join(h.ljust(w) for h, w in zip(HEAD, widths)).rstrip())
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
    print("key DERs by the ids adnmesh init gives them (its order, per type):")
    for grid, ids in legend.items():
        if ids:
            print(f"  {grid}: " + ", ".join(f"{i} = {n}" for i, n in sorted(ids.items())))
    print("findings:")
    reach = [f"{g} {pt} ({fmt_dp(r.d_up)} MW)" for g, pt, r in findings
             if r.d_up and "OUT" not in r.d_up]
    print("  in band at the schedules, out within the DERs' range up: "
          + ("; ".join(reach) or "none"))
    out = [f"{g} {pt}" + (" (also with every actuator at 0)" if r.at["0"].broken(LIM) else "")
           for g, pt, r in findings if "OUT" in r.d_up]
    print("  out of band already at the schedules: " + ("; ".join(out) or "none"))
    down = [f"{g} {pt} ({fmt_dp(r.d_dn)} MW)" for g, pt, r in findings
            if r.d_dn and "OUT" not in r.d_dn]
    print("  out within the DERs' range down: " + ("; ".join(down) or "none"))
    if args.csv:
        with open(args.csv, "w", newline="") as fh:
            csv.writer(fh).writerows([HEAD, *rows])
    log(f"scan: {len(rows)} operating points, {time.perf_counter() - t_start:.1f} s")
    if wanted and isinstance(wanted, tuple) and len(wanted) == 4:
        row, solver, code, case = wanted
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            validate(code, case, row, solver, LIM)
    elif wanted:
        log(f"--validate {args.validate}: not among the scanned points")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
