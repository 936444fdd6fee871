"""The SimBench grid at a study case, as a pandapower net (imports simbench and pandapower).

- :func:`load_simbench_net`: the net of a SimBench code (``simbench.get_simbench_net``).
- :func:`apply_study_case`: loads, generators and the slack voltage of one of the net's own study
  cases (``net.loadcases``: hL, n1, hW, hPV, lW, lPV), through simbench's own
  ``get_absolute_values(net, profiles_instead_of_study_cases=False)``: load p and q scaled by
  ``pload`` and ``qload``; static generators by ``Wind_p`` (type containing "Wind" or "WP"),
  ``PV_p`` (containing "PV") or ``RES_p`` (every other type: biomass, hydro, the aggregated
  low-voltage ``lv_RES``); the external grid's voltage set to ``Slack_vm``.
- :func:`apply_time_step`: the same at one quarter hour of the net's year of profiles
  (``get_absolute_values(net, profiles_instead_of_study_cases=True)``): loads, static
  generators and storages; the slack voltage stays as saved (the profiles have none).
  :func:`time_step_case` names such an operating point where a study case would be.
- :func:`loads_as_impedances`: every load becomes a shunt of the same power at 1 p.u. — a
  constant impedance, ``S = S_0 |V|²`` (docs/method.md#reference-case).

Why shunts and not pandapower's ``const_z_p_percent`` / ``const_z_q_percent``: pandapower
(3.5.6 here) applies a load's voltage dependence to the bus's net demand, static generators on
the same bus included, so with ``const_z_p_percent = 100`` a generator on a load's bus is scaled
by ``|V|²`` too. On 1-MV-rural at lW that is P_IP 24.62 MW instead of 23.19 MW (the shunt model,
whose power balance closes); a one-bus example (1 MW load at 100 % const_z beside a 3 MW sgen,
1.05 p.u.) gives an external-grid injection of -2.205 MW instead of -1.897 MW. A shunt is the
exact constant impedance in pandapower and in the solver alike. ``tests/test_grid.py`` checks
the solver's power balance with ``S_0 |V|²`` loads independently of both.

The 110 kV bus of the SimBench net is its external grid (the slack); the grid's other generators
are constant PQ injections (``sgen``); the six open loop-line switches of 1-MV-rural stay open
(pandapower models each as an auxiliary bus at the open end).
"""

from __future__ import annotations

from adnmesh.errors import GridError

__all__ = ["LOAD_MODELS", "TIME_STEP", "load_simbench_net", "study_cases", "apply_study_case",
           "time_step_case", "is_time_step", "time_step_of", "case_words", "time_steps", "apply_time_step",
           "apply_operating_point", "loads_as_impedances", "grid_net"]

LOAD_MODELS = ("impedance", "power")
#: how an operating point at a time step of the net's profiles is named where a study case
#: would be (``"time step 4711"``; a study case's name has no spaces)
TIME_STEP = "time step "


def load_simbench_net(code: str):
    """The pandapower net of SimBench grid ``code`` (:class:`GridError` if it is not one)."""
    import simbench

    if code not in simbench.collect_all_simbench_codes():
        raise GridError(f"grid: {code!r} is not a SimBench code (e.g. '1-MV-rural--0-no_sw')")
    return simbench.get_simbench_net(code)


def study_cases(net) -> tuple[str, ...]:
    """Names of the study cases in ``net.loadcases``."""
    cases = net.get("loadcases")
    return () if cases is None else tuple(str(c) for c in cases.index)


def apply_study_case(net, case: str) -> None:
    """Set ``net``'s loads, static generators and slack voltage to study case ``case`` (in place).

    Raises
    ------
    GridError
        If the net has no such study case.
    """
    import simbench

    cases = study_cases(net)
    if case not in cases:
        same = [c for c in cases if c.lower() == case.lower()]
        hint = f"; did you mean {same[0]!r}? study cases are case-sensitive" if same else ""
        raise GridError(f"grid: unknown study case {case!r} (this grid has: "
                        f"{', '.join(cases) or 'none'}){hint}")
    values = simbench.get_absolute_values(net, profiles_instead_of_study_cases=False)
    for (element, column), frame in values.items():
        net[element][column] = frame.loc[case, net[element].index].to_numpy(dtype=float)


