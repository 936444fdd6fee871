#!/usr/bin/env python3
"""Benchmark of the distributed runtime (``adnmesh up``), with the HELICS baseline in the same run.

Measures, each printed as it comes:

1. the SimBench scenario of ``configs/simbench.yaml`` (600 s, 11 DER processes + CPFC +
   measurement + availability monitor) on the sim clock: wall time of the run (from the start
   announcement to the end of the clock), speed factor (simulated s per wall s), start-up time,
   clock grants per second, CPU seconds per process;
2. the coordinator's time grants per second with N agents (N - 3 identical DERs, 60 s each);
3. ``--grid-cost``: the same scenario with the grid's AC power flow in the measurement agent
   against the same config without ``grid_model`` (P_IP the summed infeeds), alternating, and
   the ratio of their wall and CPU times;
4. the same control loop as HELICS value federates (``../shared/bench/helics/run_helics.py``,
   14 federates, 10 ms steps) and the ratio of the speed factors, adnmesh / HELICS;
5. with ``--secure``: the SimBench scenario also in the secure profile (mutual TLS on every
   link, Zenoh access control; certificates made for the run), alternating with the open
   profile run by run, and the cost of security as the ratio secure / open of wall time and of
   CPU time, per pair of runs;
6. with ``--view``: the SimBench scenario with the live view streamed to a file (``up --view
   FILE.rrd``: the same work as for a viewer, without one), alternating with plain runs, and
   its cost as the ratio view / plain of wall and CPU time per pair (target: <= 1.10);
7. with ``--memory``: per agent kind (DER by type, CPFC, measurement, availability monitor)
   the modules loaded and the time from the interpreter's start to the agent built (what its
   program does before it opens its session; a fresh interpreter each), and in the SimBench
   run the PSS of every process (``/proc/PID/smaps_rollup``) when all agents are ready and at
   half the run, and the start-up time to "agents ready"; with ``--baseline-rev REV[,REV...]``
   the same for those commits (a ``git worktree`` each, run with ``PYTHONPATH`` set to it),
   alternating run by run with this tree;
8. with ``--compare``: the SimBench scenario as ``python -m adnmesh up`` of this tree and of
   every ``--baseline-rev``, and the HELICS baseline, in a rotating order, repeated: speed
   factor, wall time, CPU of every process (``RUSAGE_CHILDREN``), start-up, the clock
   protocol's Zenoh samples per DER and window (from each recording), and the ratios of the
   medians to HELICS's. Beside each run of this tree, the CPU time of its run phase alone
   (from "agents ready" for the run's wall time) and the speed that allows on this machine's
   cores (``cores x simulated s / run-phase CPU s``: no run can be faster, however its work
   is spread); in the same rotation, the scenario with all agents in one fresh interpreter and
   no bus at all (:func:`adnmesh.sim.local.run_local`, the same messages): its CPU time is the
   work itself, and the rest of a run's CPU is what processes, the bus, the clock and the
   recording cost. With HELICS measured, what 6x its speed asks of that.
9. with ``--timeline``: the SimBench scenario of this tree with every agent noting when its
   windows ran (``ADNMESH_WINDOW_TIMES``, :mod:`adnmesh.runtime.window_times`): the loop's
   stages (the DERs' windows, the measurement's, the CPFC's) and the hand-overs through ``up``
   between them, median and 10th percentile, and the speed their chain allows with nothing
   else costing anything.

It measures; it asserts nothing (targets, issue 41: speed factor >= 30 on a quiet machine,
>= 6x HELICS's in the same run, summed CPU -40 %, start-up <= HELICS's). Every measurement
is repeated (``--repeat``, default 3) and reported as min / median / max, with the load average
before each run: the machine has 2 cores shared with 14+ processes and whatever else runs. The
most robust figure is the CPU time summed over all processes (``cpu_s_total``), next to the wall
time. Usage::

    .venv/bin/python benchmarks/bench_runtime.py                 # everything
    .venv/bin/python benchmarks/bench_runtime.py --skip-helics --agents 4,14 --repeat 1
    .venv/bin/python benchmarks/bench_runtime.py --helics-python /tmp/venv-helics/bin/python \\
        --helics-steps 6000 --json out/bench.json
    .venv/bin/python benchmarks/bench_runtime.py --secure --agents '' --skip-helics
    .venv/bin/python benchmarks/bench_runtime.py --view --only-pairs --agents '' --skip-helics
    .venv/bin/python benchmarks/bench_runtime.py --view --view-config CASE.yaml \
        --view-table CASE.table.json --skip-simbench --agents '' --skip-helics
    .venv/bin/python benchmarks/bench_runtime.py --memory --baseline-rev e63e162 \
        --only-pairs --agents '' --skip-helics
    .venv/bin/python benchmarks/bench_runtime.py --compare --baseline-rev 2a8b912 \
        --only-pairs --agents ''   # this tree, the baseline and HELICS in turn
    .venv/bin/python benchmarks/bench_runtime.py --timeline --only-pairs --agents '' \
        --skip-helics

The gain table for the SimBench config is ``configs/tables/simbench.<design hash>.json`` if ``adnmesh tune``
made one that holds the subsets the scenario needs; otherwise those two entries (all DERs; CHPs
and PVs) are built here from gains checked against both design constraints (stable, disk margin
>= 1.5, overshoot < 1 %), so that nothing is tuned during the measured run.
"""

from __future__ import annotations

import argparse
import bisect
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from adnmesh.config import load_config  # noqa: E402
from adnmesh.loopmodel.evaluation import evaluate  # noqa: E402
from adnmesh.loopmodel.plant import plant_from_ders  # noqa: E402
from adnmesh.runtime.launcher import UpOptions, run  # noqa: E402
from adnmesh.tuning.table import SchedulingTable, TableEntry, default_table_path, save_table  # noqa: E402

# normalised gains (K * sum of P_inst) found by a grid search meeting both constraints
SIMBENCH_GAINS = {
    "all": (0.16, 0.768),          # 11 DERs: rise 2.5 s, overshoot 0.54 %, alpha 1.51
    "no_wt": (0.54, 0.083044),     # CHPs and PVs: rise 27.5 s, overshoot 0.98 %, alpha 1.56
}
WT_GAINS = (0.2, 0.768)            # any number of identical WTs: rise 2.4 s, 0 %, alpha 1.51


def load() -> str:
    """The 1, 5 and 15 minute load averages."""
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def spread(runs: list[dict], key: str) -> dict | None:
    """``{"min", "median", "max"}`` of ``key`` over ``runs`` (the runs where it is known;
    None if it is known in none)."""
    values = sorted(run[key] for run in runs if run.get(key) is not None)
    if not values:
        return None
    return {"min": values[0], "median": statistics.median(values), "max": values[-1]}


