"""The plant side of a config: what the DERs can deliver and where the run starts.

With a grid model (the config's ``grid_model``) both come from the study case (or time step)
of its net, the SimBench grid or a pandapower net file (:mod:`adnmesh.grid`): a DER's available
power is its sgen's power there, and the initial P_IP is the power flow's at the DERs'
schedules. Without one, a DER can deliver its installed power and P_IP is
``runtime.rest_of_grid_w`` plus the schedules. The values are
computed once per config (the grid loads from its disk cache).
"""

from __future__ import annotations

import functools
import os

from adnmesh.config import Config

__all__ = ["available_power_w", "grid_label", "grid_solver", "grid_source", "initial_p_ip_w",
           "initial_q_ip_var", "reachable_ranges", "tap_changer_words",
           "sgen_problem"]


@functools.lru_cache(maxsize=8)
def _load(source: str, name: str, case: str | None, load_model: str, content: str = ""):
    """The grid data (``content``: the net file's modification stamp, so an edited file is
    read anew)."""
    if source == "pandapower":
        from adnmesh.grid.cache import load_net_grid
        return load_net_grid(name, case, load_model)
    from adnmesh.grid import load_grid
    return load_grid(name, case, load_model)


def grid_source(config: Config) -> tuple[str, str, str | None]:
    """``(source, name, case)`` of the config's grid model: ``("simbench", code, case)`` or
    ``("pandapower", resolved file path, case or None when not given)``; ``case`` names a time
    step (:func:`adnmesh.grid.simbench_net.time_step_case`) where the config gives one."""
    model = config.grid_model
    net = config.pandapower_net_path()
    if model.time_step is not None:
        from adnmesh.grid.simbench_net import time_step_case
        case = time_step_case(model.time_step)
    else:
        case = model.study_case
    if net is not None:
        given = "study_case" in model.model_fields_set or model.time_step is not None
        return "pandapower", str(net), case if given else None
    return "simbench", config.simbench_code, case


def grid_label(config: Config) -> str:
    """The grid model's net in words: ``SimBench CODE, study case X`` (or ``, time step N``) or
    ``pandapower net FILE`` (with its study case or time step if one is given)."""
    from adnmesh.grid.simbench_net import case_words

    source, name, case = grid_source(config)
    point = "" if case is None else f", {case_words(case)}"
    return (f"pandapower net {name}" if source == "pandapower" else f"SimBench {name}") + point


def _grid(config: Config):
    source, name, case = grid_source(config)
    load_model = config.grid_model.load_model
    if source == "pandapower":                   # an edited file is read anew (stat, no hash:
        return _load(source, name, case, load_model, _stamp(name))   # the loader hashes it)
    return _load(source, name, case, load_model)


def _stamp(path: str) -> str:
    """The file's modification time and size ("" if it cannot be read: the loader says so)."""
    try:
        stat = os.stat(path)
    except OSError:
        return ""
    return f"{stat.st_mtime_ns}:{stat.st_size}"


def grid_solver(config: Config):
    """A fresh :class:`adnmesh.grid.GridSolver` for the config's DERs (None without a grid)."""
    if config.grid_model is None:
        return None
    from adnmesh.grid import GridSolver
    return GridSolver(_grid(config), [d.sgen for d in config.ders])


@functools.lru_cache(maxsize=8)
def available_power_w(config: Config) -> dict[str, float]:
    """DER id -> the power it can deliver, W (at most its installed power)."""
    if config.grid_model is None:
        return {d.id: d.p_inst_w for d in config.ders}
    from adnmesh.grid import available_power_w as study_case_power
    data = _grid(config)
    powers = study_case_power(data, [d.sgen for d in config.ders])
    return {d.id: min(float(p), d.p_inst_w) for d, p in zip(config.ders, powers)}


@functools.lru_cache(maxsize=8)
def _operating_point(config: Config) -> tuple[float, float]:
    """(P_IP, Q_IP) with every DER at its schedule (the reactive one with reactive power
    control), W and var, MV -> HV positive."""
    reactive = config.reactive
    q_rest = 0.0 if reactive is None else reactive.rest_of_grid_var
    solver = grid_solver(config)
    if solver is None:
        return (config.runtime.rest_of_grid_w + sum(d.p_sched_w for d in config.ders),
                q_rest + sum(d.q_sched_var for d in config.ders))
    q_sched = None if reactive is None else [d.q_sched_var for d in config.ders]
    sample = solver.solve([d.p_sched_w for d in config.ders], q_sched)
    if not sample.converged:
        raise ValueError("the power flow at the DERs' schedules does not converge")
    return float(sample.p_ip_w), float(sample.q_ip_var)


