"""How far ``adnmesh up`` scales on this machine: the 100-DER example and cuts of it.

For each DER count N, the config is ``configs/examples/adn-100.yaml`` cut to its first N DERs
(availability events keep only those DERs; events left empty are dropped) and optionally to a
shorter scenario. Per repeat it measures, in this order:

1. the on-demand tuning of the scenario's subsets in this process (a fresh
   :class:`~adnmesh.tuning.ondemand.OnDemandTuner`, as ``up`` uses without a table): CPU per
   subset;
2. ``adnmesh up`` on the sim clock, without a table (so it tunes on demand itself), at
   ``nice -n 5``: wall time, the summary's sim speed factor (sim s per wall s of the run
   phase), the startup time, the processes (the ``up`` process and its agents), the peak
   memory of the whole process tree (sum of the processes' PSS, sampled every 0.5 s) and the
   peak RSS of its largest process; and whether every P_ref step's overshoot met the constraint.

Ranges over the repeats are printed with the 1-minute load average before and after each run.

    .venv/bin/python benchmarks/bench_scale.py --ders 25,50,100 --repeats 2
    .venv/bin/python benchmarks/bench_scale.py --source configs/examples/scale/adn-1000.yaml \
        --table T1000.json --ders 1000 --duration 60 --repeats 1    # scale mode, its table

With ``--source`` another config is cut (and ``--table`` spares the tuning: a table tuned for
the source's whole scenario serves its cuts to fewer seconds, not to fewer DERs);
``--ders-per-process N`` runs every cut in scale mode. ``--baseline-rev REV`` runs the code of
commit REV too (a ``git worktree``, ``PYTHONPATH`` set to it), alternating run by run with this
tree, a row each; a run that did not finish (a stall) is said with its last line.

    .venv/bin/python benchmarks/bench_scale.py --source configs/examples/scale/adn-1000.yaml \
        --table T1000.json --ders 1000 --duration 60 --repeats 3 --baseline-rev e9ce31c
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
SOURCE = ROOT / "configs" / "examples" / "adn-100.yaml"


def cut_down(document: dict, n_ders: int, duration_s: float | None = None) -> dict:
    """The config document with its first ``n_ders`` DERs and, with ``duration_s``, a scenario
    cut to that length (later events dropped)."""
    doc = json.loads(json.dumps(document))
    doc["ders"] = doc["ders"][:n_ders]
    keep = {d["id"] for d in doc["ders"]}
    sc = doc["scenario"]
    if duration_s is not None:
        sc["duration_s"] = duration_s
    end = sc["duration_s"]
    events = []
    for ev in sc.get("availability", []):
        ders = [d for d in ev["ders"] if d in keep]
        if ders and ev["t_s"] < end:
            events.append({**ev, "ders": ders})
    sc["availability"] = events
    sc["p_ref_steps"] = [s for s in sc.get("p_ref_steps", []) if s["t_s"] < end]
    return doc


def _tree(pid: int) -> set[int]:
    """``pid`` and all its descendants (from /proc)."""
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        found.add(p)
        try:
            for tid in os.listdir(f"/proc/{p}/task"):
                try:
                    todo += [int(c) for c in
                             Path(f"/proc/{p}/task/{tid}/children").read_text().split()]
                except OSError:
                    continue
        except OSError:
            continue
    return found


def _memory_kb(pid: int) -> tuple[int, int]:
    """(RSS, PSS) of ``pid``, kB: PSS shares each shared page among the processes mapping
    it, so the PSS of a process tree adds up to its real memory (RSS counts the shared
    libraries once per process)."""
    rss = pss = 0
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Rss:"):
                rss = int(line.split()[1])
            elif line.startswith("Pss:"):
                pss = int(line.split()[1])
    except OSError:
        pass
    return rss, pss


class _Sampler(threading.Thread):
    """Peak summed PSS, largest RSS and most processes of a process tree."""

    def __init__(self, pid: int):
        super().__init__(daemon=True)
        self.pid, self.stop = pid, threading.Event()
        self.peak_sum_kb = self.peak_one_kb = self.processes = 0

    def run(self) -> None:
        while not self.stop.is_set():
            pids = _tree(self.pid)
            mem = [_memory_kb(p) for p in pids]
            rss = [r for r, _ in mem]
            self.peak_sum_kb = max(self.peak_sum_kb, sum(p for _, p in mem))
            self.peak_one_kb = max(self.peak_one_kb, max(rss, default=0))
            self.processes = max(self.processes, sum(1 for r in rss if r > 0))
            self.stop.wait(0.5)


def tuning_cpu_per_subset(config_path: Path) -> list[float]:
    """CPU seconds of each scenario subset's on-demand tuning (fresh tuner)."""
    from adnmesh.commands.up_tables import scenario_subsets
    from adnmesh.config import load_config
    from adnmesh.tuning.ondemand import OnDemandTuner

    config = load_config(config_path)
    tuner = OnDemandTuner(config)
    out = []
    for subset in scenario_subsets(config):
        c0 = time.process_time()
        entry = tuner.tune([d for d in config.der_ids() if d in subset])
        out.append(time.process_time() - c0)
        if not entry.feasible:
            print(f"  subset of {len(subset)} DERs: not feasible ({entry.reason})")
    return out


