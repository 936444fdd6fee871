"""Check a table's static controller on fresh random subsets of its config.

Draws subsets the design did not see (:func:`~adnmesh.tuning.subset_selection.spread_random_subsets`:
sizes uniform from 1 to all, and as many with each DER in with probability 1/2), checks the
static pair on each distinct exact plant (disk margin, overshoot, settled; every loop
simulated for its own horizon: :func:`~adnmesh.tuning.static_controller.check_pair`) and prints how many fail,
the least disk margin and the worst rise time.

    .venv/bin/python benchmarks/check_static.py configs/examples/adn-100.yaml T100.json \
        [--spread 16000] [--bernoulli 4000] [--seed 201]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from rich.progress import Progress

from adnmesh.config import load_config
from adnmesh.errors import ConfigError, UsageError
from adnmesh.tuning.table import load_table
from adnmesh.tuning.problem import TuningProblem
from adnmesh.tuning.static_controller import check_pair
from adnmesh.tuning.subset_selection import random_subsets, spread_random_subsets

BATCH = 250


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config")
    ap.add_argument("table")
    ap.add_argument("--spread", type=int, default=16000, help="subsets of uniform size")
    ap.add_argument("--bernoulli", type=int, default=4000, help="subsets, each DER in w.p. 1/2")
    ap.add_argument("--seed", type=int, default=201)
    args = ap.parse_args()
    try:
        config = load_config(args.config)
        static = load_table(args.table, config).static
    except (ConfigError, UsageError, OSError) as exc:
        print(f"error: {exc}")
        return 2
    if static is None or not static.feasible:
        print(f"{args.table} has no feasible static controller")
        return 1
    problem = TuningProblem(config)
    ids = list(config.der_ids())
    subsets = list(dict.fromkeys(
        spread_random_subsets(ids, args.spread, seed=args.seed)
        + (random_subsets(ids, args.bernoulli, seed=args.seed + 1) if args.bernoulli else [])))
    powers = np.unique(np.array([problem.group_power(s) for s in subsets]), axis=0)
    t0 = time.perf_counter()
    failed, least, worst = 0, np.inf, 0.0
    with Progress() as progress:
        task = progress.add_task("checking the static pair", total=len(powers))
        for i in range(0, len(powers), BATCH):
            g = powers[i:i + BATCH]
            c = check_pair(problem, g, static.kp, static.ki)
            failed += int((~c.feasible).sum())
            least = min(least, float(c.disk_margin.min()))
            if c.feasible.any():
                worst = max(worst, float(np.nanmax(c.rise_time_s)))
            progress.advance(task, len(g))
    print(f"static K_P {static.kp:.5g} 1/W, K_I {static.ki:.5g} 1/(W s): {len(subsets)} fresh "
          f"subsets, {len(powers)} distinct plants, {failed} fail; least disk margin "
          f"{least:.5f}; worst rise time {worst:.0f} s; {time.perf_counter() - t0:.0f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