def repeated(measure, repeat: int, show) -> dict:
    """Run ``measure()`` ``repeat`` times, showing each run; every run and the spread of the
    figures that vary (wall time, speed factor, grants/s, CPU time)."""
    runs = []
    for _ in range(repeat):
        runs.append(measure())
        show(runs[-1])
    figures = [k for k in ("wall_s", "speed_factor", "grants_per_s", "cpu_s_total")
               if k in runs[0]]
    return {"runs": runs, **{k: spread(runs, k) for k in figures}}


def show_range(label: str, figure: dict, key: str, unit: str = "") -> None:
    r = figure[key]
    print(f"  {label}: {r['min']:g} .. {r['max']:g}{unit} (median {r['median']:g}{unit})",
          flush=True)


def checked_entry(config, ids, gains) -> TableEntry:
    ders = config.ders_by_id(ids)
    total = sum(d.p_inst_w for d in ders)
    kp, ki = gains[0] / total, gains[1] / total
    fig = evaluate(plant_from_ders(ders, config.design_t_com_s, config.t_meas_s), kp, ki)
    ok = bool(fig.stable[0]) and fig.disk_margin[0] >= config.constraints.disk_margin_min \
        and fig.overshoot_pct[0] < config.constraints.overshoot_max_pct
    if not ok:
        raise SystemExit(f"benchmark gains for {ids} violate the constraints")
    return TableEntry(tuple(ids), kp, ki, dict.fromkeys(ids, 1.0))


def simbench_table(config, workdir: Path) -> Path:
    """The tuned table if it has every subset the scenario needs (no tuning during the run),
    else a table with just those two entries."""
    from adnmesh.commands.up_tables import scenario_subsets
    from adnmesh.errors import ConfigError
    from adnmesh.tuning.table import load_table

    path = default_table_path(config)        # next to the config
    try:
        tuned = load_table(path, config)
        if all(tuned.lookup(s) is not None for s in scenario_subsets(config)):
            return path
    except ConfigError:
        pass
    table = SchedulingTable(config.sha256, {}, "benchmark", config.der_ids())
    table.add(checked_entry(config, config.der_ids(), SIMBENCH_GAINS["all"]))
    rest = [d.id for d in config.ders if d.type != "WT"]
    table.add(checked_entry(config, rest, SIMBENCH_GAINS["no_wt"]))
    out = workdir / "simbench.table.json"
    save_table(table, out)
    return out


def run_up(config_path: Path, table: Path, workdir: Path, certs: Path | None = None,
           view: Path | None = None) -> dict:
    """One run of ``adnmesh up`` on the sim clock (secure profile with ``certs``; the live
    view streamed to the file ``view``, as ``--view FILE.rrd``): its figures (CPU times
    include start-up; with ``view``, the view's thread and its last send after the run)."""
    from adnmesh.runtime.liveview import ViewTarget, open_view

    config = load_config(config_path)
    load_before = load()
    cpu0 = time.process_time()
    t0 = time.perf_counter()
    live = open_view(ViewTarget("file", view), "bench", lambda line: None) if view else None
    result = run(UpOptions(config=config, table_path=table, out=workdir / "bench.mcap",
                           certs=certs, view=live))
    if live is not None:
        live.close()
        if live.error:
            raise SystemExit(live.error)
    total = time.perf_counter() - t0
    if result.exit_code != 0:
        raise SystemExit(f"adnmesh up failed: {result.reason}; {result.problems}")
    sim_s = config.scenario.duration_s
    cpu = {"up (router, recorder, clock)": time.process_time() - cpu0,
           **{a: b.stats["cpu_s"] for a, b in sorted(result.byes.items())}}
    if live is not None:
        cpu["live view process"] = live.cpu_s
    return {
        "agents": len(result.byes), "sim_s": sim_s,
        "wall_s": round(result.wall_time_s, 2),
        "speed_factor": round(sim_s / result.wall_time_s, 2),
        "wall_incl_startup_s": round(total, 2), "startup_s": round(result.startup_s, 2),
        "grants": result.grants, "grants_per_s": round(result.grants / result.wall_time_s, 1),
        "messages": sum(result.recorded.values()),
        "cpu_s_total": round(sum(cpu.values()), 2),
        "cpu_s": {a: round(v, 2) for a, v in cpu.items()},
        "load_before": load_before, "load": load(),
    }


def wt_config(n_ders: int, duration_s: float, workdir: Path) -> tuple[Path, Path]:
    """A config with n identical WTs and one step; its one-entry table."""
    document = yaml.safe_load((REPO / "configs" / "examples" / "two-wt.yaml").read_text())
    base = document["ders"][0]
    document["ders"] = [dict(base, id=f"WT{i}", sgen=f"bench {i}", p_inst_w=2.0e6)
                        for i in range(1, n_ders + 1)]
    document["scenario"] = {"duration_s": duration_s,
                            "p_ref_steps": [{"t_s": 5, "delta_w": 1.0e6}]}
    path = workdir / f"wt{n_ders}.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    config = load_config(path)
    table = SchedulingTable(config.sha256, {}, "benchmark", config.der_ids())
    table.add(checked_entry(config, config.der_ids(), WT_GAINS))
    table_path = workdir / f"wt{n_ders}.table.json"
    save_table(table, table_path)
    return path, table_path


def alternating(measures: dict, repeat: int) -> dict:
    """Run the two ``measures`` (name -> callable giving a run's figures) in turn, ``repeat``
    pairs; each pair's ratios (second / first) of wall and CPU time, and the spreads."""
    (first, _), (second, _) = measures.items()
    pairs = []
    for _ in range(repeat):
        pair = {name: measure() for name, measure in measures.items()}
        for key in ("wall_s", "cpu_s_total"):
            pair[f"{key}_ratio"] = round(pair[second][key] / pair[first][key], 3)
        print(json.dumps({k: v if "ratio" in k else {f: v[f] for f in (
            "wall_s", "speed_factor", "cpu_s_total", "messages", "load_before")}
            for k, v in pair.items()}), flush=True)
        pairs.append(pair)
    found = {"pairs": pairs}
    for name in measures:
        runs = [p[name] for p in pairs]
        found[name] = {k: spread(runs, k) for k in ("wall_s", "speed_factor", "cpu_s_total")}
    for key in ("wall_s_ratio", "cpu_s_total_ratio"):
        found[key] = spread(pairs, key)
    return found


def secure_vs_open(config_path: Path, table: Path, workdir: Path, repeat: int) -> dict:
    """The scenario in the open and the secure profile, alternating; the ratios per pair."""
    from adnmesh.runtime.certificates import issue
    from adnmesh.runtime.identity import identities

    certs = workdir / "certs"
    issue(certs, identities(load_config(config_path)))
    return alternating({"open": lambda: run_up(config_path, table, workdir),
                        "secure": lambda: run_up(config_path, table, workdir, certs)}, repeat)


def view_vs_plain(config_path: Path, table: Path, workdir: Path, repeat: int) -> dict:
    """The scenario without and with the live view (``--view FILE.rrd``), alternating; the
    ratios per pair and the size of the view's file."""
    rrd = workdir / "view.rrd"
    found = alternating({"plain": lambda: run_up(config_path, table, workdir),
                         "view": lambda: run_up(config_path, table, workdir, view=rrd)},
                        repeat)
    found["view_rrd_bytes"] = rrd.stat().st_size
    return found


