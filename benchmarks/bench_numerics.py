"""Benchmark: disk margin + step info of the 11-DER SimBench loop, adnmesh vs python-control.

Prints the amortised time per candidate for 1, 100 and 10,000 candidates (adnmesh, exact
delays, vectorised) and for python-control with order-10 Padé delays on the same loops (one
state-space model per candidate, as a python-control user would write it: each DER's path
``P_inst/(1 + T s) * pade(T_com + T_delay)``), plus the ratio and the largest disagreement of
the figures on the candidates both evaluated.

    .venv/bin/python benchmarks/bench_numerics.py [--pc-samples 5] [--sizes 1,100,10000]

``--crossings``: the margins' crossing finder (:func:`adnmesh.loopmodel.margins.crossing`, regula falsi)
against scipy's ``optimize.elementwise.find_root`` and a 60-step bisection on the phase and
gain crossings of 1 and 40 SimBench loops: time (median of repeats), evaluations, largest
difference of the roots.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import control as ct
import numpy as np
import scipy.linalg

from adnmesh.config import load_config
from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.loopmodel.plant import RISE_PER_LAG, plant_from_ders

ROOT = Path(__file__).resolve().parent.parent


def candidates(total_w: float, n: int, seed: int = 0):
    """Gains scattered around a well-tuned pair (normalised kp 0.22, ki 0.85 1/s)."""
    rng = np.random.default_rng(seed)
    s = np.exp(rng.uniform(-0.7, 0.3, size=(n, 2)))
    return 0.22 * s[:, 0] / total_w, 0.85 * s[:, 1] / total_w


def pade_ss(delay, order=10):
    num, den = ct.pade(delay, order)
    return ct.ss(ct.tf(num, den))


def balanced(sys):
    _, (scale, _) = scipy.linalg.matrix_balance(sys.A, permute=False, separate=True)
    return ct.ss(sys.A / scale[:, None] * scale[None, :], sys.B / scale[:, None],
                 sys.C * scale[None, :], sys.D)


def python_control(config, kp, ki, t_end=100.0, dt=0.01):
    """Disk margin and step info the python-control way; returns (alpha, overshoot, rise)."""
    pi = ct.ss(ct.tf([kp, ki], [1.0, 0.0]))
    forward = None
    for der in config.ders:
        path = ct.ss(ct.tf([der.p_inst_w], [der.t_rise_s / RISE_PER_LAG, 1.0])) \
            * pade_ss(config.t_com_s + der.t_delay_s)
        forward = path if forward is None else forward + path
    meas = pade_ss(config.t_meas_s)
    loop = balanced(pi * forward * meas)
    alpha, _, _ = ct.disk_margins(loop, np.geomspace(1e-3, 1e2, 1000))
    closed = balanced(ct.feedback(pi * forward, meas))
    t = np.arange(0.0, t_end + dt / 2, dt)
    y = np.squeeze(ct.step_response(closed, t).outputs)
    info = ct.step_info(y, t, yfinal=1.0, SettlingTimeThreshold=0.05)
    return float(alpha), float(info["Overshoot"]), float(info["RiseTime"])


def _bisection(fun, lo, hi, iterations=60):
    """The crossing finder the margins used before (every crossing, 60 halvings)."""
    idx = np.arange(lo.size)
    flo = fun(lo, idx)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        fm = fun(mid, idx)
        same = np.sign(fm) == np.sign(flo)
        lo, flo, hi = np.where(same, mid, lo), np.where(same, fm, flo), np.where(same, hi, mid)
    return 0.5 * (lo + hi)


def crossings(config, repeats: int = 7) -> None:
    """Crossing finders compared on the phase and gain crossings of SimBench loops."""
    from scipy.optimize import elementwise

    from adnmesh.loopmodel.frequency_response import as_candidates, loop_points
    from adnmesh.loopmodel.margins import CROSSING_XTOL, crossing
    from adnmesh.loopmodel.stability import nyquist_stability
    from adnmesh.tuning import TuningProblem

    problem = TuningProblem(config)
    rng = np.random.default_rng(0)
    for m_loops in (1, 40):
        f = rng.dirichlet(np.ones(len(problem.actuators)), m_loops)
        plant = problem.plant(f)
        kp, ki = rng.uniform(0.05, 0.5, m_loops), rng.uniform(0.005, 0.2, m_loops)
        nyq = nyquist_stability(plant, kp, ki)
        kp, ki, g = as_candidates(plant, kp, ki)
        logw = np.log(nyq.omega)
        for kind, part in (("phase", lambda v: v.imag), ("gain", lambda v: np.abs(v) - 1.0)):
            val = part(nyq.loop)
            m, k = np.nonzero(np.sign(val[:, :-1]) != np.sign(val[:, 1:]))
            calls = [0]

            def fun(x, i, m=m, part=part):
                calls[0] += 1
                return part(loop_points(plant, kp[m[i]], ki[m[i]], g[m[i]], np.exp(x)))

            runs = {
                "adnmesh crossing": lambda: crossing(fun, logw[k], logw[k + 1]),
                "scipy find_root": lambda: elementwise.find_root(
                    lambda x, i: fun(x, i.astype(int)), (logw[k], logw[k + 1]),
                    args=(np.arange(k.size).astype(float),),
                    tolerances={"xatol": CROSSING_XTOL, "xrtol": 0.0}).x,
                "bisection (60)": lambda: _bisection(fun, logw[k], logw[k + 1]),
            }
            roots, times, evals = {}, {}, {}
            for name, run in runs.items():
                dts = []
                for _ in range(repeats):
                    calls[0] = 0
                    t0 = time.perf_counter()
                    roots[name] = run()
                    dts.append(time.perf_counter() - t0)
                times[name], evals[name] = np.array(dts) * 1e3, calls[0]
            ref = times["scipy find_root"]
            print(f"{m_loops:>2} loop(s), {k.size:>5} {kind} crossings:")
            for name in runs:
                t = times[name]
                diff = np.abs(roots[name] - roots["scipy find_root"]).max()
                print(f"  {name:17s} median {np.median(t):7.2f} ms (range {t.min():.2f}-"
                      f"{t.max():.2f}), {evals[name]:>3} evaluations, / scipy "
                      f"{np.median(t) / np.median(ref):4.2f}, largest root difference "
                      f"{diff:.1e}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1,100,10000")
    ap.add_argument("--pc-samples", type=int, default=5)
    ap.add_argument("--crossings", action="store_true",
                    help="only compare the crossing finders (margins) with scipy's")
    args = ap.parse_args(argv)
    config = load_config(ROOT / "configs" / "simbench.yaml")
    if args.crossings:
        crossings(config)
        return 0
    plant = plant_from_ders(config.ders, config.t_com_s, config.t_meas_s)
    total = float(plant.total_gain_w)
    evaluate(plant, *candidates(total, 4))          # warm-up (imports, caches)

    print(f"11-DER SimBench loop, {len(plant.actuators)} actuator groups; "
          "disk margin + step info per candidate")
    ours = {}
    for n in (int(x) for x in args.sizes.split(",")):
        kp, ki = candidates(total, n)
        t0 = time.perf_counter()
        f = evaluate(plant, kp, ki, classical=False)
        dt = time.perf_counter() - t0
        ours[n] = dt / n
        print(f"adnmesh          M={n:>6}: {dt:8.3f} s total, {dt / n * 1e3:9.4f} ms/candidate "
              f"({int(f.stable.sum())} stable)")

    kp, ki = candidates(total, args.pc_samples, seed=1)
    python_control(config, kp[0], ki[0])            # warm-up
    t0 = time.perf_counter()
    ref = [python_control(config, a, b) for a, b in zip(kp, ki)]
    pc = (time.perf_counter() - t0) / args.pc_samples
    print(f"python-control   M={args.pc_samples:>6}: {pc * 1e3:9.1f} ms/candidate "
          "(Padé order 10, 1000 frequencies, 10001 time samples)")
    f = evaluate(plant, kp, ki, classical=False)
    d_alpha = max(abs(r[0] - a) / a for r, a in zip(ref, f.disk_margin))
    d_os = max(abs(r[1] - o) for r, o in zip(ref, f.overshoot_pct))
    d_tr = max(abs(r[2] - t) for r, t in zip(ref, f.rise_time_s))
    print(f"agreement on those: disk margin {d_alpha:.1e} rel, overshoot {d_os:.1e} %-points, "
          f"rise time {d_tr:.1e} s (python-control samples at 10 ms, no interpolation)")
    for n, per in ours.items():
        print(f"speed-up at M={n:>6}: {pc / per:8.0f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
