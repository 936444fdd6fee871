"""Benchmark: the warm-started grid solver against pandapower's runpp on a control run's points.

The operating points are those of a control run on configs/simbench.yaml: the eleven actuators
start at their schedule (the wind turbines at half their installed power, CHP and PV at 0 W),
then every ``--period-s`` each moves by a first-order lag (its reference-model T) towards a
setpoint that steps by +-1 MW (shared by installed power) every 5 s, plus a small random jitter
(0.05 % of P_inst): small steps between consecutive samples, as the measurement agent sees them.
Prints, per repeat, the median and p99 time of one solve (GridSolver.solve; wall clock, and the
thread's CPU time, which preemption on a shared machine does not inflate) beside pandapower's
runpp on every ``--runpp-every``-th point of the same run (default init, and init="results",
pandapower's own warm start), their ratio, and the largest |dP_IP| and |dQ_IP|; then the cold
load time (fresh interpreter, empty cache: simbench, pandapower and the grid build) and the
cached one (fresh interpreter, warm cache; and up to the first solved sample).

    .venv/bin/python benchmarks/bench_grid.py [--samples 3000] [--repeat 3] [--runpp-every 10]
"""
from __future__ import annotations

import argparse
import copy
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CODE, CASE = "1-MV-rural--0-no_sw", "lW"

_LOAD_SCRIPT = """
import time; t0 = time.perf_counter()
from adnmesh.grid import GridSolver, available_power_w, load_grid
data = load_grid({code!r}, {case!r}, cache_dir={cache!r}); t1 = time.perf_counter()
names = {names!r}
sample = GridSolver(data, names).solve(available_power_w(data, names))
print(t1 - t0, time.perf_counter() - t0, sample.converged)
"""


def trajectory(ders, n: int, period_s: float, seed: int = 0) -> np.ndarray:
    """(n, m) actuator powers in W along a control-like run (see the module docstring)."""
    rng = np.random.default_rng(seed)
    p_inst = np.array([d.p_inst_w for d in ders])
    lag = np.array([d.t_rise_s / np.log(9.0) for d in ders])
    share = p_inst / p_inst.sum()
    p = np.array([d.p_sched_w for d in ders], dtype=float)
    setpoint = p.copy()
    out = np.empty((n, len(ders)))
    steps_per_change = max(1, int(round(5.0 / period_s)))
    for k in range(n):
        if k and k % steps_per_change == 0:
            sign = 1.0 if (k // steps_per_change) % 2 else -1.0
            setpoint = np.clip(setpoint + sign * 1e6 * share, 0.0, p_inst)
        p = setpoint + (p - setpoint) * np.exp(-period_s / lag)
        p = np.clip(p + rng.normal(0.0, 5e-4, len(ders)) * p_inst, 0.0, p_inst)
        out[k] = p
    return out


def set_sgens(net, index, p_w) -> None:
    net.sgen.loc[index, "p_mw"] = p_w / 1e6


def time_solver(solver, points) -> tuple[np.ndarray, np.ndarray, list]:
    """Wall time and CPU time (this thread) of every solve, s, and the samples."""
    wall, cpu, samples = np.empty(len(points)), np.empty(len(points)), []
    for k, p in enumerate(points):
        c0, t0 = time.thread_time(), time.perf_counter()
        samples.append(solver.solve(p))
        wall[k], cpu[k] = time.perf_counter() - t0, time.thread_time() - c0
    return wall, cpu, samples


def time_runpp(net, index, points, **options) -> tuple[np.ndarray, np.ndarray]:
    import pandapower as pp
    times, pq = np.empty(len(points)), np.empty((len(points), 2))
    for k, p in enumerate(points):
        set_sgens(net, index, p)
        t0 = time.perf_counter()
        pp.runpp(net, **options)
        times[k] = time.perf_counter() - t0
        ext = net.res_ext_grid.iloc[0]
        pq[k] = (-ext.p_mw * 1e6, -ext.q_mvar * 1e6)
    return times, pq


def load_times(names) -> tuple[float, float, float]:
    """(cold load_grid s, cached load_grid s, cached to first sample s), fresh interpreters."""
    with tempfile.TemporaryDirectory() as cache:
        script = _LOAD_SCRIPT.format(code=CODE, case=CASE, cache=cache, names=list(names))
        runs = []
        for _ in range(2):
            out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                                 check=True, cwd=ROOT)
            runs.append([float(x) for x in out.stdout.split()[:2]])
    return runs[0][0], runs[1][0], runs[1][1]


