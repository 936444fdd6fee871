"""The gain tables and the operating point ``adnmesh up`` runs with: a table found (given, next
to the config, or one an earlier ``up`` tuned for the same design and scenario) or the
scenario's subsets tuned now and kept (:func:`table_for`), and the grid model's checks before
any agent starts (:func:`operating_point`). ``adnmesh check`` and ``adnmesh up`` of a hierarchy
use the same."""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

from adnmesh.config import Config
from adnmesh.errors import ConfigError, GridError, UsageError
from adnmesh.reactive import reactive_view
from adnmesh.tuning.table import (SchedulingTable, default_table_path, load_table, new_table,
                                   save_table)

__all__ = ["operating_point", "scenario_subsets", "static_controller", "table_for",
           "tuned_table_path"]


def scenario_subsets(config: Config) -> list[frozenset[str]]:
    """The sets of available DERs the scenario goes through, in order (all DERs first): those
    ``adnmesh tune --subsets scenario`` tunes."""
    from adnmesh.control.operating_point import available_power_w
    from adnmesh.tuning.subset_selection import scenario_subsets as in_config_order

    return [frozenset(s) for s in in_config_order(config, available_power_w(config))]


def _tuner():
    """``tune(config, der_ids)`` for the subsets a missing table lacks: on-demand tuning
    (:class:`adnmesh.tuning.ondemand.OnDemandTuner`, each entry a starting point for the next;
    a subset too large is a one-line error)."""
    from adnmesh.tuning.ondemand import OnDemandTuner   # numba: only when there is no table

    tuners: dict[str, OnDemandTuner] = {}

    def tune(config: Config, der_ids):
        if config.sha256 not in tuners:
            tuners[config.sha256] = OnDemandTuner(config)
        return tuners[config.sha256].tune(der_ids)
    return tune


def tuned_table_path(config: Config, subsets) -> Path:
    """Where ``up`` keeps the table it tunes for itself: ``<cache>/tables/<config stem>.<key>.json``
    (``<cache>``: :func:`adnmesh.grid.cache.default_cache_dir`), the key the first 16 hex of the
    SHA-256 of the config's design (:mod:`adnmesh.tuning.design_key`) and the scenario's
    ``subsets``: exactly what the tuning depends on, so a run that finds it uses the table it
    would have tuned."""
    from adnmesh.grid.cache import default_cache_dir
    from adnmesh.tuning.design_key import design_sha256

    order = {d: i for i, d in enumerate(config.der_ids())}
    listed = sorted(sorted(subset, key=order.__getitem__) for subset in subsets)
    key = hashlib.sha256(json.dumps([design_sha256(config), listed]).encode()).hexdigest()
    return default_cache_dir() / "tables" / f"{Path(config.path).stem}.{key[:16]}.json"


def table_for(given: str | None, config: Config, run_dir: Path, run_id: str, log) -> Path:
    """The table file the CPFC will use: ``given`` (``--table``; for the Q loop, whose
    ``config`` is the reactive view, ``--q-table``), else the config's own
    (:func:`default_table_path`, next to the config), else the one an earlier run tuned for
    this design and scenario (:func:`tuned_table_path`), else the scenario's subsets tuned now
    and kept there (beside the recording if the cache cannot be written)."""
    q = config.quantity == "Q"
    what, option = ("Q gain table", " --quantity q") if q else ("gain table", "")
    path = Path(given) if given else default_table_path(config)
    subsets = scenario_subsets(config)
    if path.exists():
        table = load_table(path, config)  # a bad table: one line now, not in the CPFC later
        _check_gains(config, table, subsets, path)
        return path                     # subsets it lacks: the CPFC tunes them on demand
    if given:
        raise UsageError(f"no {what} {path}; run 'adnmesh tune {config.path}{option} --out "
                         f"{path}' first, or leave out --{'q-' if q else ''}table to have the "
                         "scenario's subsets tuned now")
    cached = tuned_table_path(config, subsets)
    if cached.exists():
        try:
            table = load_table(cached, config)
            _check_gains(config, table, subsets, cached)
        except (ConfigError, UsageError) as exc:
            log(f"not using the tuned {what} an earlier run kept: {exc}; tuning again")
        else:
            log(f"{what} {cached}: tuned by an earlier run for this design and scenario")
            return cached
    tune = _tuner()
    log(f"no {what} at {path}: tuning the {len(subsets)} subset(s) the scenario needs")
    table = new_table(config, config.constraints.model_dump(), "on-demand")
    ordered = [tuple(d for d in config.der_ids() if d in subset) for subset in subsets]
    for subset in ordered:
        entry = tune(config, list(subset))
        if not entry.feasible:      # the CPFC would have no gains for it: refused now
            names = ", ".join(subset) if len(subset) <= 6 else f"{len(subset)} DERs"
            raise ConfigError(f"{config.path}: constraints: no PI pair meets them for the "
                              f"scenario's DERs {names} ({entry.reason}); relax them or "
                              "change the DERs")
        table.add(entry)
    table.static = static_controller(config, ordered, log)
    try:
        cached.parent.mkdir(parents=True, exist_ok=True)
        save_table(table, cached)
        path = cached
    except OSError as exc:
        path = run_dir / f"{run_id}.table.json"
        log(f"cannot keep the tuned table in {cached.parent} ({exc.strerror or exc}); "
            "writing it beside the recording")
        save_table(table, path)
    log(f"tuned {what} written to {path}")
    return path


