"""The static generators of a SimBench net or a pandapower net file at a study case, and P_IP
there (imports simbench and pandapower).

:func:`survey_simbench` loads the net of a SimBench code at one of its study cases, with the
grid model's own functions (:func:`adnmesh.grid.simbench_net.grid_net`: loads as constant
impedances, generators scaled by the study case), solves it with pandapower's ``runpp`` and
returns a :class:`Survey`: every static generator with its bus voltage level, its SimBench
type and profile, its installed power (the net's ``p_mw`` before the study case's scaling, W)
and what it produces at the study case (W), plus the net's size and P_IP (the external grids'
exchange with the sign turned: MV -> HV positive, W).
"""

from __future__ import annotations

from dataclasses import dataclass

from adnmesh.errors import GridError

__all__ = ["Generator", "Survey", "survey_pandapower", "survey_simbench"]


@dataclass(frozen=True)
class Generator:
    """One static generator of the net.

    Attributes
    ----------
    name : str
        Its ``sgen`` name (what a config's ``sgen`` names).
    bus : int
        Its bus (the net's index).
    vn_kv : float
        Its bus's nominal voltage, kV.
    kind, profile : str
        The net's ``type`` and ``profile`` of the generator (``Wind_MV``, ``WP4``).
    p_inst_w : float
        Installed power: the net's ``p_mw`` as stored, W.
    p_case_w : float
        Its infeed at the study case, W (0 out of service).
    """

    name: str
    bus: int
    vn_kv: float
    kind: str
    profile: str
    p_inst_w: float
    p_case_w: float


@dataclass(frozen=True)
class Survey:
    """A net's generators at a study case or time step (see the module docstring).

    ``case`` is the operating point's name (a study case, or
    :func:`adnmesh.grid.simbench_net.time_step_case`); ``when`` its time in brackets for a
    time step (`` (10.02.2016 01:45)``), else "".
    """

    code: str
    case: str
    cases: tuple[str, ...]
    buses: int
    generators: tuple[Generator, ...]
    p_ip_w: float
    ext_grids: int
    when: str = ""


def _text(value) -> str:
    return "" if value is None or value != value else str(value)


def survey_simbench(code: str, case: str) -> Survey:
    """The :class:`Survey` of SimBench ``code`` at study ``case`` (:class:`GridError` for an
    unknown code or study case, or a net whose power flow does not converge there)."""
    from adnmesh.grid.simbench_net import (apply_operating_point, load_simbench_net,
                                           loads_as_impedances)

    net = load_simbench_net(code)
    installed = net.sgen.p_mw.copy()
    when = _when(net, case)
    apply_operating_point(net, case)
    loads_as_impedances(net)
    return _survey(net, installed, code, case, when)


def survey_pandapower(path, case: str | None) -> Survey:
    """The :class:`Survey` of a pandapower net file at study ``case`` of its loadcases table,
    or as saved (``case`` None, a net without one; :mod:`adnmesh.grid.net_file`). Installed
    power is the file's ``p_mw`` (``sn_mva`` where that is larger)."""
    from adnmesh.grid.net_file import net_at_case, read_net

    net, _ = read_net(path)
    installed = net.sgen.p_mw.copy()
    if "sn_mva" in net.sgen:
        rated = net.sgen.sn_mva.astype(float)
        installed = installed.where(~(rated > installed), rated)
    when = _when(net, case)
    used = net_at_case(net, case, "impedance")
    return _survey(net, installed, str(path), used, when)


def _when(net, case: str | None) -> str:
    """`` (10.02.2016 01:45)`` for a time step of the net's profiles, else ""."""
    from adnmesh.grid.simbench_net import time_step_of, time_steps

    step = time_step_of(case)
    if step is None:
        return ""
    times = net.profiles["load"].get("time") if time_steps(net) else None
    return f" ({times.iloc[step]})" if times is not None and 0 <= step < len(times) else ""


def _survey(net, installed, code: str, case: str, when: str = "") -> Survey:
    import pandapower as pp

    from adnmesh.grid.simbench_net import case_words, study_cases

    try:
        pp.runpp(net)
    except pp.LoadflowNotConverged:
        raise GridError(f"grid {code}: the power flow at {case_words(case)} does not "
                        "converge") from None
    sgen = net.sgen
    scaling = sgen.scaling.fillna(1.0)
    on = sgen.in_service.astype(bool)
    generators = tuple(
        Generator(name=_text(sgen.name.at[i]), bus=int(sgen.bus.at[i]),
                  vn_kv=float(net.bus.vn_kv.at[sgen.bus.at[i]]),
                  kind=_text(sgen.type.at[i]) if "type" in sgen else "",
                  profile=_text(sgen.profile.at[i]) if "profile" in sgen else "",
                  p_inst_w=float(installed.at[i]) * 1e6,
                  p_case_w=float(sgen.p_mw.at[i] * scaling.at[i]) * 1e6 if on.at[i] else 0.0)
        for i in sgen.index)
    slack = net.ext_grid.index[net.ext_grid.in_service.astype(bool)]
    return Survey(code=code, case=case, cases=study_cases(net), buses=len(net.bus),
                  generators=generators,
                  p_ip_w=-float(net.res_ext_grid.p_mw.loc[slack].sum()) * 1e6,
                  ext_grids=len(slack), when=when)