def show_pairs(found: dict, names: tuple[str, str]) -> None:
    for name in names:
        show_range(f"{name}: wall time", found[name], "wall_s", " s")
        show_range(f"{name}: CPU time, all processes", found[name], "cpu_s_total", " s")
    show_range(f"{names[1]} / {names[0]}, wall time", found, "wall_s_ratio")
    show_range(f"{names[1]} / {names[0]}, CPU time", found, "cpu_s_total_ratio")


def without_grid(config_path: Path, workdir: Path) -> Path:
    """The config without its ``grid_model`` (P_IP = rest_of_grid_w + the summed infeeds)."""
    document = yaml.safe_load(config_path.read_text())
    document.pop("grid_model", None)
    path = workdir / f"{config_path.stem}-no-grid.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def grid_cost(config_path: Path, workdir: Path, repeat: int) -> dict:
    """Wall and CPU time with and without the grid, alternating runs; ratios of the medians."""
    plain = without_grid(config_path, workdir)
    tables = {"grid": simbench_table(load_config(config_path), workdir)}
    tables["summed"] = simbench_table(load_config(plain), workdir / "plain")
    runs: dict[str, list] = {"grid": [], "summed": []}
    for _ in range(repeat):
        for name, path in (("grid", config_path), ("summed", plain)):
            figures = run_up(path, tables[name], workdir)
            figures.pop("cpu_s")
            runs[name].append(figures)
            print(f"  {name:6s}: wall {figures['wall_s']} s, CPU {figures['cpu_s_total']} s "
                  f"(load {figures['load']})", flush=True)
    out = {name: {k: spread(r, k) for k in ("wall_s", "cpu_s_total")} for name, r in runs.items()}
    for key in ("wall_s", "cpu_s_total"):
        out[f"ratio_{key}"] = round(out["grid"][key]["median"] / out["summed"][key]["median"], 3)
    return out


# -- memory and start-up per agent kind (--memory) ---------------------------------------------

PROBE = """
import sys, time
t0 = time.perf_counter()
kind, config_path, table_path, der, model = sys.argv[1:6]
import adnmesh.agents.{program}
t_import = time.perf_counter() - t0
from adnmesh.config import load_config
from adnmesh.control.registry import build_agent
from adnmesh.sim.node import Node
config = load_config(config_path)
if kind == "cpfc":
    from adnmesh.control.cpfc_controller import GainSchedule
    from adnmesh.tuning.table import load_table
    agent = build_agent("cpfc", config, GainSchedule(config, load_table(table_path, config)))
elif der != "-":
    from adnmesh.names import der_agent_id
    from adnmesh.control import der_model
    (d,) = config.ders_by_id([der])
    if hasattr(der_model, "params_from_json"):   # handed over by up, as up does
        agent = build_agent(der_agent_id(der), config, p_avail_w=d.p_inst_w,
                            der_params=der_model.params_from_json(model))
    else:                                         # before: calibrated in the process
        agent = build_agent(der_agent_id(der), config, p_avail_w=d.p_inst_w)
else:
    agent = build_agent(kind, config)
Node.for_config(agent, config)
t_built = time.perf_counter() - t0
import json
heavy = ("scipy", "numba", "pandas", "pyarrow", "pandapower", "lightsim2grid")
print(json.dumps({"modules": len(sys.modules), "import_s": round(t_import, 3),
                  "built_s": round(t_built, 3),
                  "heavy": [h for h in heavy if h in sys.modules]}))
"""


def probe_kinds(tree: Path, config_path: Path, table: Path) -> dict:
    """Per agent kind (a DER of each type): modules loaded and time from the interpreter's
    start to the module imported and to the agent built, in a fresh interpreter of ``tree``
    (a DER given its available power, and its model parameters where ``tree``'s ``up`` hands
    them over)."""
    config = load_config(config_path)
    kinds = {f"der {t}": ("der", next(d.id for d in config.ders if d.type == t))
             for t in dict.fromkeys(d.type for d in config.ders)}
    kinds.update({k: (k, "-") for k in ("cpfc", "measurement", "availability")})
    found = {}
    for name, (kind, der) in kinds.items():
        model = "-"
        if der != "-":
            from adnmesh.control.der_model import der_params, params_json
            (d,) = config.ders_by_id([der])
            model = params_json(der_params(d, config, d.p_inst_w))
        out = subprocess.run([sys.executable, "-c", PROBE.replace("{program}", kind), kind,
                              str(config_path), str(table), der, model], env=tree_env(tree),
                             cwd=tree, capture_output=True, text=True, timeout=300, check=True)
        found[name] = json.loads(out.stdout.splitlines()[-1])
    return found


def tree_env(tree: Path) -> dict:
    """The environment of a process of the adnmesh source ``tree`` (as ``adnmesh`` sets it
    for itself: OpenBLAS on one thread)."""
    return dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1")


def pss_kb(pid: int) -> int | None:
    """Proportional set size of process ``pid``, kB (None: gone)."""
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def stat_fields(pid: int) -> list[str] | None:
    """The fields of ``/proc/PID/stat`` after the process's name (``[0]`` its state, ``[1]``
    its parent, ``[11:15]`` utime, stime, cutime, cstime in ticks); None if it is gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def descendants(parent: int) -> set[int]:
    """Every process below ``parent`` (from /proc)."""
    parents = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        fields = stat_fields(int(stat.parent.name))
        if fields is not None:
            parents[int(stat.parent.name)] = int(fields[1])
    below, todo = set(), [parent]
    while todo:
        here = todo.pop()
        children = {pid for pid, ppid in parents.items() if ppid == here} - below
        below |= children
        todo += children
    return below


def agent_pids(parent: int) -> dict[str, int]:
    """The processes below ``parent`` that run an agent program: agent (``cpfc``, ``der
    SGen1``...) -> pid; a program started as such is known by its command line, an agent forked
    by the fork server (``runtime.agent_start: fork``) by its name (``/proc/PID/comm``), the
    fork server itself as ``fork server``."""
    found = {}
    for pid in descendants(parent):
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            name = Path(f"/proc/{pid}/comm").read_text().strip()
        except OSError:
            continue
        words = [a.decode() for a in argv if a]
        program = next((w for w in words if w.startswith("adnmesh.")), None)
        if program == "adnmesh.runtime.forkserver":
            found["fork server" if name == "adnmesh forks" else name] = pid
        elif program is not None and program.startswith("adnmesh.agents."):
            kind = program.rsplit(".", 1)[1]
            if "--der" in words:
                kind += " " + words[words.index("--der") + 1]
            found[kind] = pid
    return found


def pss_sample(up_pid: int, kinds: dict[str, str]) -> dict:
    """PSS, MB, of ``up`` (router, clock, recorder) and its agent processes now: the median
    per kind (``der WT``...), ``up``'s and the total."""
    per_agent = {a: pss_kb(pid) for a, pid in agent_pids(up_pid).items()}
    per_agent = {a: kb / 1024 for a, kb in per_agent.items() if kb is not None}
    by_kind: dict[str, list] = {}
    for agent, mb in per_agent.items():
        by_kind.setdefault(kinds.get(agent, agent), []).append(mb)
    out = {k: round(statistics.median(v), 1) for k, v in sorted(by_kind.items())}
    out["up"] = round((pss_kb(up_pid) or 0) / 1024, 1)
    out["total"] = round(sum(per_agent.values()) + out["up"], 1)
    out["agents"] = len(per_agent)
    return out


