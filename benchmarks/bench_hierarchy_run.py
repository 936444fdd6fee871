"""Cost of a hierarchy's run (``adnmesh cascade --run``), against its ADNs run alone.

The hierarchy's levels are made as the command makes them (its sites, the upper config and table
written to a temporary folder). Then, alternating in the same process for ``--repeat`` rounds:

- the hierarchy: :func:`adnmesh.study.hierarchy.simulate`, every level's agents under one clock;
- the peer: each ADN's level alone with :func:`adnmesh.sim.local.run_local` (the in-process
  runner ``up``'s tests use), same duration, its offset from above left at 0; the sum of their
  times.

The ratio says what the coupling costs (the site agents, the upper level, one clock over all
grids). Printed: wall times and speed (sim s per wall s) as ranges, the ratio of the medians,
messages, agents, and the process's peak RSS.

    python benchmarks/bench_hierarchy_run.py configs/examples/hierarchy/hv.yaml --repeat 3
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import tempfile
import time
from pathlib import Path

from adnmesh.cascade.upper_table import certify_entries
from adnmesh.commands.cascade import upper_level
from adnmesh.config import load_hierarchy
from adnmesh.sim.local import run_local
from adnmesh.study.hierarchy import hierarchy_levels, simulate
from adnmesh.tuning import tune_table


def levels_of(path: str, folder: Path):
    hierarchy = load_hierarchy(path)
    sites, upper = upper_level(hierarchy, folder)
    table = tune_table(upper, "paper")
    certify_entries(table, {s.id: s for s in sites}, hierarchy.t_meas_s, upper.constraints)
    return hierarchy, upper, table, sites


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("hierarchy")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:    # the upper config's HV net lives there
        run_rounds(*levels_of(args.hierarchy, Path(tmp)), args.repeat)


def run_rounds(hierarchy, upper_config, table, sites, repeat: int) -> None:
    """The hierarchy and its ADNs alone, ``repeat`` rounds alternating; print the figures."""
    end_s = upper_config.scenario.duration_s
    adns = hierarchy.adns
    ours, alone, messages = [], [], 0
    print(f"{hierarchy.name}: {len(adns)} ADNs, {end_s:g} s; load "
          f"{os.getloadavg()[0]:.1f} at the start", flush=True)
    for round_ in range(repeat):
        order = ("hierarchy", "alone") if round_ % 2 == 0 else ("alone", "hierarchy")
        for which in order:
            # fresh levels each time: a gain schedule keeps what it tuned on demand
            upper, levels, delays = hierarchy_levels(hierarchy, upper_config, table, sites)
            t0 = time.perf_counter()
            if which == "hierarchy":
                result = simulate(upper, levels, delays)
                ours.append(time.perf_counter() - t0)
                messages, agents = len(result.run.messages), len(result.run.nodes)
            else:
                for level in levels.values():
                    run_local(level.config, level.schedule, end_s=end_s)
                alone.append(time.perf_counter() - t0)
        print(f"  round {round_ + 1}: hierarchy {ours[-1]:.2f} s, ADNs alone {alone[-1]:.2f} s",
              flush=True)
    ratio = statistics.median(ours) / statistics.median(alone)
    print(f"hierarchy run: {min(ours):.2f}-{max(ours):.2f} s "
          f"({end_s / max(ours):.1f}-{end_s / min(ours):.1f}x real time), {agents} agents, "
          f"{messages} messages")
    print(f"its ADNs alone (sum): {min(alone):.2f}-{max(alone):.2f} s; ratio of the medians "
          f"{ratio:.2f}")
    print(f"peak RSS of this process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f}"
          f" MB; load {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
