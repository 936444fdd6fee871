"""Benchmark: a table certified over an uncertainty set against the nominal table.

For a config with ``constraints.robust`` (e.g. written by ``adnmesh identify --robust-out``)
and the same config without it, per subset (default: the scenario's):

- the as-deployed figures on the reference model: rise and settling time, overshoot, disk
  margin;
- the worst member of the set the certificate finds for each table (its disk margin and
  overshoot, and where);
- the **b-range each entry certifies**: the interval of one factor ``b`` on every DER's time
  constant (reference PT1, dead times as configured) around 1 within which both constraints
  still hold, each end by bisection to 0.1 % (``> 100`` / ``< 0.01`` where none is found);

and the cost: tuning the subsets over the set against tuning them nominally, in the same run
(``--repeat`` times; wall seconds and the ratio, as a range).

    .venv/bin/python benchmarks/bench_robust.py CONFIG_WITH_SET [--subsets scenario|all]
        [--repeat 1]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adnmesh import one_blas_thread  # noqa: E402

one_blas_thread()

from adnmesh.config import load_config  # noqa: E402
from adnmesh.loopmodel.evaluation import evaluate  # noqa: E402
from adnmesh.tuning import tune_table  # noqa: E402
from adnmesh.tuning.problem import TuningProblem  # noqa: E402
from adnmesh.tuning.robust_check import worst_members  # noqa: E402
from adnmesh.tuning.subset_selection import select_subsets  # noqa: E402

B_EDGES = (0.01, 100.0)


def _holds(problem, gains, kp, ki, b: float) -> bool:
    plant = problem.plant(gains).with_model("pt1", b)
    f = evaluate(plant, np.array([kp]), np.array([ki]), band_pct=problem.band_pct,
                 classical=False)
    return bool(f.stable[0] and f.disk_margin[0] >= problem.disk_margin_min
                and f.overshoot_pct[0] < problem.overshoot_max_pct
                and np.isfinite(f.settling_time_s[0]))


def b_range(problem, gains, kp, ki) -> tuple[str, str]:
    """The b interval around 1 in which the loop keeps both constraints (text per end)."""
    ends = []
    for edge in B_EDGES:
        good, bad = 1.0, None
        b = 1.0
        while bad is None:
            b = max(b / 2, edge) if edge < 1 else min(b * 2, edge)
            if _holds(problem, gains, kp, ki, b):
                good = b
                if b == edge:
                    break
            else:
                bad = b
        if bad is None:
            ends.append(f"{'<' if edge < 1 else '>'} {edge:g}")
            continue
        while abs(np.log(bad / good)) > 1e-3:
            mid = float(np.sqrt(good * bad))
            good, bad = (mid, bad) if _holds(problem, gains, kp, ki, mid) else (good, mid)
        ends.append(f"{good:.3g}")
    return ends[0], ends[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", type=Path)
    parser.add_argument("--subsets", default="scenario")
    parser.add_argument("--repeat", type=int, default=1)
    args = parser.parse_args()
    robust_cfg = load_config(args.config)
    if robust_cfg.constraints.robust is None:
        print(f"{args.config}: no constraints.robust", file=sys.stderr)
        return 2
    nominal_cfg = robust_cfg.model_copy(update={"constraints": robust_cfg.constraints.model_copy(
        update={"robust": None})})
    subsets = select_subsets(robust_cfg, args.subsets)
    times = {"nominal": [], "robust": []}
    tables = {}
    for _ in range(args.repeat):
        for name, cfg in (("nominal", nominal_cfg), ("robust", robust_cfg)):
            t0 = time.perf_counter()
            tables[name] = tune_table(cfg, "paper", 1, subsets=subsets)
            times[name].append(time.perf_counter() - t0)
    ratio = [r / n for r, n in zip(times["robust"], times["nominal"])]
    print(f"tuning {len(subsets)} subset(s), one process: nominal "
          f"{min(times['nominal']):.1f}-{max(times['nominal']):.1f} s, over the set "
          f"{min(times['robust']):.1f}-{max(times['robust']):.1f} s "
          f"({min(ratio):.1f}-{max(ratio):.1f}x)")
    judge = TuningProblem(robust_cfg)
    print("| subset | table | rise [s] | settling [s] | overshoot [%] | disk margin | "
          "worst over the set: disk margin / overshoot [%] | b-range kept (PT1) |")
    print("|---|---|---|---|---|---|---|---|")
    for s in subsets:
        for name in ("nominal", "robust"):
            e = tables[name].lookup(s)
            if e is None or not e.feasible:
                print(f"| {len(s)} DERs | {name} | infeasible: {e.reason if e else 'none'} |")
                continue
            gains = judge.group_power(e.ders, e.w)
            wc = worst_members(judge, gains[None], np.array([e.kp]), np.array([e.ki]))
            lo, hi = b_range(judge, gains, e.kp, e.ki)
            f = e.figures
            worst = (f"{wc.disk_margin[0]:.3f} / {wc.overshoot_pct[0]:.3f}"
                     if wc.settled[0] else "unstable or not settled")
            label = ",".join(s) if len(s) <= 5 else f"{len(s)} DERs"
            print(f"| {label} | {name} | {f['rise_time_s']:.3f} | {f['settling_time_s']:.3f} | "
                  f"{f['overshoot_pct']:.3f} | {f['disk_margin']:.3f} | {worst} | "
                  f"{lo} to {hi} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
