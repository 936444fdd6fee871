"""Cost of the cascade certificate, against python-control evaluating the same nested loop.

For each upper entry of a hierarchy (``adnmesh cascade``'s sites, built here the same way), it
times, in the same run and alternating:

- ours: :func:`adnmesh.cascade.certificate.cascade_figures` (exact delays: Nyquist count, disk
  margin refined, the nested step response until settled);
- python-control: the order-10 Padé models of :func:`adnmesh.cascade.control_models.cascade_models`,
  their closed-loop poles, ``disk_margins`` on a 2,000-point grid and ``step_response`` on a
  10 ms grid over the same horizon.

It prints the ranges over ``--repeat`` rounds and the ratio of the medians, and the largest
differences between the two (disk margin, overshoot, rise time).

    python benchmarks/bench_cascade.py configs/examples/hierarchy/hv.yaml --repeat 5
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import control as ct
import numpy as np

from adnmesh.cascade.certificate import cascade_figures
from adnmesh.cascade.control_models import cascade_models
from adnmesh.cascade.upper_table import cascade_of
from adnmesh.commands.cascade import hierarchy_sites
from adnmesh.config import load_hierarchy
from adnmesh.loopmodel.step_figures import step_figures
from adnmesh.tuning.table import TableEntry


def python_control(cascade, kp, ki, horizon):
    loop, closed = cascade_models(cascade, kp, ki, order=10)
    stable = bool(np.max(closed.poles().real) < 0)
    dm, _, _ = ct.disk_margins(loop, np.geomspace(1e-3, 1e2, 2000))
    t = np.arange(0.0, horizon, 0.01)
    y = np.squeeze(ct.step_response(closed, T=t).outputs)
    return stable, float(dm), step_figures(t, y)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("hierarchy")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    hierarchy = load_hierarchy(args.hierarchy)
    sites = {s.id: s for s in hierarchy_sites(hierarchy)}
    ids = [a.id for a in hierarchy.adns]
    # one PI pair per entry, per W of its DC gain: stable, with some overshoot
    entries = []
    for n in range(1, 2 ** len(ids)):
        subset = tuple(i for b, i in enumerate(ids) if n >> b & 1)
        total = sum(sites[i].adn.capacity_w for i in subset)
        entries.append(TableEntry(subset, 0.8 / total, 0.8 / total, {i: 1.0 for i in subset}))
    cascades = [cascade_of(sites, e, hierarchy.t_meas_s) for e in entries]
    ours_t, theirs_t, diffs = [], [], []
    cascade_figures(cascades[0], entries[0].kp, entries[0].ki)        # compile
    print(f"load before: {os.getloadavg()[0]:.2f}")
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        figs = [cascade_figures(c, e.kp, e.ki) for c, e in zip(cascades, entries)]
        ours_t.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        refs = [python_control(c, e.kp, e.ki, 4 * f.settling_time_s)
                for c, e, f in zip(cascades, entries, figs)]
        theirs_t.append(time.perf_counter() - t0)
        for f, (stable, dm, step) in zip(figs, refs):
            assert stable == f.stable
            diffs.append((abs(dm - f.disk_margin) / f.disk_margin,
                          abs(step.overshoot_pct - f.overshoot_pct),
                          abs(step.rise_time_s - f.rise_time_s) / f.rise_time_s))
    n = len(entries)
    print(f"load after: {os.getloadavg()[0]:.2f}")
    print(f"{n} entries per round, {args.repeat} rounds")
    print(f"ours:           {min(ours_t) / n * 1e3:.1f}-{max(ours_t) / n * 1e3:.1f} ms per entry")
    print(f"python-control: {min(theirs_t) / n * 1e3:.1f}-{max(theirs_t) / n * 1e3:.1f} ms "
          "per entry (Padé 10, 2,000 frequencies, 10 ms steps)")
    print(f"ratio of medians: {statistics.median(theirs_t) / statistics.median(ours_t):.1f}x")
    d = np.array(diffs)
    shoot = [f.overshoot_pct for f in figs]
    print(f"the entries' overshoot: {min(shoot):.2f}-{max(shoot):.2f} %, disk margin "
          f"{min(f.disk_margin for f in figs):.2f}-{max(f.disk_margin for f in figs):.2f}")
    print(f"largest differences: disk margin {d[:, 0].max():.2e} (relative), overshoot "
          f"{d[:, 1].max():.3f} points, rise time {d[:, 2].max():.2e} (relative)")


if __name__ == "__main__":
    main()