def run_up(config_path: Path, work: Path, timeout_s: float, table: Path | None = None,
           env: dict | None = None) -> dict:
    """One ``adnmesh up`` run (sim clock; without ``table`` it tunes on demand; ``env``: of
    another source tree) with its figures."""
    summary = work / "summary.json"
    argv = ["nice", "-n", "5", sys.executable, "-m", "adnmesh", "up", str(config_path),
            "--out", str(work / "run.mcap"), "--summary-json", str(summary),
            "--table", str(table or work / "absent.table.json"), "--startup-timeout", "900"]
    load0 = os.getloadavg()[0]
    t0 = time.monotonic()
    proc = subprocess.Popen(argv, cwd=work, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)
    sampler = _Sampler(proc.pid)
    sampler.start()
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        for pid in sorted(_tree(proc.pid) - {proc.pid}):
            try:
                os.kill(pid, 9)
            except OSError:
                pass
        proc.kill()
        out, err = proc.communicate()
    wall = time.monotonic() - t0
    sampler.stop.set()
    sampler.join()
    data = json.loads(summary.read_text()) if summary.exists() else {}
    extra = data.get("extra", {})
    return {"exit": proc.returncode, "wall_s": wall, "speed": data.get("speed_factor"),
            "run_wall_s": data.get("wall_time_s"), "startup_s": extra.get("startup_s"),
            "agents": extra.get("agents"), "processes": sampler.processes,
            "pss_sum_mb": sampler.peak_sum_kb / 1024, "rss_max_mb": sampler.peak_one_kb / 1024,
            "steps": data.get("steps", []), "load": (load0, os.getloadavg()[0]),
            "stderr_tail": err.strip().splitlines()[-1:] if proc.returncode else [],
            "ended": extra.get("ended")}


def _compensated(step: dict, overshoot_max_pct: float, band: float) -> bool:
    """A summary step settled in the band with its overshoot below the limit."""
    fig = step.get("figures") or {}
    return (fig.get("overshoot_pct") is not None and fig["overshoot_pct"] < overshoot_max_pct
            and fig.get("settling_time_s") is not None
            and step.get("steady_error_w") is not None
            and abs(step["steady_error_w"]) < band * abs(step["step_w"]))


