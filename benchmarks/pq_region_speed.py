"""Benchmark: how to compute the feasible P-Q region (docs/method.md#feasible-p-q-region).

Three optimisers of the support function ``max cos θ · P_IP + sin θ · Q_IP`` over the DERs'
set-points, in the same ``--directions`` evenly spread directions, each direction from the last
one's optimum, the grid limits of the config (``--v-max`` to lower the voltage limit so that it
binds):

- **SLSQP** (scipy; what :func:`adnmesh.analysis.pq_region.pq_region` uses): the DER circles as
  analytic constraints, P_IP, Q_IP and the grid limits by forward differences of the
  warm-started power flow;
- **SLP** (scipy's ``linprog``, HiGHS): sequential linear programming on the same forward
  differences, a trust region on the set-points, the grid limits elastic (l1 penalty), the
  circles by their tangents (then the point scaled back onto the circle), a step kept only if
  the penalised objective gains; a direction that ends outside the limits counts as failed;
- **pandapower OPF** (``--opf``; PYPOWER's interior point on the SimBench net): the DERs as
  controllable sgens with their P and Q box, the external grid's voltage pinned to ±1e-4 p.u.,
  linear costs on its P and Q. It has no apparent-power circle and rates lines in MVA, not by
  current, so its values differ by more than the optimiser.

Prints per optimiser: wall and CPU time, power flows, and per direction its value against
SLSQP's (positive: further out). Then the whole region as ``adnmesh analyze --pq-region``
computes it (with the comparison region and the refinement).

    .venv/bin/python benchmarks/pq_region_speed.py [CONFIG] [--directions 24] [--v-max 1.04] [--opf]
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def _setup(config, v_max):
    from adnmesh.analysis import pq_region as region_module
    from adnmesh.control.operating_point import available_power_w, grid_solver

    limits = config.grid_model.limits
    if v_max is not None:
        limits = limits.model_copy(update={"v_max_pu": v_max})
    solver = grid_solver(config)
    problem = region_module._Problem(solver, config.ders, available_power_w(config),
                                     config.reactive, {d.id for d in config.ders})
    schedules = np.array([d.p_sched_w for d in config.ders]
                         + [d.q_sched_var for d in config.ders], float)
    return region_module, problem, limits, problem.start(schedules)


def run_slsqp(config, thetas, v_max) -> tuple[list[float], int]:
    module, problem, limits, x0 = _setup(config, v_max)
    search = module._Search(problem, limits, x0, module._Progress(len(thetas), None))
    values = [search.toward(float(t)).value for t in thetas]
    return values, problem.power_flows


def run_slp(config, thetas, v_max, iterations: int = 60) -> tuple[list[float], int]:
    """Trust-region SLP with linprog, the grid limits elastic (an l1 penalty, so that it
    starts from a point outside them too); see the module docstring."""
    from scipy.optimize import linprog

    module, problem, limits, x = _setup(config, v_max)
    problem.limits = limits
    rows = np.arange(len(problem.labels))
    weight = 10.0 * problem.rating.sum()          # W per unit of violation (0.01 p.u., 10 %)

    def merit(c, z, g):
        return c @ z - weight * np.maximum(-g, 0.0).sum()

    values = []
    for theta in thetas:
        c = np.array([math.cos(theta), math.sin(theta)])
        trust, cuts = 0.2, []
        problem.forget()
        for _ in range(iterations):
            z, g = problem.value(x, rows)
            jz, jg = problem.jacobian(x, rows)
            if problem.circles:      # tangents of the circles here and at earlier points
                cuts.append((problem.circle_jacobian(x), problem.circle(x), x.copy()))
            n, m = x.size, g.size      # variables: the step, then one slack per limit
            a_ub = np.vstack([np.hstack([-jg, -np.eye(m)]),
                              *[np.hstack([-a, np.zeros((a.shape[0], m))]) for a, _, _ in cuts]])
            b_ub = np.concatenate([g, *[v + a @ (x - at) for a, v, at in cuts]])
            bounds = [(max(lo - xi, -trust), min(hi - xi, trust))
                      for lo, hi, xi in zip(problem.x_lo, problem.x_hi, x)] + [(0, None)] * m
            cost = np.concatenate([-(c @ jz), np.full(m, weight)])
            lp = linprog(cost, A_ub=a_ub, b_ub=b_ub, bounds=bounds, method="highs")
            if lp.status != 0:
                trust /= 2
            else:
                trial = _radial(problem, x + lp.x[:n])
                z_new, g_new = problem.value(trial, rows)
                gain = merit(c, z_new, g_new) - merit(c, z, g)
                if gain > 0:
                    x = trial
                    if gain < 0.01 and np.all(g_new * problem.unit >= -problem.tolerance):
                        break
                else:
                    trust /= 2
            if trust < 1e-7:
                break
        z, g = problem.value(x, rows)
        inside = np.all(g * problem.unit >= -problem.tolerance)
        values.append(float(c @ z) if inside else math.nan)
    return values, problem.power_flows


def _radial(problem, x):
    """``x`` into the DER limits: each (P, Q) outside its circle scaled back onto it (the
    tangents let the LP step out of it), then the box."""
    full = problem.full(x)
    for i in problem.circles:
        radius = math.hypot(full[i], full[problem.n + i])
        if radius > problem.rating[i]:
            full[[i, problem.n + i]] *= problem.rating[i] / radius
    return problem.on_capability(problem.start(full))


def run_opf(config, thetas, v_max) -> tuple[list[float], int]:
    import warnings

    import pandapower as pp

    from adnmesh.grid.simbench_net import grid_net
    from adnmesh.reactive import capability_of

    limits = config.grid_model.limits
    net = grid_net(config.simbench_code, config.grid_model.study_case,
                   config.grid_model.load_model)
    index = {name: i for i, name in zip(net.sgen.index, net.sgen.name)}
    net.sgen["controllable"] = False
    for der in config.ders:
        cap = capability_of(der, config.reactive)
        i = index[der.sgen]
        net.sgen.loc[i, ["controllable", "min_p_mw", "max_p_mw", "min_q_mvar", "max_q_mvar"]] = [
            True, 0.0, float(net.sgen.p_mw[i]), cap.q_min_var / 1e6, cap.q_max_var / 1e6]
    net.bus["min_vm_pu"], net.bus["max_vm_pu"] = limits.v_min_pu, v_max or limits.v_max_pu
    slack, vm = net.ext_grid.bus, net.ext_grid.vm_pu.values   # its voltage would be free;
    net.bus.loc[slack, "min_vm_pu"] = vm - 1e-4                # pinned exactly, no direction
    net.bus.loc[slack, "max_vm_pu"] = vm + 1e-4                # converged (pandapower 3.5.6)
    net.line["max_loading_percent"] = net.trafo["max_loading_percent"] = limits.loading_max_pct
    net.ext_grid["controllable"] = True
    for column in ("min_p_mw", "min_q_mvar"):
        net.ext_grid[column] = -1e3
    for column in ("max_p_mw", "max_q_mvar"):
        net.ext_grid[column] = 1e3
    values = []
    for theta in thetas:
        net.poly_cost = net.poly_cost.iloc[0:0]
        pp.create_poly_cost(net, 0, "ext_grid", cp1_eur_per_mw=math.cos(theta),
                            cq1_eur_per_mvar=math.sin(theta))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                pp.runopp(net, calculate_voltage_angles=False, init="pf")
            values.append(-1e6 * (math.cos(theta) * net.res_ext_grid.p_mw.sum()
                                  + math.sin(theta) * net.res_ext_grid.q_mvar.sum()))
        except pp.OPFNotConverged:
            values.append(math.nan)
    return values, 0


def timed(function, *args, **kwargs):
    wall, cpu = time.perf_counter(), time.process_time()
    out = function(*args, **kwargs)
    return out, time.perf_counter() - wall, time.process_time() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", nargs="?", default=str(ROOT / "configs" / "simbench.yaml"))
    parser.add_argument("--directions", type=int, default=24)
    parser.add_argument("--v-max", type=float, help="lower voltage limit, p.u.")
    parser.add_argument("--opf", action="store_true", help="also pandapower's OPF (slow)")
    args = parser.parse_args()

    import adnmesh
    adnmesh.one_blas_thread()
    from adnmesh.analysis.pq_region import pq_region
    from adnmesh.config import load_config
    from adnmesh.control.operating_point import available_power_w, grid_solver

    config = load_config(args.config)
    thetas = 2 * math.pi * np.arange(args.directions) / args.directions
    grid_solver(config)                                        # the grid loaded once
    print(f"{args.config}: {args.directions} directions, v_max "
          f"{args.v_max or config.grid_model.limits.v_max_pu} p.u.")
    (reference, flows), wall, cpu = timed(run_slsqp, config, thetas, args.v_max)
    print(f"  SLSQP           {wall:7.2f} s wall {cpu:7.2f} s CPU  {flows:7d} power flows")
    runs = [("SLP (linprog)", run_slp)] + ([("pandapower OPF", run_opf)] if args.opf else [])
    for name, run in runs:
        (values, flows), wall, cpu = timed(run, config, thetas, args.v_max)
        diff = np.array(values) - np.array(reference)
        failed = int(np.isnan(diff).sum())
        print(f"  {name:15s} {wall:7.2f} s wall {cpu:7.2f} s CPU  {flows:7d} power flows; "
              f"value - SLSQP's: median {np.nanmedian(diff):+.4g} W, min {np.nanmin(diff):+.4g}"
              f" W, max {np.nanmax(diff):+.4g} W" + (f"; {failed} failed" if failed else ""))
    limits = config.grid_model.limits
    if args.v_max is not None:
        limits = limits.model_copy(update={"v_max_pu": args.v_max})
    region, wall, cpu = timed(pq_region, grid_solver(config), config.ders,
                              available_power_w(config), limits, config.reactive,
                              directions=args.directions)
    print(f"  pq_region (both regions, refined): {wall:.2f} s wall {cpu:.2f} s CPU, "
          f"{region.power_flows} power flows, {len(region.support)} and "
          f"{len(region.without_limits.support)} support points, edges within "
          f"{region.boundary_error_w:.0f} W")


if __name__ == "__main__":
    main()
