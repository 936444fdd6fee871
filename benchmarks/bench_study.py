"""Benchmark: the year study (adnmesh study's engine) beside pandapower's run_timeseries.

Per repeat, in one process and one after the other:

- **study**: ``study_year`` over the whole SimBench year of configs/simbench.yaml (35,136
  quarter hours; profiles and grid from the cache, the gain table read), wall and CPU time;
- **pandapower**: ``pandapower.timeseries.run_timeseries`` of the same net with simbench's own
  profile controllers (``apply_const_controllers``) on ``--sample`` consecutive intervals
  starting at a random one (after a warm-up run of 10), its time per interval and that times
  35,136: the year it would take; and the ratio of the two.

The pandapower net keeps SimBench's constant-power loads (its time series cannot turn them into
shunts per step); the study uses the config's constant impedances. Both solve one AC power
flow of the 1-MV-rural net per interval; the study also finds the availability, the entries,
ranges, guard and contributions.

    .venv/bin/python benchmarks/bench_study.py [--repeat 3] [--sample 300]
"""
from __future__ import annotations

import argparse
import logging
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def _study_once(config, profiles, data, p_op, table) -> tuple[float, float, int]:
    from adnmesh.study.year import study_year
    wall, cpu = time.perf_counter(), time.process_time()
    result = study_year(config, profiles, data, p_op, table)
    return time.perf_counter() - wall, time.process_time() - cpu, len(result)


def _pandapower_once(net, start: int, count: int) -> float:
    from pandapower.timeseries import run_timeseries
    began = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_timeseries(net, time_steps=range(start, start + count), verbose=False,
                       continue_on_divergence=True)
    return (time.perf_counter() - began) / count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--sample", type=int, default=300)
    args = parser.parse_args()
    logging.disable(logging.WARNING)

    import simbench

    from adnmesh.config import load_config
    from adnmesh.control.operating_point import available_power_w
    from adnmesh.grid import load_grid
    from adnmesh.grid.profiles import load_profiles
    from adnmesh.grid.simbench_net import load_simbench_net
    from adnmesh.tuning.table import default_table_path, load_table

    config = load_config(ROOT / "configs" / "simbench.yaml")
    code, model = config.simbench_code, config.grid_model.load_model
    profiles = load_profiles(code, model)
    data = load_grid(code, "time step 0", model)
    power = available_power_w(config)
    p_op = np.array([power[d] for d in config.der_ids()])
    path = default_table_path(config)
    if not path.exists():
        raise SystemExit(f"no table at {path}: run 'adnmesh tune {config.path}' first")
    table = load_table(path, config)
    net = load_simbench_net(code)
    simbench.apply_const_controllers(net, simbench.get_absolute_values(net, True))
    rng = np.random.default_rng(0)
    _pandapower_once(net, 0, 10)                  # warm-up: imports, the output writer's set-up
    print(f"year: {len(profiles)} intervals of {code}; pandapower on {args.sample} of them")
    ratios = []
    for r in range(args.repeat):
        wall, cpu, n = _study_once(config, profiles, data, p_op, table)
        start = int(rng.integers(0, len(profiles) - args.sample))
        per = _pandapower_once(net, start, args.sample)
        year = per * len(profiles)
        ratios.append(year / wall)
        print(f"repeat {r + 1}: study {wall:.2f} s wall ({cpu:.2f} s CPU, "
              f"{wall / n * 1e6:.0f} us/interval); pandapower run_timeseries "
              f"{per * 1e3:.1f} ms/interval -> {year:.0f} s for the year; ratio {year / wall:.0f}x")
    print(f"ratio range: {min(ratios):.0f}-{max(ratios):.0f}x")


if __name__ == "__main__":
    main()
