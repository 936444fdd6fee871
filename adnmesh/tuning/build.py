"""Build the gain-scheduling table CP: every subset, deduplicated, chunked, resumable.

Subsets whose normalised plants coincide are tuned once (:class:`TuningProblem.key`); their
gains differ only by ``1 / sum P_inst``. Plants are tuned in chunks (all plants of a chunk in
lock-step, chunks optionally in worker processes); after every chunk the table so far is saved
atomically, so an interrupted run leaves a valid partial table that ``resume`` continues.
"""
from __future__ import annotations

import csv
import dataclasses
import io
import math
import multiprocessing
import os
import threading
import time
from contextlib import contextmanager
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from adnmesh import BLAS_THREADS_ENV
from adnmesh.files import write_atomic
from adnmesh.tuning.certify import PlantGroup, certified_entries, certify_static
from adnmesh.tuning.global_search import tune_global
from adnmesh.tuning.paper import initial_values, tune_paper
from adnmesh.tuning.problem import TuningProblem, all_subsets, horizon_s
from adnmesh.tuning.static_controller import design_over, static_any_size
from adnmesh.tuning.table import (FIGURE_KEYS, SchedulingTable, TableEntry, load_table, new_table,
                                   save_table)
from adnmesh.tuning.warm import SHARES, warm_share

__all__ = ["tune_table", "static_entry", "paper_path", "write_csv", "group_subsets",
           "plant_chunks", "METHODS", "PHASES"]

METHODS = ("paper", "global")
#: an entry's certificate over the uncertainty set (tables of configs with one)
ROBUST_KEYS = ("robust_disk_margin", "robust_disk_margin_at", "robust_overshoot_pct",
               "robust_overshoot_at")
#: CSV columns that are text
TEXT_KEYS = ("tuned_by", "robust_disk_margin_at", "robust_overshoot_at")
#: ``tuned_by`` of a paper-method entry whose path search never found a feasible point
PAPER_FALLBACK = "global (the paper's path found no feasible point)"
#: plants per chunk, at most: the paper method's path walk checks its plants in 800-900
#: lock-step batches per chunk whatever the chunk's size, so 148 plants a chunk (6 chunks
#: for SimBench's 887) take ~0.8x the CPU of 48 (19 chunks); the global search is
#: indifferent (its checks are wide batches either way), and a chunk of 148 still saves a
#: partial table every few seconds
CHUNK = 148
#: random subsets the static controller of a selection is verified on
STATIC_SAMPLE = 1000
#: how long a starting worker waits for the others' shares of the compiled kernels, s
WARM_WAIT_S = 60.0
#: phases of a chunk whose CPU and wall time :func:`tune_table` reports (``phases=``)
PHASES = ("initial values", "global search", "paper path", "find W", "back-off",
          "as-deployed figures")


class _Clock:
    """CPU and wall seconds per phase, summed over chunks (``{phase: [cpu, wall]}``)."""

    def __init__(self):
        self.times = {p: [0.0, 0.0] for p in PHASES}

    @contextmanager
    def phase(self, name: str):
        c0, w0 = time.process_time(), time.perf_counter()
        try:
            yield
        finally:
            self.times[name][0] += time.process_time() - c0
            self.times[name][1] += time.perf_counter() - w0


def group_subsets(problem: TuningProblem, subsets: Sequence[Sequence[str]]) -> list[PlantGroup]:
    """The subsets grouped by normalised plant (:meth:`TuningProblem.key`), plants in the order
    of their first subset."""
    groups: dict[tuple, list] = {}
    fracs: dict[tuple, np.ndarray] = {}
    for s in subsets:
        f, _ = problem.fractions(s)
        key = problem.key(f)
        groups.setdefault(key, []).append(tuple(s))
        fracs.setdefault(key, f)
    return [PlantGroup(fracs[k], tuple(v)) for k, v in groups.items()]