@functools.lru_cache(maxsize=8)
def reachable_ranges(config: Config):
    """``((P_min, P_max), (Q_min, Q_max))`` of P_IP and Q_IP the DERs can reach within the
    grid limits and their capability, W and var (:func:`adnmesh.analysis.pq_region.
    reference_bounds`), or a one-line reason why not (a str): no grid model, clipping off in
    the config, or the optimisation failed. Without reactive power control every DER's Q
    stays at 0 (its sgen's at the study case, SimBench's), so the P range is at that Q."""
    model = config.grid_model
    if model is None:
        return "no grid model"
    if not model.guard.clip_references:
        return "grid_model.guard.clip_references is off"
    from adnmesh.analysis.pq_region import reference_bounds
    ders = config.ders
    if config.reactive is None:
        ders = tuple(d.model_copy(update={"q_capability": "unity", "q_sched_var": 0.0})
                     for d in ders)
    try:
        return reference_bounds(grid_solver(config), ders, available_power_w(config),
                                model.limits, config.reactive)
    except Exception as exc:          # noqa: BLE001 - any failure leaves the references as asked
        return f"the reachable range could not be found ({type(exc).__name__}: {exc})"


def tap_changer_words(config: Config) -> str | None:
    """The config's tap changer in words (its transformers, range, position, what it keeps),
    None without one; :class:`~adnmesh.errors.GridError` (one line) if the net has no such tap
    changer."""
    if config.grid_model is None or config.grid_model.tap_changer is None:
        return None
    from adnmesh.control.grid_side import tap_changer_of
    settings = config.grid_model.tap_changer
    solver = grid_solver(config)
    control, trafos, _ = tap_changer_of(settings, solver)
    names = ", ".join(solver.trafo_names[i] for i in trafos)
    keeps = (f"its busbar at {control.v_set_pu:.4f} ± {control.dead_band_pu:g} p.u."
             if settings.regulates == "busbar" else
             f"every bus voltage {settings.extremes_margin_pu:g} p.u. inside the band")
    return (f"tap changer of {names}: positions {control.tap_min} to {control.tap_max}, at "
            f"{control.position}; keeps {keeps}, a step after {settings.delay_s:g} s outside")


def initial_p_ip_w(config: Config) -> float:
    """P_IP with every DER at its schedule, W (MV -> HV positive): the operating point."""
    return _operating_point(config)[0]


def initial_q_ip_var(config: Config) -> float:
    """Q_IP with every DER at its schedule, var (MV -> HV positive; without a grid model and
    reactive power control: 0)."""
    return _operating_point(config)[1]


def sgen_problem(config: Config) -> str | None:
    """The first DER whose sgen does not fit what the config says of it, as ``ders[i].key:
    why`` (None if all fit; no grid model: None): ``p_inst_w`` above the sgen's rating (the
    net's ``sn_mva``; the gains would be designed for power the plant does not have), or a
    ``type`` that is not the sgen's (its net ``type`` read as :func:`adnmesh.adn.dynamics.
    der_type_of` reads it; a type it cannot tell, GEN, fits any)."""
    if config.grid_model is None:
        return None
    from adnmesh.adn.dynamics import der_type_of

    data = _grid(config)
    index = data.sgen_index([d.sgen for d in config.ders])
    for i, (der, k) in enumerate(zip(config.ders, index)):
        rating_w = float(data.sgen_rating_mw[k]) * 1e6
        if rating_w == rating_w and der.p_inst_w > rating_w * (1 + 1e-9):
            return (f"ders[{i}].p_inst_w: {der.p_inst_w / 1e6:g} MW is more than its sgen "
                    f"{der.sgen!r} is rated for, {rating_w / 1e6:g} MW (the net's sn_mva): the "
                    "gains would be designed for power it does not have")
        kind = data.sgen_types[k]
        net_type = der_type_of(kind)
        if kind and net_type != "GEN" and net_type != der.type:
            return (f"ders[{i}].type: {der.type}, but its sgen {der.sgen!r} is a {kind} plant "
                    f"({net_type}); its detailed model and default dynamics are {net_type}'s")
    return None