def time_step_case(step: int) -> str:
    """The operating point's name of time step ``step`` (quarter hours from 1 January 00:00)."""
    return f"{TIME_STEP}{int(step)}"


def case_words(case: str | None) -> str:
    """An operating point in words: ``"study case lW"``, ``"time step 4711"`` or, for None,
    ``"the net as saved"``."""
    if case is None:
        return "the net as saved"
    return case if is_time_step(case) else f"study case {case}"


def is_time_step(case: str | None) -> bool:
    """Whether ``case`` names a time step (:func:`time_step_case`), not a study case."""
    return bool(case) and case.startswith(TIME_STEP)


def time_step_of(case: str | None) -> int | None:
    """The time step ``case`` names (:func:`time_step_case`), None for a study case."""
    return int(case[len(TIME_STEP):]) if is_time_step(case) else None


def time_steps(net) -> int:
    """Number of time steps of ``net``'s profiles (SimBench: 35,136 quarter hours; 0: none)."""
    profiles = net.get("profiles")
    if not profiles or "load" not in profiles:
        return 0
    return len(profiles["load"])


def apply_time_step(net, step: int) -> str:
    """Set ``net``'s loads, static generators and storages to time step ``step`` of its
    profiles (in place), through simbench's ``get_absolute_values(net,
    profiles_instead_of_study_cases=True)``; the external grid's voltage stays as saved.
    Returns the step's time as the profiles give it (``"10.02.2016 01:45"``).

    Raises
    ------
    GridError
        If the net has no profiles or no such step.
    """
    import simbench

    count = time_steps(net)
    if not count:
        raise GridError("grid: a time step asked for, but the net has no profiles (SimBench "
                        "nets have a year of quarter hours); use a study case")
    if not 0 <= step < count:
        raise GridError(f"grid: time step {step} is not in the net's profiles (0 to "
                        f"{count - 1}, quarter hours from the first)")
    values = simbench.get_absolute_values(net, profiles_instead_of_study_cases=True)
    for (element, column), frame in values.items():
        if frame.shape[1]:
            net[element][column] = frame.loc[step, net[element].index].to_numpy(dtype=float)
    times = net.profiles["load"].get("time")
    return str(times.iloc[step]) if times is not None else f"step {step}"


def apply_operating_point(net, case: str) -> None:
    """Set ``net`` to study case ``case`` or, if ``case`` names one (:func:`time_step_case`),
    to that time step of its profiles (in place)."""
    step = time_step_of(case)
    if step is not None:
        apply_time_step(net, step)
    else:
        apply_study_case(net, case)


def loads_as_impedances(net) -> None:
    """Replace every in-service load by a shunt of the same p and q at 1 p.u. (in place).

    The loads stay in the table, out of service; the shunts are named ``"<load name> (Z)"``.
    """
    import pandapower as pp

    loads = net.load[net.load.in_service]
    if loads.empty:
        return
    scaling = loads.scaling.fillna(1.0).to_numpy()
    buses, names = loads.bus.to_numpy(), [f"{n} (Z)" for n in loads.name.astype(str)]
    p_mw, q_mvar = loads.p_mw.to_numpy() * scaling, loads.q_mvar.to_numpy() * scaling
    if len(set(buses.tolist())) == len(buses):
        pp.create_shunts(net, buses, q_mvar=q_mvar, p_mw=p_mw, name=names)
    else:       # pandapower's create_shunts fails on two loads at one bus (CIGRE MV has them)
        for bus, p, q, name in zip(buses, p_mw, q_mvar, names):
            pp.create_shunt(net, int(bus), q_mvar=float(q), p_mw=float(p), name=name)
    net.load.loc[loads.index, "in_service"] = False


def grid_net(code: str, case: str = "lW", load_model: str = "impedance"):
    """The net of SimBench ``code`` at study ``case`` (or the time step it names:
    :func:`time_step_case`), loads as ``load_model`` (a new net).

    ``load_model``: ``"impedance"`` (constant impedance, as shunts;
    docs/method.md#reference-case) or ``"power"``
    (constant power, SimBench's own).
    """
    if load_model not in LOAD_MODELS:
        raise GridError(f"grid: load model must be one of {', '.join(LOAD_MODELS)}, "
                        f"got {load_model!r}")
    net = load_simbench_net(code)
    apply_operating_point(net, case)
    if load_model == "impedance":
        loads_as_impedances(net)
    return net