def _check_gains(config: Config, table: SchedulingTable, subsets, path: Path) -> None:
    """Refuse a table with gains the CPFC could use that are not certified stable, in one
    line, before anything starts (:mod:`adnmesh.tuning.table_check`)."""
    from adnmesh.tuning.table_check import unstable_gains

    bad = unstable_gains(config, table, subsets)
    if bad:
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        raise UsageError(f"{path}: gains not certified stable, refusing to run them: "
                         f"{bad[0].describe()}{more}; retune with 'adnmesh tune {config.path} "
                         f"--out {path}'")


def static_controller(config: Config, subsets, log):
    """The static controller (``subsets``: tuples of DER ids in config order) of the table ``up`` tunes for itself (None where it is not
    designed): what the CPFC uses at once when it meets a subset the table lacks, while that
    subset is tuned. Designed on the scenario's subsets and the extreme plants and verified on
    random subsets (:func:`adnmesh.tuning.build.static_entry`; ~5 s for SimBench). Configs with
    more dynamics classes than the on-demand tuner's exact limit are left without one here:
    for the 100-DER example (70 classes) the design takes ~80 s, which ``adnmesh tune
    --subsets scenario`` spends once (its table, given with ``--table``, has the pair)."""
    from adnmesh.tuning.build import static_entry
    from adnmesh.tuning.problem import MAX_EXACT_CLASSES
    from adnmesh.tuning.problem import TuningProblem

    problem = TuningProblem(config)
    if len(problem.actuators) > MAX_EXACT_CLASSES:
        log(f"no static controller: {len(problem.actuators)} dynamics classes (more than "
            f"{MAX_EXACT_CLASSES}); a subset the table lacks waits for its on-demand tuning "
            f"('adnmesh tune {config.path} --subsets scenario' makes a table with one)")
        return None
    t0 = time.perf_counter()
    entry = static_entry(problem, list(config.der_ids()), subsets)
    if not entry.feasible:
        log(f"no static controller: {entry.reason}")
        return None
    u = config.unit
    log(f"static controller: K_P {entry.kp:.4g} 1/{u}, K_I {entry.ki:.4g} 1/({u} s), verified on "
        f"{entry.figures.get('verified_random_subsets', 0)} random subsets "
        f"({time.perf_counter() - t0:.1f} s)")
    return entry


def operating_point(config: Config, log) -> dict[str, float]:
    """The DERs' available power (loading the grid model once, before any agent starts: the
    first time it builds its disk cache, which takes tens of seconds); checks every DER's
    model parameters and that the power flow at the schedules converges. ``adnmesh check``
    runs the same checks.

    Raises
    ------
    ConfigError
        An unknown SimBench code or study case, an sgen the net does not have, a ``p_inst_w``
        above the sgen's rating, a ``type`` that is not the sgen's, a schedule
        above what the DER can deliver, a bad model override, a power flow that does not
        converge; with reactive power control what :func:`adnmesh.reactive.reactive_view`
        refuses (a reactive schedule outside its range, reactive dynamics the numerics cannot
        hold, no DER with a reactive range); a tap changer the net does not have.
    """
    from adnmesh.control.der_model import check_der_models
    from adnmesh.control.operating_point import (available_power_w, initial_p_ip_w,
                                                 sgen_problem)

    if config.grid_model is not None:
        from adnmesh.control.operating_point import grid_label, grid_source
        from adnmesh.grid.cache import is_cached
        source, name, case = grid_source(config)
        building = "" if source != "simbench" or is_cached(
            name, case, config.grid_model.load_model) else \
            " (not cached yet: tens of seconds to build its cache)"
        log(f"grid model: {grid_label(config)}{building}")
    try:
        available = available_power_w(config)
    except GridError as exc:
        raise GridError(f"{config.path}: {exc}") from None
    problem = sgen_problem(config)
    if problem is not None:
        raise ConfigError(f"{config.path}: {problem}")
    check_der_models(config, available)
    if config.reactive is not None:
        reactive_view(config)
    from adnmesh.control.operating_point import tap_changer_words
    try:
        tap = tap_changer_words(config)
    except GridError as exc:
        raise ConfigError(f"{config.path}: {exc}") from None
    if tap is not None:
        log(tap)
    try:
        p_ip_w = initial_p_ip_w(config)
    except ValueError as exc:
        raise ConfigError(f"{config.path}: grid_model: {exc}") from None
    if config.grid_model is not None:
        log(f"grid model ready: P_IP {p_ip_w / 1e6:.4f} MW at the schedules")
    return available