def memory_run(tree: Path, config_path: Path, table: Path, workdir: Path) -> dict:
    """One ``adnmesh up CONFIG`` of ``tree`` on the sim clock: its start-up to "agents ready"
    (as it says), the PSS of every process when all are ready and half-way through the run
    (the sample, every 0.25 s, in the middle of the run's wall time), MB."""
    config = load_config(config_path)
    kinds = {f"der {d.id}": f"der {d.type}" for d in config.ders}
    argv = [sys.executable, "-m", "adnmesh", "up", str(config_path), "--table", str(table),
            "--out", str(workdir / "memory.mcap")]
    load_before = load()
    up = subprocess.Popen(argv, env=tree_env(tree), cwd=tree, stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, text=True)
    startup_s, ready, during = None, None, []
    try:
        for line in up.stderr:
            found = re.search(r"agents ready in ([0-9.]+) s", line)
            if found:
                startup_s, ready = float(found.group(1)), pss_sample(up.pid, kinds)
                break
        while up.poll() is None and ready is not None:
            during.append(pss_sample(up.pid, kinds))
            time.sleep(0.25)
        rest = up.stderr.read()
    finally:
        if up.poll() is None:
            up.terminate()
        code = up.wait()
    if code != 0 or ready is None:
        raise SystemExit(f"adnmesh up ({tree}) failed with exit code {code}: {rest[-2000:]}")
    during = [d for d in during if d["agents"] == ready["agents"]]
    return {"startup_s": startup_s, "pss_mb": {"ready": ready,
                                               "mid_run": during[len(during) // 2]},
            "load_before": load_before}


def helics_script() -> Path:
    """The HELICS baseline's runner, ``../shared/bench/helics/run_helics.py``."""
    script = REPO.parent / "shared" / "bench" / "helics" / "run_helics.py"
    return script if script.exists() else Path("/work/shared/bench/helics/run_helics.py")


def helics_memory_run(python: str, steps: int, nfeds: int, core: str) -> dict:
    """One run of the HELICS baseline with the PSS of its broker and federates sampled every
    0.25 s: the sample half-way through the samples that have every process, MB."""
    script = helics_script()
    load_before = load()
    runner = subprocess.Popen([python, str(script), "--nfeds", str(nfeds), "--core", core,
                               "--steps", str(steps), "--port", str(25000 + os.getpid() % 1000),
                               "--timeout", "1800"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    samples = []
    try:
        while runner.poll() is None:
            pss = [pss_kb(pid) for pid in descendants(runner.pid)]
            pss = [kb / 1024 for kb in pss if kb is not None]
            samples.append((len(pss), sum(pss), max(pss, default=0.0)))
            time.sleep(0.25)
    finally:
        if runner.poll() is None:
            runner.kill()       # our own child, by handle (PID)
        runner.wait()
    most = max(n for n, _, _ in samples)
    full = [s for s in samples if s[0] == most]
    processes, total, largest = full[len(full) // 2]
    return {"processes": processes, "total": round(total, 1),
            "per_process": round(total / processes, 1), "largest": round(largest, 1),
            "load_before": load_before}


def worktree(rev: str) -> Path:
    """A detached worktree of ``rev`` under /tmp (made once)."""
    sha = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short=12", rev],
                         capture_output=True, text=True, check=True).stdout.strip()
    path = Path(tempfile.gettempdir()) / f"adnmesh-bench-{sha}"
    if not path.exists():
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(path), sha],
                       capture_output=True, check=True)
    return path


def memory_compare(args, table: Path, workdir: Path) -> dict:
    """``--memory``: this tree and every ``--baseline-rev``, alternating run by run; per tree
    the probes (once), and start-up and PSS as ranges over the runs."""
    config_path = Path(args.config).resolve()
    trees = {"this tree": REPO}
    for rev in [r.strip() for r in (args.baseline_rev or "").split(",") if r.strip()]:
        trees[rev] = worktree(rev)
    probes = {}
    for name, tree in trees.items():
        probes[name] = probe_kinds(tree, config_path, table)
        for kind, p in probes[name].items():
            print(f"  {name:>12}: {kind:14s} {p['modules']:5d} modules, import "
                  f"{p['import_s']:.2f} s, built {p['built_s']:.2f} s "
                  f"{' '.join(p['heavy'])}", flush=True)
    runs: dict[str, list] = {name: [] for name in trees}
    for i in range(args.repeat):
        for name, tree in (trees.items() if i % 2 == 0 else reversed(trees.items())):
            r = memory_run(tree, config_path, table, workdir)
            runs[name].append(r)
            print(f"  {name:>12}: start-up {r['startup_s']} s, PSS total ready "
                  f"{r['pss_mb']['ready']['total']} MB, mid-run "
                  f"{r['pss_mb']['mid_run']['total']} MB (load {r['load_before']})",
                  flush=True)
    if not args.skip_helics:
        runs["HELICS"] = []
        for _ in range(args.repeat):
            r = helics_memory_run(args.helics_python, args.helics_steps, 14, args.helics_core)
            runs["HELICS"].append(r)
            print(f"        HELICS: PSS mid-run {r['total']} MB in {r['processes']} processes "
                  f"(broker and federates; {r['per_process']} MB each, largest "
                  f"{r['largest']} MB; load {r['load_before']})", flush=True)
    summary = {}
    for name, found in runs.items():
        if name == "HELICS":
            summary[name] = {k: spread(found, k) for k in ("total", "per_process", "largest")}
            print(f"  HELICS: PSS mid-run, MB (min .. max): total "
                  f"{summary[name]['total']['min']:g}..{summary[name]['total']['max']:g}",
                  flush=True)
            continue
        out = summary[name] = {"startup_s": spread(found, "startup_s"), "pss_mb": {}}
        show_range(f"{name}: start-up to agents ready", out, "startup_s", " s")
        for when in ("ready", "mid_run"):
            keys = found[0]["pss_mb"][when]
            pss = out["pss_mb"][when] = {k: spread([f["pss_mb"][when] for f in found], k)
                                         for k in keys}
            print(f"  {name}: PSS at {when}, MB (min .. max): " + ", ".join(
                f"{k} {v['min']:g}..{v['max']:g}" for k, v in pss.items() if k != "agents"),
                flush=True)
    if "HELICS" in summary:
        helics = summary["HELICS"]["total"]["median"]
        for name in trees:
            mine = summary[name]["pss_mb"]["mid_run"]["total"]["median"]
            print(f"  {name} / HELICS, summed PSS mid-run (medians): {mine / helics:.2f}x",
                  flush=True)
    return {"probes": probes, "runs": runs, "summary": summary}


def clock_traffic(recording: Path) -> dict:
    """Zenoh samples of the clock protocol per DER per window (a window: one grant), from a
    recording of any revision: in, the grants plus start and stop; out, the reports put on
    their own key plus the goodbye. A DER that reports its stats (``samples_clock_out``:
    reports that rode a data sample are not on their own key) is counted from them; an older
    one put every report on its own key, so its recorded reports are its samples out."""
    from adnmesh.recording import read_recording

    grants: dict[str, int] = {}
    reports: dict[str, int] = {}
    stats: dict[str, dict] = {}
    data_out: dict[str, int] = {}
    for m in read_recording(recording).messages:
        parts = m.topic.split("/clock/", 1)
        if len(parts) == 2 and "/der/" in "/" + parts[1]:
            kind, agent = parts[1].split("/", 1)
            if kind == "grant":
                grants[agent] = grants.get(agent, 0) + 1
            elif kind == "report":
                reports[agent] = reports.get(agent, 0) + 1
            elif kind == "bye":
                stats[agent] = json.loads(m.data)["stats"]
    per_der = []
    for agent, windows in grants.items():
        st = stats.get(agent, {})
        if "samples_clock_out" in st:
            out = st["samples_clock_out"] + 1
            clock_in = st["samples_clock_in"]
            data_out[agent] = st["samples_data_out"]
        else:
            out, clock_in = reports.get(agent, 0) + 1, windows + 2
        per_der.append({"windows": windows, "out": out / windows, "in": clock_in / windows,
                        "data_out": data_out[agent] / windows if agent in data_out else None})
    def mean(k):
        values = [d[k] for d in per_der if d[k] is not None]
        return round(statistics.mean(values), 3) if values else None
    return {"ders": len(per_der), "windows_per_der": mean("windows"),
            "clock_out_per_window": mean("out"), "clock_in_per_window": mean("in"),
            "data_out_per_window": mean("data_out")}


def speed_run(tree: Path, config_path: Path, table: Path, workdir: Path,
              env: dict[str, str] | None = None) -> dict:
    """One ``python -m adnmesh up CONFIG`` of ``tree`` on the sim clock, in a subprocess: its
    wall time and speed factor (as it prints them), start-up, the CPU time of ``up`` and every
    agent (``RUSAGE_CHILDREN``: ``up`` reaps its agents), the CPU time of its run phase alone
    (:class:`RunPhaseCpu`) and the clock's samples per DER and window (:func:`clock_traffic`);
    ``env``: more environment for the run."""
    import resource

    out = workdir / "speed.mcap"
    argv = [sys.executable, "-m", "adnmesh", "up", str(config_path), "--table", str(table),
            "--out", str(out)]
    load_before = load()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    said: dict[str, list[str]] = {"stdout": [], "stderr": []}
    with subprocess.Popen(argv, env={**tree_env(tree), **(env or {})}, cwd=tree,
                          stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True) as proc:
        phase = RunPhaseCpu(proc.pid)

        def read(stream, lines: list[str]) -> None:
            for line in stream:
                lines.append(line)
                if "agents ready in" in line:   # logged as the run phase starts
                    phase.start()

        readers = [threading.Thread(target=read, args=(stream, said[name]), daemon=True)
                   for name, stream in (("stdout", proc.stdout), ("stderr", proc.stderr))]
        for reader in readers:
            reader.start()
        try:
            proc.wait(timeout=1800)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            phase.stop()
            for reader in readers:
                reader.join(30)
        if any(reader.is_alive() for reader in readers):
            raise SystemExit(f"adnmesh up ({tree}): its output stayed open after it ended "
                             "(a process of the run lives on)")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    stdout, stderr = "".join(said["stdout"]), "".join(said["stderr"])
    found = re.search(r"run: ([0-9.]+) s simulated in ([0-9.]+) s wall", stdout)
    ready = re.search(r"agents ready in ([0-9.]+) s", stderr)
    if proc.returncode != 0 or not found:
        raise SystemExit(f"adnmesh up ({tree}) failed with exit code {proc.returncode}: "
                         f"{stderr[-2000:]}")
    sim_s, wall_s = float(found.group(1)), float(found.group(2))
    return {"speed_factor": round(sim_s / wall_s, 2), "wall_s": wall_s, "sim_s": sim_s,
            "startup_s": float(ready.group(1)) if ready else None,
            "cpu_s_total": round(after.ru_utime + after.ru_stime - before.ru_utime
                                 - before.ru_stime, 2),
            "cpu_s_run": phase.over(wall_s),
            "clock": clock_traffic(out), "load_before": load_before, "load": load()}


class RunPhaseCpu:
    """The CPU time ``up`` and its processes spend in the run phase alone: from "agents
    ready" (:meth:`start`, which takes the process tree then) for the run's wall time
    (:meth:`over`), read from ``/proc`` every :attr:`PERIOD_S` and interpolated.

    ``up`` says "agents ready" just before it starts its run timer (a collection of its heap
    comes between, tens of milliseconds), and the line reaches this process a little later:
    the window is that much late against ``up``'s, well under 1 % of a SimBench run. Only the
    processes there at the start are read: if one of them ends within the window (a killed
    agent, whose restart would not be counted), :meth:`over` says None."""

    PERIOD_S = 0.05

    def __init__(self, root: int) -> None:
        self.root = root
        self.samples: list[tuple[float, float]] = []   # (monotonic s, CPU s of the tree)
        self._pids: list[int] = []
        self._ended_at: float | None = None            # when the first of them was gone
        self._done = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self._thread is not None:                    # once
            return
        self._pids = [self.root, *descendants(self.root)]
        self.samples.append((time.monotonic(), self._cpu_s()))
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._done.set()
        if self._thread is not None:
            self._thread.join()

    def over(self, wall_s: float) -> float | None:
        """CPU s of the tree from the start to ``wall_s`` later (None: not measured)."""
        if len(self.samples) < 2:
            return None
        t0, c0 = self.samples[0]
        end = t0 + wall_s
        if self._ended_at is not None and self._ended_at <= end:
            return None
        for (ta, ca), (tb, cb) in zip(self.samples, self.samples[1:]):
            if tb >= end:
                return round(ca + (cb - ca) * (end - ta) / (tb - ta) - c0, 2)
        return None

    def _sample(self) -> None:
        while not self._done.wait(self.PERIOD_S):
            self.samples.append((time.monotonic(), self._cpu_s()))

    def _cpu_s(self) -> float:
        """utime + stime of the tree's processes and of the children they reaped, s (notes
        when the first of them is gone)."""
        ticks = 0
        for pid in self._pids:
            fields = stat_fields(pid)
            if fields is None:
                if self._ended_at is None:
                    self._ended_at = time.monotonic()
                continue
            ticks += sum(int(f) for f in fields[11:15])
        return ticks / os.sysconf("SC_CLK_TCK")


def speed_compare(args, table: Path, workdir: Path) -> dict:
    """``--compare``: the SimBench scenario with this tree, every ``--baseline-rev`` and (unless
    ``--skip-helics``) the HELICS baseline, one after the other in a rotating order, repeated;
    per contestant the speed factor, wall time, summed CPU and start-up as ranges, and the
    ratios to HELICS's median speed factor."""
    config_path = Path(args.config).resolve()
    trees = {"this tree": REPO}
    for rev in [r.strip() for r in (args.baseline_rev or "").split(",") if r.strip()]:
        trees[rev] = worktree(rev)
    names = list(trees) + [BUS_FREE] + ([] if args.skip_helics else ["HELICS"])
    runs: dict[str, list] = {name: [] for name in names}
    for i in range(args.repeat):
        order = names[i % len(names):] + names[:i % len(names)]
        for name in order:
            if name == "HELICS":
                r = run_helics(args.helics_python, args.helics_steps, 14, args.helics_core)
                r["wall_s"], r["cpu_s_total"] = r["wall_exec_s"], r["cpu_all_children_s"]
                print(f"  {name:>12}: speed factor {r['speed_factor']}x, wall {r['wall_s']} s, "
                      f"CPU {r['cpu_s_total']} s, start-up {r['startup_s']} s "
                      f"(load {r['load_before']})", flush=True)
            elif name == BUS_FREE:
                r = bus_free(config_path, table)
                print(f"  {name:>12}: CPU {r['cpu_s']} s, all agents in one process, no bus "
                      f"(load {r['load_before']})", flush=True)
            else:
                r = speed_run(trees[name], config_path, table, workdir)
                r["cpu_bound"] = cpu_bound(r["sim_s"], r["cpu_s_run"])
                c = r["clock"]
                print(f"  {name:>12}: speed factor {r['speed_factor']}x, wall {r['wall_s']} s, "
                      f"CPU {r['cpu_s_total']} s ({r['cpu_s_run']} s in the run phase: "
                      f"{r['cpu_bound']}x at most on {cores()} cores), "
                      f"start-up {r['startup_s']} s; per DER and window: clock samples in "
                      f"{c['clock_in_per_window']}, out {c['clock_out_per_window']} "
                      f"(load {r['load_before']})", flush=True)
            runs[name].append(r)
    summary = {}
    for name, found in runs.items():
        keys = (("cpu_s",) if name == BUS_FREE else
                ("speed_factor", "wall_s", "cpu_s_total", "startup_s")
                + (("cpu_s_run", "cpu_bound") if name != "HELICS" else ()))
        out = summary[name] = {k: spread(found, k) for k in keys}
        print(f"  {name}: " + ", ".join(
            f"{k} {v['min']:g}..{v['max']:g} (median {v['median']:g})" if v else f"{k} n/a"
            for k, v in out.items()), flush=True)
    if "HELICS" in summary:
        theirs = summary["HELICS"]
        for name in trees:
            ours = summary[name]
            ratio = {label: round(ours[key]["median"] / theirs[key]["median"], 2)
                     if ours[key] and theirs[key] else None
                     for label, key in (("speed", "speed_factor"), ("cpu", "cpu_s_total"),
                                        ("startup", "startup_s"))}
            summary[name]["to_helics"] = ratio
            print(f"  {name} / HELICS (medians): speed {ratio['speed']}x, CPU "
                  f"{ratio['cpu']}x, start-up {ratio['startup']}x", flush=True)
    asks(summary, runs["this tree"][0]["sim_s"])
    return {"runs": runs, "summary": summary}


BUS_FREE = "bus-free"
"""``--compare``'s name for the scenario with all agents in one process and no bus."""


def asks(summary: dict, sim_s: float) -> None:
    """Print what the work itself takes of this tree's run phase (medians) and, with HELICS
    measured, what 6x its speed allows."""
    work, ours = summary[BUS_FREE]["cpu_s"], summary["this tree"]["cpu_s_run"]
    if work is None or ours is None:
        print("  run-phase CPU not measured: no comparison with the work itself", flush=True)
        return
    work, ours = work["median"], ours["median"]
    print(f"  the work itself (all agents in one process, no bus): {work:g} s CPU (median), "
          f"{sim_s / work:.1f}x on one core; of this tree's run phase ({ours:g} s CPU, "
          f"median), {ours - work:.1f} s ({(ours - work) / ours:.0%}) is processes, bus, clock "
          "and recording", flush=True)
    if "HELICS" in summary:
        target = 6 * summary["HELICS"]["speed_factor"]["median"]
        allowed = cores() * sim_s / target
        print(f"  6x HELICS's median speed is {target:.1f}x: on {cores()} cores the run phase "
              f"may then take at most {allowed:.1f} s of CPU, {allowed - work:.1f} s beyond "
              f"the work itself (today {ours - work:.1f} s)", flush=True)


def cores() -> int:
    """The CPUs this process (and the runs it starts) may run on."""
    return len(os.sched_getaffinity(0))


def cpu_bound(sim_s: float, cpu_s: float | None) -> float | None:
    """The speed factor ``cpu_s`` of CPU time allows on :func:`cores` for ``sim_s`` of
    simulated time (all of them busy all the time with the run's work); None if ``cpu_s``
    is."""
    return None if cpu_s is None else round(cores() * sim_s / cpu_s, 1)


def bus_free(config_path: Path, table: Path) -> dict:
    """The CPU time of the scenario with every agent in one fresh interpreter of this tree
    and no bus (:func:`adnmesh.sim.local.run_local`: the same nodes, clock and messages as
    ``up``), s, and the load before."""
    program = (
        "import sys, time\n"
        "from adnmesh.config import load_config\n"
        "from adnmesh.control.cpfc_controller import GainSchedule\n"
        "from adnmesh.sim.local import run_local\n"
        "from adnmesh.tuning.table import load_table\n"
        "config = load_config(sys.argv[1])\n"
        "schedule = GainSchedule(config, load_table(sys.argv[2], config))\n"
        "cpu = time.process_time()\n"
        "run_local(config, schedule)\n"
        "print(time.process_time() - cpu)\n")
    load_before = load()
    done = subprocess.run([sys.executable, "-c", program, str(config_path), str(table)],
                          env=tree_env(REPO), cwd=REPO, capture_output=True, text=True,
                          timeout=1800, check=False)
    if done.returncode != 0:
        raise SystemExit(f"run_local failed: {done.stderr[-2000:]}")
    return {"cpu_s": round(float(done.stdout.split()[-1]), 2), "load_before": load_before}


def timeline(config_path: Path, table: Path, workdir: Path, repeat: int) -> list[dict]:
    """``--timeline``: the SimBench scenario of this tree with every agent noting when its
    windows ran (:mod:`adnmesh.runtime.window_times`), ``repeat`` times; per run the speed
    factor and the cycle's stages (:func:`stage_timeline`)."""
    from adnmesh.runtime.window_times import ENV

    found = []
    for i in range(repeat):
        directory = workdir / f"windows-{i}"
        directory.mkdir()
        run = speed_run(REPO, config_path, table, workdir, {ENV: str(directory)})
        stages = stage_timeline(directory)
        found.append({"speed_factor": run["speed_factor"], **stages})
        print(f"  speed factor {run['speed_factor']}x (load {run['load_before']})", flush=True)
        if "missing" in stages:
            print(f"  no timeline: {stages['missing']}", flush=True)
            continue
        print(f"  {stages['cycles']} cycles of {stages['cycle_s']:g} s of sim time, ms "
              "(median / p10):", flush=True)
        for name, figure in stages["stages"].items():
            print(f"    {name:44s} {figure['median_ms']:6.2f} / {figure['p10_ms']:5.2f}",
                  flush=True)
        work = stages["window_cpu_ms"]
        print(f"  a window's CPU time (median): a DER's {work['der']:.2f} ms, the "
              f"measurement's {work['measurement']:.2f} ms, the CPFC's {work['cpfc']:.2f} ms",
              flush=True)
        print(f"  the chain with nothing else costing anything (the windows at their median "
              f"CPU time, the DERs' spread over {cores()} cores, the hand-overs at their p10): "
              f"{stages['chain_ms']:.2f} ms a cycle, {stages['chain_speed']:.1f}x at most",
              flush=True)
    return found


def stage_timeline(directory: Path) -> dict:
    """The cycle of the SimBench loop from the window times in ``directory``: the DERs'
    windows, then the measurement's (no delay on the physical link), then the CPFC's, then the
    DERs' of the next cycle, and the hand-overs between them through ``up`` (from a window's
    end to the next stage's grant; a window begins once its grant and the messages it expects
    are in); each as the median and 10th percentile over the cycles every agent ran whole, ms.
    The chain: a cycle with the DERs' windows spread over :func:`cores`, every window at its
    median CPU time (its thread's), the hand-overs at their 10th percentile and nothing else
    costing anything. ``{"missing": why}`` if the files do not give a cycle."""
    windows: dict[str, list] = {}
    for path in directory.glob("*.json"):   # a killed and restarted agent: two files
        data = json.loads(path.read_text())
        windows.setdefault(data["agent"], []).extend(tuple(w) for w in data["windows"])
    ders = {a: {w[0]: w for w in ws} for a, ws in windows.items() if a.startswith("der/")}
    if not ders or not windows.get("measurement") or not windows.get("cpfc"):
        return {"missing": f"window times of {sorted(windows) or 'no agent'} only"}
    measurement = sorted(windows["measurement"])
    cpfc = sorted(windows["cpfc"])
    cpfc_untils = [w[0] for w in cpfc]
    ends = [w[0] for w in measurement]
    cycle = int(statistics.median(b - a for a, b in zip(ends, ends[1:]))) if len(ends) > 1 \
        else 0
    names = ("the DERs' windows, first grant to last end",
             "-> measurement's grant", "measurement: grant to begin", "measurement's window",
             "-> CPFC's grant", "CPFC: grant to begin", "CPFC's window",
             "-> the next cycle's first DER grant", "whole cycle")
    stages: dict[str, list[int]] = {names[0]: [], "one DER's window": [],
                                    **{k: [] for k in names[1:]}}
    cpu: dict[str, list[int]] = {"der": [], "measurement": [], "cpfc": []}
    for until, granted, began, ended, spent in measurement:
        mine = [d.get(until) for d in ders.values()]
        after = [d.get(until + cycle) for d in ders.values()]
        at = bisect.bisect_right(cpfc_untils, until)   # the CPFC's next window in sim time
        c = cpfc[at] if at < len(cpfc) and cpfc[at][0] <= until + cycle else None
        if not cycle or None in mine or None in after or c is None or granted is None \
                or c[1] is None or any(w[1] is None for w in after):
            continue
        last_der, first_next = max(w[3] for w in mine), min(w[1] for w in after)
        last_next = max(w[3] for w in after)
        for key, value in zip(names, (
                last_next - first_next, granted - last_der, began - granted, ended - began,
                c[1] - ended, c[2] - c[1], c[3] - c[2], first_next - c[3],
                last_next - last_der)):
            stages[key].append(value)
        stages["one DER's window"] += [w[3] - w[2] for w in after]
        cpu["der"] += [w[4] for w in after]
        cpu["measurement"].append(spent)
        cpu["cpfc"].append(c[4])
    if not stages["whole cycle"]:
        return {"missing": "no cycle that every agent ran whole"}

    def figure(values: list[int]) -> dict:
        ordered = sorted(values)
        return {"median_ms": statistics.median(ordered) / 1e6,
                "p10_ms": ordered[len(ordered) // 10] / 1e6}

    out = {k: figure(v) for k, v in stages.items()}
    work = {k: statistics.median(v) / 1e6 for k, v in cpu.items()}
    hand_overs = sum(out[k]["p10_ms"] for k in ("-> measurement's grant", "-> CPFC's grant",
                                                "-> the next cycle's first DER grant"))
    chain = len(ders) * work["der"] / cores() + work["measurement"] + work["cpfc"] + hand_overs
    return {"cycles": len(stages["whole cycle"]), "cycle_s": cycle / 1e9, "stages": out,
            "window_cpu_ms": work, "chain_ms": chain, "chain_speed": cycle / 1e6 / chain}


def run_helics(python: str, steps: int, nfeds: int, core: str) -> dict:
    """One run of the HELICS baseline: the JSON line of ``run_helics.py``."""
    load_before = load()
    script = helics_script()
    result = subprocess.run([python, str(script), "--nfeds", str(nfeds), "--core", core,
                             "--steps", str(steps), "--port", str(24000 + os.getpid() % 1000),
                             "--timeout", "1800"],
                            capture_output=True, text=True, timeout=3600, check=False)
    lines = [line for line in result.stdout.splitlines() if line.startswith("{")]
    if not lines:
        raise SystemExit(f"HELICS run failed:\n{result.stdout}\n{result.stderr}")
    data = json.loads(lines[-1])
    data["load_before"], data["load"] = load_before, load()
    return data


def view_pairs(figures: dict, args, config_path: Path, table: Path, workdir: Path) -> None:
    """Without and with the live view, alternating (SimBench, or ``--view-config``)."""
    what = "SimBench scenario"
    if args.view_config:
        config_path, table = Path(args.view_config), Path(args.view_table)
        what = f"{config_path.name}, {load_config(config_path).scenario.duration_s:g} s"
    print(f"{what} without and with the live view (--view FILE.rrd) alternating, "
          f"{args.repeat} pairs ...", flush=True)
    live = figures["view_vs_plain"] = view_vs_plain(config_path, table, workdir, args.repeat)
    live["case"] = what
    show_pairs(live, ("plain", "view"))
    print(f"  view file: {live['view_rrd_bytes'] / 1e6:.1f} MB", flush=True)


def simbench_runs(figures: dict, config_path: Path, table: Path, workdir: Path,
                  repeat: int) -> None:
    print(f"SimBench scenario ({config_path.name}), sim clock, {repeat} runs ...", flush=True)
    figures["simbench"] = repeated(lambda: run_up(config_path, table, workdir), repeat,
                                   lambda f: print(json.dumps(f), flush=True))
    for key, label, unit in (("speed_factor", "speed factor", "x"),
                             ("wall_s", "wall time", " s"),
                             ("cpu_s_total", "CPU time, all processes", " s"),
                             ("grants_per_s", "grants/s", "")):
        show_range(label, figures["simbench"], key, unit)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default=str(REPO / "configs" / "simbench.yaml"))
    parser.add_argument("--agents", default="4,8,14,23",
                        help="agent counts N for the grants/s sweep (N - 3 DERs), '' to skip")
    parser.add_argument("--sweep-s", type=float, default=60.0, help="sim s per sweep run")
    parser.add_argument("--repeat", type=int, default=3, help="runs of every measurement")
    parser.add_argument("--skip-simbench", action="store_true")
    parser.add_argument("--skip-helics", action="store_true")
    parser.add_argument("--grid-cost", action="store_true",
                        help="also: the scenario with the grid against without it")
    parser.add_argument("--helics-python", default="/tmp/venv-helics/bin/python")
    parser.add_argument("--helics-steps", type=int, default=60000,
                        help="10 ms steps (60000: the 600 s of the SimBench scenario)")
    parser.add_argument("--helics-core", default="tcp")
    parser.add_argument("--secure", action="store_true",
                        help="also the SimBench scenario in the secure profile, alternating "
                        "with the open one (the cost of mutual TLS and access control)")
    parser.add_argument("--view", action="store_true",
                        help="also the SimBench scenario with the live view (--view FILE.rrd), "
                        "alternating with plain runs (the cost of --view)")
    parser.add_argument("--view-config", metavar="YAML",
                        help="with --view: measure on this config (with --view-table) instead "
                        "of the SimBench scenario")
    parser.add_argument("--view-table", metavar="JSON", help="the gain table of --view-config")
    parser.add_argument("--only-pairs", action="store_true",
                        help="with --secure, --view or --memory: skip the plain SimBench runs "
                        "before")
    parser.add_argument("--memory", action="store_true",
                        help="also modules, import time and PSS per agent kind and start-up "
                        "to agents ready (SimBench scenario), alternating with --baseline-rev")
    parser.add_argument("--baseline-rev", metavar="REV[,REV...]",
                        help="with --memory or --compare: also measure these commits (a git "
                        "worktree each)")
    parser.add_argument("--compare", action="store_true",
                        help="the SimBench scenario of this tree, every --baseline-rev and "
                        "HELICS in a rotating order (speed, CPU, start-up, clock samples per "
                        "DER and window), then the ratios to HELICS")
    parser.add_argument("--timeline", action="store_true",
                        help="the SimBench scenario of this tree with every agent noting when "
                        "its windows ran: the loop's stages and hand-overs, and the speed "
                        "their chain allows")
    parser.add_argument("--json", metavar="PATH", help="also write every figure as JSON")
    args = parser.parse_args()

    figures: dict = {"machine": {"cpus": os.cpu_count(), "load_at_start": load()}}
    with tempfile.TemporaryDirectory(prefix="adnmesh-bench-") as tmp:
        workdir = Path(tmp)
        if not args.skip_simbench:
            config_path = Path(args.config)
            table = simbench_table(load_config(config_path), workdir)
            if not args.only_pairs:
                simbench_runs(figures, config_path, table, workdir, args.repeat)
            if args.secure:
                print(f"SimBench scenario, open and secure profile alternating, {args.repeat} "
                      "pairs ...", flush=True)
                security = figures["secure_vs_open"] = secure_vs_open(config_path, table,
                                                                      workdir, args.repeat)
                show_pairs(security, ("open", "secure"))
            if args.view and not args.view_config:
                view_pairs(figures, args, config_path, table, workdir)
            if args.compare:
                print(f"SimBench scenario, this tree, {args.baseline_rev or 'no baseline'} "
                      f"{'' if args.skip_helics else 'and HELICS '}in a rotating order, "
                      f"{args.repeat} rounds ...", flush=True)
                figures["compare"] = speed_compare(args, table, workdir)
            if args.timeline:
                print(f"SimBench scenario, this tree, the windows' wall times, {args.repeat} "
                      "runs ...", flush=True)
                figures["timeline"] = timeline(config_path, table, workdir, args.repeat)
            if args.memory:
                print(f"memory and start-up per agent kind, {args.repeat} runs per tree, "
                      "alternating ...", flush=True)
                figures["memory"] = memory_compare(args, table, workdir)
        if args.view and args.view_config:
            view_pairs(figures, args, None, None, workdir)
        if args.grid_cost:
            print(f"grid cost: {args.repeat} runs each with and without grid_model ...",
                  flush=True)
            (workdir / "plain").mkdir()
            figures["grid_cost"] = cost = grid_cost(Path(args.config), workdir, args.repeat)
            print(f"  with the grid / summed infeeds: wall {cost['ratio_wall_s']}x, CPU "
                  f"{cost['ratio_cpu_s_total']}x (medians)", flush=True)
        sweep = []
        for n in [int(x) for x in args.agents.split(",") if x.strip()]:
            path, table = wt_config(n - 3, args.sweep_s, workdir)
            point = repeated(lambda: run_up(path, table, workdir), args.repeat, lambda f: None)
            for run_figures in point["runs"]:
                run_figures.pop("cpu_s")
            sweep.append({"agents": n, **point})
            g, v = point["grants_per_s"], point["speed_factor"]
            print(f"N = {n:3d} agents: {point['runs'][0]['grants']} grants, "
                  f"{g['min']:g} .. {g['max']:g} grants/s (median {g['median']:g}), speed factor "
                  f"median {v['median']:g} (load {point['runs'][-1]['load']})", flush=True)
        figures["grants_vs_agents"] = sweep
        if not args.skip_helics and not args.compare:   # --compare ran HELICS in its turns
            print(f"HELICS baseline: 14 federates, {args.helics_steps} steps of 10 ms, "
                  f"core {args.helics_core}, {args.repeat} runs ...", flush=True)
            figures["helics"] = repeated(
                lambda: run_helics(args.helics_python, args.helics_steps, 14, args.helics_core),
                args.repeat, lambda f: print(json.dumps(f), flush=True))
            show_range("speed factor", figures["helics"], "speed_factor", "x")
            if "simbench" in figures:
                ours = figures["simbench"]["speed_factor"]["median"]
                theirs = figures["helics"]["speed_factor"]["median"]
                figures["ratio_adnmesh_to_helics"] = round(ours / theirs, 2)
                print(f"speed factor (medians) adnmesh {ours:g} / HELICS {theirs:g} = "
                      f"{ours / theirs:.2f}", flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(figures, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
