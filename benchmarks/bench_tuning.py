"""Benchmark and audit of tuning: wall and CPU per method and per phase, before/after in one run.

For every method, ``--repeats`` runs of ``adnmesh tune`` in a subprocess (wall time and the
CPU time of the process and its workers), and, with ``--baseline-rev REV``, the same runs of
the code at git revision REV (checked out in a temporary ``git worktree``, run with this venv):
both measured in the same run, so the ratio holds even though the machine's speed varies
(each source runs the first method once untimed before: numba's compiling into a fresh
worktree's cache would count in its first run).
Then one in-process run per method gives CPU and wall seconds per phase (summed over the
worker processes' chunks) and an independent audit of every entry (``adnmesh.loopmodel.evaluation.evaluate``
on ``plant_from_ders`` with the entry's weights, full step info). Figures are ranges
(min - max) over the repeats.

    .venv/bin/python benchmarks/bench_tuning.py [--config configs/simbench.yaml]
        [--methods paper,global] [--workers 2] [--repeats 3] [--baseline-rev 2b468a6]
    .venv/bin/python benchmarks/bench_tuning.py --audit tables/simbench.<sha12>.json
    .venv/bin/python benchmarks/bench_tuning.py --on-demand 100 --table T.json

``--on-demand N`` tunes N random subsets of the config on demand (:class:`OnDemandTuner`), each
with every entry of its *plant* left out of the table (an unseen plant), and prints wall and
CPU per subset (median, p99), how many the global search had to decide and the rise time over
the table's.
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: the caller's OpenBLAS setting, before this process sets it to one thread: each run
#: gets the environment it would get from the caller's shell
_CALLER_OPENBLAS = os.environ.get("OPENBLAS_NUM_THREADS")

import adnmesh  # noqa: E402

adnmesh.one_blas_thread()   # before numpy, for this process's in-process runs, as the CLI does
import numpy as np  # noqa: E402

from adnmesh.config import load_config  # noqa: E402
from adnmesh.loopmodel.evaluation import evaluate  # noqa: E402
from adnmesh.loopmodel.plant import plant_from_ders  # noqa: E402
from adnmesh.tuning.table import load_table, save_table  # noqa: E402
from adnmesh.tuning import tune_table  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def audit(config, table) -> int:
    """Re-evaluate every feasible entry; print violations and the method/global gap."""
    entries = [e for e in table.entries.values() if e.feasible]
    c = config.constraints
    violations = 0
    for e in entries:
        plant = plant_from_ders(config.ders_by_id(e.ders), config.design_t_com_s,
                                config.t_meas_s, weights=e.w)
        f = evaluate(plant, e.kp, e.ki, band_pct=c.settling_band_pct, classical=False).row(0)
        if not (f["stable"] and f["disk_margin"] >= c.disk_margin_min
                and f["overshoot_pct"] < c.overshoot_max_pct):
            violations += 1
            print(f"  VIOLATION {','.join(e.ders)}: alpha {f['disk_margin']}, "
                  f"overshoot {f['overshoot_pct']}")
    print(f"audit: {len(entries)} feasible entries re-evaluated, {violations} violations, "
          f"{len(table.entries) - len(entries)} infeasible entries")
    ratio = np.array([e.figures["design_rise_time_s"] / e.figures["global_rise_time_s"]
                      for e in entries if e.figures.get("global_rise_time_s")])
    if ratio.size:
        print(f"{table.method} rise time / global rise time over {ratio.size} subsets: "
              f"median {np.median(ratio):.4f}, 90th pct {np.quantile(ratio, 0.9):.4f}, "
              f"worst {ratio.max():.4f}, best {ratio.min():.4f}")
    weighted = sum(any(w < 1 for w in e.w.values()) for e in entries)
    backed = sum((e.figures.get("gain_back_off") or 1.0) < 1 for e in entries)
    print(f"entries with a lowered weight: {weighted}, with gains backed off: {backed}")
    return violations


def same_entries(new, base) -> None:
    """How the new table's entries compare with the baseline's: for every subset the global
    optimum's rise time (new / baseline), and for the paper method whether the path's pair
    is identical."""
    ratio, differ, paper, subsets, identical, figures = [], 0, 0, 0, 0, 0
    for e in base.entries.values():
        n = new.lookup(e.ders)
        subsets += 1
        if n is None or n.feasible != e.feasible:
            differ += 1
            continue
        identical += (n.kp, n.ki, n.w) == (e.kp, e.ki, e.w)
        g_new, g_old = n.figures.get("global_rise_time_s"), e.figures.get("global_rise_time_s")
        if g_new and g_old:
            ratio.append(g_new / g_old)
        if new.method == "paper" and e.figures.get("tuned_by") == "paper":
            paper += 1
            # the path result is the pair; its figures may differ in the last digits (a
            # candidate's step sequence depends on the other candidates in its batch)
            if n.figures.get("tuned_by") != "paper" or (n.kp, n.ki) != (e.kp, e.ki):
                differ += 1
            d_new, d_old = n.figures["design_rise_time_s"], e.figures["design_rise_time_s"]
            figures += abs(d_new / d_old - 1) > 1e-9
    r = np.array(ratio)
    rise = (f"global rise time new/baseline median {np.median(r):.6f}, range {r.min():.6f} - "
            f"{r.max():.6f}, {int(np.sum(np.abs(r - 1) > 0.005))} off by more than 0.5 %"
            if r.size else "no subset has a global rise time in both tables")
    print(f"  entries vs baseline: {subsets} subsets, feasibility or path result differs on "
          f"{differ}; {rise}" + (f"; paper path entries compared: {paper}, design rise time "
                                  f"off by more than 1e-9 (relative) on {figures}"
                                  if paper else ""))
    same_static = ((new.static is None) == (base.static is None)
                   and (new.static is None or (new.static.kp, new.static.ki)
                        == (base.static.kp, base.static.ki)))
    print(f"  gains K_P, K_I and weights W bit-identical on {identical} of {subsets}; "
          f"static pair {'identical' if same_static else 'differs'}")


def _run_cli(src: Path, config: str, method: str, workers: int, out: Path) -> tuple[float, float]:
    """(wall s, CPU s of the process and its children) of one ``adnmesh tune`` from ``src``."""
    env = dict(os.environ, PYTHONPATH=str(src))
    env.pop("OPENBLAS_NUM_THREADS", None)
    if _CALLER_OPENBLAS is not None:
        env["OPENBLAS_NUM_THREADS"] = _CALLER_OPENBLAS
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "adnmesh", "tune", config, "--method", method,
                    "--workers", str(workers), "--out", str(out)], cwd=src, env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def _span(xs) -> str:
    return f"{min(xs):.1f}" if len(xs) == 1 else f"{min(xs):.1f} - {max(xs):.1f}"


def _compare(config_path: str, methods, workers: int, repeats: int, baseline: Path | None,
             tmp: Path) -> None:
    """Before/after of the whole command, interleaved so both see the same machine.

    Each source first runs the command once untimed: numba compiles the kernels into a source
    tree's cache on its first run (a fresh baseline worktree, or a changed kernel), seconds
    in every worker that a timed run would count."""
    sources = [("new", ROOT)] + ([("baseline", baseline)] if baseline else [])
    for name, src in sources:
        _run_cli(src, str(Path(config_path).resolve()), methods[0], workers,
                 tmp / f"warm-up-{name}.json")
    for method in methods:
        res = {name: [] for name, _ in sources}
        for r in range(repeats):
            for name, src in sources:
                res[name].append(_run_cli(src, str(Path(config_path).resolve()), method,
                                          workers, tmp / f"{name}-{method}-{r}.json"))
        for name, _ in sources:
            walls, cpus = zip(*res[name])
            print(f"{method:6s} {name:8s} wall {_span(walls)} s, CPU {_span(cpus)} s "
                  f"({repeats} runs, {workers} workers)")
        if baseline:
            config = load_config(config_path)
            same_entries(load_table(tmp / f"new-{method}-0.json", config),
                         load_table(tmp / f"baseline-{method}-0.json", config))
            ratio = [b[0] / n[0] for b, n in zip(res["baseline"], res["new"])]
            ratio_cpu = [b[1] / n[1] for b, n in zip(res["baseline"], res["new"])]
            print(f"{method:6s} speed-up baseline/new: wall {min(ratio):.2f} - {max(ratio):.2f}x, "
                  f"CPU {min(ratio_cpu):.2f} - {max(ratio_cpu):.2f}x")


def _phases(config, method: str, workers: int) -> int:
    phases: dict = {}
    t0, c0 = time.perf_counter(), time.process_time()
    table = tune_table(config, method, workers, phases=phases)
    wall = time.perf_counter() - t0
    out = Path(tempfile.gettempdir()) / f"bench-table-{method}.json"
    save_table(table, out)
    print(f"method {method}: {len(table.entries)} subsets in {wall:.1f} s wall "
          f"(main process CPU {time.process_time() - c0:.1f} s) -> {out}")
    for name, (cpu, w) in phases.items():
        print(f"  {name:22s} CPU {cpu:7.1f} s   wall {w:7.1f} s (summed over chunks)")
    return audit(config, table)


def _peer(problem) -> float:
    """CPU s of a fixed peer task of the same kind (one 16-candidate constraint check of a
    fixed SimBench-like plant), to compare runs under different machine load."""
    f = np.full(len(problem.actuators), 1.0 / len(problem.actuators))
    kp, ki = np.geomspace(0.05, 0.5, 16), np.geomspace(0.01, 0.1, 16)
    c0 = time.process_time()
    problem.check(np.broadcast_to(f, (16, f.size)), kp, ki)
    return time.process_time() - c0


def on_demand(config, table, n: int) -> None:
    """On-demand tuning of ``n`` random subsets, each on an unseen plant."""
    from adnmesh.tuning import TuningProblem
    from adnmesh.tuning.ondemand import OnDemandTuner
    from adnmesh.tuning.subset_selection import random_subsets

    problem = TuningProblem(config)
    subsets = random_subsets(config.der_ids(), n, seed=1)[1:]
    warm = OnDemandTuner(config, table)
    warm.tune(subsets[0])                               # numba and caches warm
    _peer(problem)
    walls, cpus, peers, ratio, fallback, bad = [], [], [], [], 0, 0
    for s in subsets:
        tuner = OnDemandTuner(config)
        tuner.add_table(table, exclude={problem.key(problem.fractions(s)[0])})
        c0, w0 = time.process_time(), time.perf_counter()
        e = tuner.tune(s)
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
        peers.append(_peer(problem))
        fallback += e.figures.get("tuned_by") == "global"
        bad += not e.feasible
        ref = table.lookup(s)
        if ref is not None and ref.feasible:
            ratio.append(e.figures["design_rise_time_s"] / ref.figures["design_rise_time_s"])
    w, c, p = np.array(walls) * 1e3, np.array(cpus) * 1e3, np.array(peers) * 1e3
    print(f"on demand, {len(subsets)} random subsets on unseen plants: wall median "
          f"{np.median(w):.0f} ms, p99 {np.quantile(w, 0.99):.0f} ms; CPU median "
          f"{np.median(c):.0f} ms, p99 {np.quantile(c, 0.99):.0f} ms; global search decided "
          f"{fallback}; not certified {bad}")
    print(f"  peer (one 16-candidate check) CPU median {np.median(p):.1f} ms; "
          f"subset CPU / peer: median {np.median(c / p):.2f}, p99 {np.quantile(c / p, 0.99):.1f}; "
          f"load average {os.getloadavg()[0]:.1f}")
    if ratio:
        r = np.array(ratio)
        print(f"  rise time / table's: median {np.median(r):.3f}, worst {r.max():.3f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "simbench.yaml"))
    ap.add_argument("--methods", default="paper,global")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--baseline-rev", help="git revision to compare with (temporary worktree)")
    ap.add_argument("--no-phases", action="store_true", help="skip the per-phase run and audit")
    ap.add_argument("--audit", help="only audit this table")
    ap.add_argument("--on-demand", type=int, metavar="N",
                    help="only benchmark on-demand tuning of N random subsets (needs --table)")
    ap.add_argument("--table", help="table of the config (for --on-demand)")
    args = ap.parse_args(argv)
    config = load_config(args.config)
    if args.audit:
        return 1 if audit(config, load_table(args.audit, config)) else 0
    if args.on_demand:
        if not args.table:
            ap.error("--on-demand needs --table")
        on_demand(config, load_table(args.table, config), args.on_demand)
        return 0
    methods = args.methods.split(",")
    with tempfile.TemporaryDirectory(prefix="bench-tuning-") as tmp:
        base = None
        if args.baseline_rev:
            base = Path(tmp) / "baseline"
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(base),
                            args.baseline_rev], check=True, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
        try:
            _compare(args.config, methods, args.workers, args.repeats, base, Path(tmp))
        finally:
            if base is not None:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force",
                                str(base)], check=False)
    bad = 0
    if not args.no_phases:
        for method in methods:
            bad += _phases(config, method, args.workers)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