def stats_us(t: np.ndarray) -> str:
    return f"median {np.median(t) * 1e6:7.1f} us, p99 {np.percentile(t, 99) * 1e6:8.1f} us"


def stats_ms(t: np.ndarray) -> str:
    return f"median {np.median(t) * 1e3:6.2f} ms, p99 {np.percentile(t, 99) * 1e3:7.2f} ms"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=3000)
    ap.add_argument("--period-s", type=float, default=0.01)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--runpp-every", type=int, default=10)
    ap.add_argument("--no-load-times", action="store_true")
    args = ap.parse_args(argv)

    from adnmesh.config import load_config
    from adnmesh.grid import GridSolver, available_power_w
    from adnmesh.grid.from_net import build_grid_data
    from adnmesh.grid.simbench_net import grid_net

    ders = load_config(ROOT / "configs" / "simbench.yaml").ders
    names = [d.sgen for d in ders]
    print(f"{CODE} at {CASE}, {len(names)} actuators, loads as constant impedances; "
          f"load average {os.getloadavg()[0]:.1f}")
    net = grid_net(CODE, CASE, "impedance")
    data = build_grid_data(copy.deepcopy(net), CODE, CASE, "impedance")
    index = [net.sgen.index[net.sgen.name == n][0] for n in names]
    points = trajectory(ders, args.samples, args.period_s)
    step = np.abs(np.diff(points, axis=0)).max(axis=1)
    print(f"{len(points)} points, {args.period_s * 1e3:g} ms apart; largest actuator change "
          f"between samples: median {np.median(step) / 1e3:.2f} kW, max {step.max() / 1e3:.1f} kW")
    _t0_report(net, index, data, names, ders)
    sub = points[::args.runpp_every]
    for r in range(args.repeat):
        t_ls, c_ls, samples = time_solver(GridSolver(data, names), points)
        t_pp, pq_pp = time_runpp(net, index, sub)
        t_pw, _ = time_runpp(net, index, sub, init="results")
        ours = np.array([(s.p_ip_w, s.q_ip_var) for s in samples])[::args.runpp_every]
        dp, dq = np.abs(ours - pq_pp).max(axis=0)
        iters = np.bincount([s.iterations for s in samples])
        print(f"repeat {r + 1}: GridSolver.solve {stats_us(t_ls)} (iterations: "
              + ", ".join(f"{i}: {c}" for i, c in enumerate(iters) if c) + ")")
        print(f"          (CPU time: {stats_us(c_ls)}; the wall p99 holds preemption on a "
              "busy machine)")
        print(f"          runpp            {stats_ms(t_pp)}   ratio runpp/solve "
              f"{np.median(t_pp) / np.median(t_ls):6.0f} (medians)")
        print(f"          runpp(results)   {stats_ms(t_pw)}   ratio "
              f"{np.median(t_pw) / np.median(t_ls):6.0f}")
        print(f"          agreement on {len(sub)} points: max |dP_IP| {dp:.3g} W, "
              f"max |dQ_IP| {dq:.3g} var; all converged: {all(s.converged for s in samples)}")
    if not args.no_load_times:
        cold, cached, first = load_times(names)
        print(f"load: cold {cold:.1f} s (fresh interpreter, empty cache), cached {cached:.2f} s"
              f" (fresh interpreter), cached to the first sample {first:.2f} s")
    return 0


def _t0_report(net, index, data, names, ders) -> None:
    """P_IP, Q_IP at t = 0 (the schedule) and at the study case's available power, vs runpp."""
    from adnmesh.grid import GridSolver, available_power_w
    work = copy.deepcopy(net)
    for label, p in [("t = 0 (schedule)", np.array([d.p_sched_w for d in ders], float)),
                     ("study case (available)", available_power_w(data, names))]:
        sample = GridSolver(data, names).solve(p)
        _, pq = time_runpp(work, index, [p])
        print(f"{label:24s}: P_IP {sample.p_ip_w / 1e6:.6f} MW (runpp {pq[0, 0] / 1e6:.6f}), "
              f"Q_IP {sample.q_ip_var / 1e3:.4f} kvar (runpp {pq[0, 1] / 1e3:.4f}); "
              f"V {sample.vm_min_pu:.4f}-{sample.vm_max_pu:.4f} p.u., line "
              f"{sample.line_loading_max_pct:.1f} %, trafo {sample.trafo_loading_max_pct:.1f} %")


if __name__ == "__main__":
    sys.exit(main())