def _range(values, fmt=".1f") -> str:
    vals = [v for v in values if v is not None]
    if not vals:
        return "-"
    lo, hi = min(vals), max(vals)
    return format(lo, fmt) if lo == hi else f"{format(lo, fmt)}-{format(hi, fmt)}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ders", default="25,50,100", help="DER counts, e.g. 25,50,100")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="cut the scenario to S s of sim time (default: all 300 s)")
    parser.add_argument("--timeout", type=float, default=3600.0, metavar="S",
                        help="longest wall time of one up run")
    parser.add_argument("--source", type=Path, default=SOURCE, metavar="CONFIG",
                        help="the config to cut (default: configs/examples/adn-100.yaml)")
    parser.add_argument("--table", type=Path, metavar="JSON",
                        help="a table for the source's scenario (then nothing is tuned: e.g. "
                        "configs/examples/scale/adn-1000.yaml, tuned with 'adnmesh tune "
                        "CONFIG --subsets scenario')")
    parser.add_argument("--ders-per-process", type=int, metavar="N",
                        help="set runtime.ders_per_process (scale mode) in every cut")
    parser.add_argument("--baseline-rev", metavar="REV",
                        help="also run commit REV, alternating with this tree")
    args = parser.parse_args(argv)
    try:
        counts = [int(x) for x in args.ders.split(",")]
    except ValueError:
        parser.error(f"--ders must be a comma-separated list of integers, got {args.ders!r}")
    document = yaml.safe_load(args.source.read_text())
    most = len(document["ders"])
    if any(not 1 <= n <= most for n in counts) or args.repeats < 1:
        parser.error(f"--ders must be within 1..{most} and --repeats at least 1")
    if args.ders_per_process is not None:
        document.setdefault("runtime", {})["ders_per_process"] = args.ders_per_process
    from adnmesh.config import load_config
    constraints = load_config(args.source).constraints      # with the defaults
    limit, band = constraints.overshoot_max_pct, constraints.settling_band_pct / 100.0
    trees = {"this tree": None}
    if args.baseline_rev:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_runtime import tree_env, worktree
        trees[args.baseline_rev] = tree_env(worktree(args.baseline_rev))
    print(f"{'DERs':>4} {'procs':>5} {'wall s':>13} {'startup s':>11} {'speed x':>9} "
          f"{'PSS sum MB':>11} {'RSS max MB':>10} {'tune CPU s/subset':>18} {'steps ok':>8} "
          f"{'load':>9}")
    for n in counts:
        with tempfile.TemporaryDirectory(prefix=f"bench-scale-{n}-") as tmp:
            work = Path(tmp)
            cfg = work / f"adn-{n}.yaml"
            cfg.write_text(yaml.safe_dump(cut_down(document, n, args.duration), sort_keys=False))
            by_tree: dict[str, list] = {name: [] for name in trees}
            cpu = []
            for _ in range(args.repeats):
                if args.table is None:
                    cpu += tuning_cpu_per_subset(cfg)
                for name, env in trees.items():      # alternating run by run
                    r = run_up(cfg, work, args.timeout, args.table, env)
                    by_tree[name].append(r)
                    if r["exit"] != 0 or r["ended"] != "finished":
                        print(f"  {name}: up exited {r['exit']}, ended {r['ended']!r}: "
                              f"{' '.join(r['stderr_tail'])[:300]}")
            for name, runs in by_tree.items():
                _row(n, runs, cpu, limit, band, name if len(trees) > 1 else "")
    return 0


def _row(n: int, runs: list, cpu: list, limit: float, band: float, name: str) -> None:
    """The printed figures of one DER count's runs (of one source tree, ``name``)."""
    ok = [bool(r["steps"]) and all(_compensated(s, limit, band) for s in r["steps"])
          for r in runs]
    for r in runs:
        for s in r["steps"]:
            if not _compensated(s, limit, band):
                fig = s.get("figures") or {}
                print(f"  step at {s.get('t_s')} s not compensated: overshoot "
                      f"{fig.get('overshoot_pct')} % (limit {limit} %), settling "
                      f"{fig.get('settling_time_s')} s, steady error "
                      f"{s.get('steady_error_w')} W")
    loads = [x for r in runs for x in r["load"]]
    print(f"{n:>4} {_range([r['processes'] for r in runs], 'd'):>5} "
          f"{_range([r['wall_s'] for r in runs]):>13} "
          f"{_range([r['startup_s'] for r in runs]):>11} "
          f"{_range([r['speed'] for r in runs]):>9} "
          f"{_range([r['pss_sum_mb'] for r in runs], '.0f'):>11} "
          f"{_range([r['rss_max_mb'] for r in runs], '.0f'):>10} "
          f"{_range(cpu, '.2f'):>18} {f'{sum(ok)}/{len(ok)}':>8} {_range(loads):>9}"
          f"  {name}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