def plant_chunks(groups: list[PlantGroup], chunk_size: int) -> list[list[PlantGroup]]:
    """The plants dealt into ``ceil(P / chunk_size)`` chunks in turn (plant i into chunk
    i mod n): every chunk a cross-section of the subset sizes, so chunks cost about the
    same, and the lock-step searches' sequential moves (set by a chunk's longest path, not
    by its size) are shared by ~``chunk_size`` plants. Fixed by the plant list alone, so a
    resumed run and any number of workers tune the same batches."""
    n = max(1, -(-len(groups) // max(1, chunk_size)))
    return [groups[i::n] for i in range(n) if groups[i::n]]


@contextmanager
def _one_blas_thread_in_workers():
    """While the pool starts its worker processes: ``OPENBLAS_NUM_THREADS=1`` in the
    environment they get, unless the caller has set it (see :func:`adnmesh.one_blas_thread`).
    A worker started afresh ("spawn", "forkserver") reads it when it imports numpy; a forked
    one keeps this process's OpenBLAS as it is (one thread when run from the command line)."""
    if BLAS_THREADS_ENV in os.environ:
        yield
        return
    os.environ[BLAS_THREADS_ENV] = "1"
    try:
        yield
    finally:
        os.environ.pop(BLAS_THREADS_ENV, None)


def _one_numba_thread_if(single_thread: bool) -> None:
    """In a pool worker: numba kernels on one thread (the workers share the cores)."""
    if single_thread:
        import numba
        numba.set_num_threads(1)


def _start_worker(counter, barrier, config, constraints) -> None:
    """Pool worker start: the compiled kernels' share of this worker (they take
    :data:`~.warm.SHARES` in turn), then wait until every worker has its share, so that the
    others are in numba's cache when this one needs them (a first run compiled every kernel
    in every worker at once, ~6 s; see :mod:`.warm`). A worker that does not arrive within
    :data:`WARM_WAIT_S` is not waited for: the kernels it should have compiled are then
    compiled where they are needed, as before."""
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    problem = TuningProblem(config, constraints["disk_margin_min"],
                            constraints["overshoot_max_pct"])
    warm_share(problem, SHARES[index % len(SHARES)])
    try:
        barrier.wait(timeout=WARM_WAIT_S)
    except threading.BrokenBarrierError:
        pass


def _tune_chunk(args) -> tuple[list[TableEntry], dict]:
    """Worker: tune a chunk of plant groups (picklable entry point); returns the entries and
    the CPU and wall seconds per phase."""
    config, constraints, method, groups, single_thread = args
    _one_numba_thread_if(single_thread)
    clock = _Clock()
    problem = TuningProblem(config, constraints["disk_margin_min"], constraints["overshoot_max_pct"])
    fractions = np.array([g.fractions for g in groups])
    with clock.phase("initial values"):
        kp0, ki0 = initial_values(problem, fractions)
    with clock.phase("global search"):
        glob = tune_global(problem, fractions, kp0, ki0)
    if method == "global":
        kp, ki, feas, rise = glob.kp, glob.ki, glob.feasible, glob.rise_time_s
        tuned_by = ["global"] * len(groups)
    else:
        with clock.phase("paper path"):
            res = tune_paper(problem, fractions)
        # where the paper's path never met the feasible set, the global search's pair is used
        lost = ~res.feasible & glob.feasible
        kp = np.where(lost, glob.kp, res.kp)
        ki = np.where(lost, glob.ki, res.ki)
        rise = np.where(lost, glob.rise_time_s, res.rise_time_s)
        feas = res.feasible | glob.feasible
        tuned_by = [PAPER_FALLBACK if x else "paper" for x in lost]
    reasons = ["no feasible pair: every candidate violates the disk margin or overshoot limit"
               if not f else None for f in feas]
    return certified_entries(problem, groups, kp, ki, feas, reasons, glob.rise_time_s, rise,
                             tuned_by, clock), clock.times


def tune_table(config, method: str = "paper", workers: int = 1, out: Path | None = None,
               resume: bool = False, constraints: dict | None = None,
               on_progress: Callable[[int, int], None] | None = None,
               subsets: Sequence[Sequence[str]] | None = None,
               chunk_size: int = CHUNK, phases: dict | None = None) -> SchedulingTable:
    """Tune CP for ``config`` (all 2^m - 1 subsets unless ``subsets`` is given).

    Parameters
    ----------
    method : "paper" or "global"
    workers : int
        Worker processes (chunks of plants run in parallel).
    out : Path, optional
        Where the table is saved after every chunk (and finally).
    resume : bool
        Continue the partial table at ``out`` (same config, method and constraints).
    constraints : dict, optional
        ``disk_margin_min`` / ``overshoot_max_pct`` overriding the config's.
    on_progress : callable(done, total), optional
        Called with the number of subsets done.
    chunk_size : int
        Normalised plants tuned together, at most (:func:`plant_chunks`). Chunks are fixed
        from the full subset list, so a resumed run tunes exactly the batches an
        uninterrupted run would (same results).
    phases : dict, optional
        Filled with ``{phase: [cpu s, wall s]}`` summed over chunks (:data:`PHASES`, plus
        ``static controller``); worker processes' CPU included.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}")
    problem = TuningProblem(config, **(constraints or {}))
    ids = list(config.der_ids())
    wanted = [tuple(s) for s in (subsets if subsets is not None else all_subsets(ids))]
    table = new_table(config, problem.constraints, method)
    if resume and out is not None and Path(out).exists():
        old = load_table(out, config)
        if old.method == method and old.constraints == problem.constraints:
            table = old
            table.complete = False
            table.design = new_table(config, {}, method).design   # an older table had none
    groups = group_subsets(problem, wanted)
    chunks = [c for c in plant_chunks(groups, chunk_size)
              if any(table.lookup(s) is None for g in c for s in g.subsets)]
    done = len(wanted) - sum(len(g.subsets) for c in chunks for g in c)
    if on_progress:
        on_progress(done, len(wanted))
    jobs = [(config, problem.constraints, method, c, workers > 1) for c in chunks]

    def absorb(result):
        nonlocal done
        entries, times = result
        if phases is not None:
            for k, (c, w) in times.items():
                acc = phases.setdefault(k, [0.0, 0.0])
                acc[0] += c
                acc[1] += w
        for e in entries:
            table.add(e)
        done += len(entries)
        if out is not None:
            save_table(table, out)
        if on_progress:
            on_progress(done, len(wanted))

    # a worker runs it with numba single-threaded (flag True), the main process keeps its threads
    static_job = (config, problem.constraints, ids, None if subsets is None else wanted)
    static = None
    try:
        if workers > 1 and len(jobs) > 1:
            # no more workers than jobs: every worker starts (at once with "fork", one per
            # job submitted otherwise) and meets the others at the barrier of _start_worker
            size = min(workers, len(jobs) + (table.static is None))
            context = multiprocessing.get_context()
            start = (context.Value("i", 0), context.Barrier(size), config, problem.constraints)
            with _one_blas_thread_in_workers(), ProcessPoolExecutor(
                    max_workers=size, mp_context=context, initializer=_start_worker,
                    initargs=start) as pool:
                # the static controller needs no entry: it runs beside the chunks, not after
                pending = (pool.submit(_static_job, (*static_job, True))
                           if table.static is None else None)
                for entries in pool.map(_tune_chunk, jobs):
                    absorb(entries)
                if pending is not None:
                    static = pending.result()
        else:
            for job in jobs:
                absorb(_tune_chunk(job))
    except KeyboardInterrupt:
        if out is not None:
            save_table(table, out)
        raise
    if table.static is None:
        entry, times = static if static is not None else _static_job((*static_job, False))
        table.static = entry
        if phases is not None:
            phases["static controller"] = times
    table.complete = subsets is None
    if out is not None:
        save_table(table, out)
    return table


def _static_job(args) -> tuple[TableEntry, list[float]]:
    """Worker: the static controller's entry (picklable entry point) and its [CPU s, wall s]."""
    config, constraints, ids, subsets, single_thread = args
    _one_numba_thread_if(single_thread)
    c0, w0 = time.process_time(), time.perf_counter()
    problem = TuningProblem(config, constraints["disk_margin_min"],
                            constraints["overshoot_max_pct"])
    entry = static_entry(problem, ids, subsets)
    return entry, [time.process_time() - c0, time.perf_counter() - w0]


def static_entry(problem: TuningProblem, ids: list[str],
                  subsets: Sequence[Sequence[str]] | None = None) -> TableEntry:
    """The static controller with its worst-case figures.

    Over every subset when the table holds them all; over a selection (``subsets``) the pair
    is designed on those subsets and the extreme plants
    (:func:`~.static_controller.extreme_subsets`) and verified on them and a random sample of
    subsets (:func:`~.static_controller.static_any_size`): the subsets a run meets are not all
    in the table. The figures are those of every plant
    checked, each simulated until it settles.
    """
    verified = {}
    if subsets is None:
        cases = all_subsets(ids)
        powers, tot, res = design_over(problem, cases)
    else:
        any_size = static_any_size(problem, ids, sample=STATIC_SAMPLE, extra=subsets)
        res, cases, powers = any_size.result, any_size.cases, any_size.powers
        tot = powers.sum(axis=1)
        verified = {"verified_random_subsets": any_size.verified,
                    "verified_plants": len(any_size.powers),
                    "design_subsets_added_from_sample": any_size.added,
                    "lowered_on_exact_plant": any_size.lowered}
    if not res.feasible:
        return TableEntry(tuple(ids), float("nan"), float("nan"), {d: 1.0 for d in ids}, False,
                          "no pair is feasible on every subset", verified)
    kp, ki = np.full(len(tot), res.kp), np.full(len(tot), res.ki)
    robust = {}
    if problem.box is not None:
        f = powers / tot[:, None]
        kp_s, ki_s, robust, why = certify_static(problem, powers, res.kp, res.ki,
                                                 horizon_s(f, kp * tot, ki * tot))
        if why is not None:
            return TableEntry(tuple(ids), float("nan"), float("nan"), {d: 1.0 for d in ids},
                              False, "not certified over the uncertainty set: " + why,
                              {**verified, **robust})
        res = dataclasses.replace(res, kp=kp_s, ki=ki_s)
        kp, ki = np.full(len(tot), res.kp), np.full(len(tot), res.ki)
    fig = problem.figures(powers, kp, ki, t_max_s=horizon_s(powers, kp, ki))
    if robust:                           # lowered or not, the worst plant of the pair in use
        j = int(np.nanargmax(fig.rise_time_s))
        res = dataclasses.replace(res, worst_rise_time_s=float(fig.rise_time_s[j]), worst_plant=j)
    worst = next(s for s in cases
                 if np.allclose(problem.group_power(s), powers[res.worst_plant]))
    figures = {
        "worst_rise_time_s": res.worst_rise_time_s,
        "worst_rise_time_subset": list(worst),
        "min_disk_margin": float(np.min(fig.disk_margin)),
        "max_overshoot_pct": float(np.max(fig.overshoot_pct)),
        "max_settling_time_s": float(np.max(fig.settling_time_s)),
        "min_phase_margin_deg": float(np.min(fig.phase_margin_deg)),
        "min_delay_margin_s": float(np.min(fig.delay_margin_s)),
        **verified,
        **robust,
    }
    return TableEntry(tuple(ids), res.kp, res.ki, {d: 1.0 for d in ids}, True, None, figures)


def paper_path(config, der_ids: Sequence[str]) -> list[tuple[float, float, bool]]:
    """The paper method's search path for one subset as (K_P 1/W, K_I 1/(W s), feasible)."""
    problem = TuningProblem(config)
    ders = [d for d in config.der_ids() if d in set(der_ids)]
    fractions, total = problem.fractions(ders)
    res = tune_paper(problem, fractions[None], record=True)
    return [(kp / total, ki / total, ok) for kp, ki, ok in res.paths[0]]


def _number(value) -> object:
    """A CSV cell of a number: as it is, empty for None or NaN (booleans as they are)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return value


def write_csv(table: SchedulingTable, path: Path) -> None:
    """One row per entry, tidy (every cell one value; pandas reads it with its defaults): the
    subset's label (``+``-joined), ``in_<der>`` (1 if the DER is in the subset, else 0) and
    ``w_<der>`` (its weight, empty if it is not) per DER of the table, the gains (1/W,
    1/(W s)), feasibility, the reason (text) and the figures (empty: none). Written atomically."""
    keys = list(FIGURE_KEYS) + ["settling_time_2pct_s", "design_rise_time_s",
                                "global_rise_time_s", "tuned_by"]
    if any("robust_disk_margin" in e.figures for e in table.entries.values()):
        keys += list(ROBUST_KEYS)
    ders = list(table.der_ids)
    text = io.StringIO(newline="")
    w = csv.writer(text)
    w.writerow(["subset", "kp_per_w", "ki_per_w_s"] + [f"in_{d}" for d in ders]
               + [f"w_{d}" for d in ders] + ["feasible", "reason"] + keys)
    for e in table.to_json()["entries"]:
        members = set(e["ders"])
        w.writerow(["+".join(e["ders"]), _number(e["kp"]), _number(e["ki"])]
                   + [int(d in members) for d in ders]
                   + [_number(e["w"].get(d)) if d in members else "" for d in ders]
                   + [e["feasible"], e["reason"] or ""]
                   + [_number(e.get(k)) if k not in TEXT_KEYS else e.get(k) or ""
                      for k in keys])
    write_atomic(path, text.getvalue())
