"""The upper table: gain-scheduled on which ADNs are available, tuned on their equivalent
models, certified on the exact cascade.

1. Each ADN is described by its active entry (:func:`lower_adn`) and the equivalent model of
   its closed loop (:mod:`adnmesh.cascade.equivalent`).
2. The upper level is written as an ordinary adnmesh config (:func:`upper_config_document`):
   one actuator per ADN, of installed power its capacity ``C_i``, dead time ``D_eq,i`` plus its
   inter-site delay, rise time ``T_eq,i ln 9``; so every subset of ADNs is tuned by the table
   machinery every ADN's own table comes from (paper path search, Find W, certificate).
3. Every entry is then certified on the exact cascade (:func:`certify_entries`): the upper PI
   with the entry's weights over the available ADNs' exact closed loops and delays. Where the
   equivalent model was optimistic, both gains are backed off by the smallest power of
   :data:`~adnmesh.cascade.certificate.BACK_OFF_STEP` that meets the constraints; the entry's
   figures become those of the cascade, and what the equivalent models gave is kept under
   ``equivalent``. An entry that needed a back-off is then tuned on the exact cascade itself
   (:mod:`adnmesh.cascade.refine`: the ratio ``K_I/K_P`` searched, each ratio at its largest
   certified gains), since the back-off keeps the equivalent models' ratio.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

from adnmesh.cascade.certificate import CascadeFigures, back_off, cascade_figures
from adnmesh.cascade.equivalent import Equivalent
from adnmesh.cascade.lower_adn import LowerAdn
from adnmesh.cascade.refine import refine
from adnmesh.cascade.structure import Cascade
from adnmesh.loopmodel.plant import plant_from_ders
from adnmesh.tuning.table import SchedulingTable, TableEntry

__all__ = ["Site", "lower_adn", "upper_config_document", "upper_t_com_s", "certify_entries",
           "cascade_of", "CertifiedRow"]

#: grid of the equivalent models' delays in the upper config, s (the configs' delays are
#: taken to whole milliseconds by the cascade's simulation)
DELAY_GRID_S = 1e-3


@dataclass(frozen=True)
class Site:
    """One ADN at its site, as the upper level sees it."""

    id: str
    adn: LowerAdn
    t_com_s: float
    equivalent: Equivalent
    p_sched_w: float = 0.0
    """Its room below its schedule: the schedules of the entry's DERs, W."""
    p_ip0_w: float = 0.0
    """Its exchange with the level above in its operating point, W (MV -> HV positive)."""
    q_ip0_var: float = 0.0
    """... and its reactive exchange there, var (MV -> HV positive)."""
    grid_gain: float = 1.0
    """How the upper P_IP moves with its exchange, W/W: ``∂P_IP/∂P`` of the HV grid at its
    bus (below 1 by the HV losses it causes); 1 without an HV grid."""


@dataclass(frozen=True)
class CertifiedRow:
    """One upper entry before and after its certificate on the exact cascade: the back-off
    factor and the rise time it gave, and the final figures (after the refinement, if any)."""

    adns: tuple[str, ...]
    back_off: float | None
    cascade: CascadeFigures
    backed_off_rise_time_s: float
    equivalent_rise_time_s: float
    equivalent_overshoot_pct: float
    equivalent_disk_margin: float


def lower_adn(config, entry: TableEntry, name: str) -> LowerAdn:
    """The ADN of ``config`` under its table ``entry`` (weights applied, its design T_com)."""
    ders = config.ders_by_id(entry.ders)
    plant = plant_from_ders(ders, config.design_t_com_s, config.t_meas_s, entry.w,
                            rise_per_lag=config.rise_per_lag)
    return LowerAdn(name, plant, float(entry.kp), float(entry.ki),
                    float(sum(d.p_inst_w for d in ders)))


def upper_config_document(hierarchy, sites: list[Site], hv_net: str | None = None) -> dict:
    """The upper level as an adnmesh config document (YAML-ready): one ``GEN`` actuator per
    ADN with its equivalent model; ``t_com_s`` the shortest inter-site delay (at least 1 ms)
    and each ADN's remainder in its dead time, to whole milliseconds. Each ADN's DER runs from
    0 to its installed power with its room below its schedule as ``p_sched_w``. Without an HV
    grid, ``rest_of_grid_w`` makes the upper P_IP the sum of the ADNs' exchanges; with one
    (``hv_net``: its net file with the ADNs attached, :mod:`adnmesh.grid.hv_attach`, relative
    to the config), P_IP is its exchange with the level above. The scenario and faults are
    the hierarchy file's."""
    t_com = upper_t_com_s(sites)
    ders = []
    for site in sites:
        eq = site.equivalent
        delay = max(eq.delay_s + site.t_com_s - t_com, 0.0)
        ders.append({"id": site.id, "type": "GEN", "p_inst_w": site.adn.capacity_w,
                     "p_sched_w": site.p_sched_w,
                     "t_delay_s": round(delay / DELAY_GRID_S) * DELAY_GRID_S,
                     "t_rise_s": float(f"{eq.t_rise_s:.6g}"), "sgen": site.id})
    constraints = hierarchy.constraints.model_dump() | {"sampled_pi": False}
    runtime = {} if hv_net else {"rest_of_grid_w": sum(s.p_ip0_w - s.p_sched_w for s in sites)}
    if hierarchy.faults:
        runtime["faults"] = [f.model_dump(mode="json", exclude_none=True)
                             for f in hierarchy.faults]
    grid = {} if hv_net is None else {"grid_model": {
        "pandapower_net": hv_net, "load_model": hierarchy.hv_grid.load_model}}
    return {"grid": hierarchy.name, "t_com_s": t_com, "t_meas_s": hierarchy.t_meas_s,
            "constraints": constraints, "ders": ders,
            "scenario": hierarchy.scenario.model_dump(mode="json", exclude_defaults=True) | {
                "duration_s": hierarchy.scenario.duration_s}, **grid, "runtime": runtime}


def upper_t_com_s(sites: list[Site]) -> float:
    """The upper config's ``t_com_s``: the shortest inter-site delay, at least 1 ms, s."""
    return max(min(s.t_com_s for s in sites), DELAY_GRID_S)


def cascade_of(sites: dict[str, Site], entry: TableEntry, t_meas_s: float) -> Cascade:
    """The exact cascade of an upper entry: its ADNs with ``K_i = w_i C_i g_i`` (W; ``g_i``
    the site's :attr:`~Site.grid_gain`)."""
    chosen = [sites[i] for i in entry.ders]
    return Cascade(tuple(s.adn for s in chosen),
                   tuple(entry.w[s.id] * s.adn.capacity_w * s.grid_gain for s in chosen),
                   tuple(s.t_com_s for s in chosen), t_meas_s)


def _finite(value):
    return value if value is not None and math.isfinite(value) else None


def _number(value) -> float:
    return math.nan if value is None else float(value)


def _cascade_figures(fig: CascadeFigures, factor: float | None) -> dict:
    """The table's figures of an entry from its cascade (margins other than the disk margin
    are not computed on the cascade: None)."""
    return {"rise_time_s": _finite(fig.rise_time_s),
            "settling_time_s": _finite(fig.settling_time_s),
            "settling_time_2pct_s": _finite(fig.settling_time_2pct_s),
            "overshoot_pct": _finite(fig.overshoot_pct), "disk_margin": fig.disk_margin,
            "gain_margin": None, "phase_margin_deg": None, "delay_margin_s": None,
            "cascade_back_off": factor, "certified_on": "cascade"}


def _certified(entry: TableEntry, factor: float | None, fig: CascadeFigures, constraints,
               gains: tuple[float, float] | None = None):
    """The entry with the backed-off (or ``gains``: the refined) gains and the cascade's
    figures; what the tuning on the equivalent models found is kept under ``equivalent``."""
    figures = _cascade_figures(fig, factor) | {"equivalent": dict(entry.figures)}
    if factor is None:
        return replace(entry, feasible=False, figures=figures,
                       reason=fig.problem(constraints.disk_margin_min,
                                          constraints.overshoot_max_pct))
    if gains is not None:
        figures["refined_on_cascade"] = True
        return replace(entry, kp=gains[0], ki=gains[1], figures=figures)
    return replace(entry, kp=entry.kp * factor, ki=entry.ki * factor, figures=figures)


def certify_entries(table: SchedulingTable, sites: dict[str, Site], t_meas_s: float,
                    constraints, on_entry=None, refine_backed_off: bool = True
                    ) -> list[CertifiedRow]:
    """Certify (and back off) every feasible entry of ``table`` on the exact cascade, in
    place; an entry that needed a back-off is then tuned on the exact cascade
    (:func:`~adnmesh.cascade.refine.refine`) unless ``refine_backed_off`` is false;
    ``on_entry(done, total)`` after each. Returns one row per entry (its final figures)."""
    rows = []
    entries = list(table.entries.values())
    for done, entry in enumerate(entries, 1):
        if entry.feasible:
            cascade = cascade_of(sites, entry, t_meas_s)
            factor, fig = back_off(cascade, entry.kp, entry.ki, constraints.disk_margin_min,
                                   constraints.overshoot_max_pct, constraints.settling_band_pct)
            gains, backed_off_rise = None, fig.rise_time_s
            if factor is not None and factor < 1.0 and refine_backed_off:
                kp, ki, fig = refine(cascade, entry.kp * factor, entry.ki * factor, fig,
                                     constraints)
                gains = (kp, ki)
            table.add(_certified(entry, factor, fig, constraints, gains))
            rows.append(CertifiedRow(entry.ders, factor, fig, backed_off_rise,
                                     _number(entry.figures.get("rise_time_s")),
                                     _number(entry.figures.get("overshoot_pct")),
                                     _number(entry.figures.get("disk_margin"))))
        if on_entry:
            on_entry(done, len(entries))
    if table.static is not None and table.static.feasible:
        table.static = _certified_static(table, sites, t_meas_s, constraints)
    return rows


def _certified_static(table, sites, t_meas_s, constraints) -> TableEntry:
    """The static pair backed off until the cascade of every subset meets the constraints."""
    static = table.static
    factor = 1.0
    for entry in table.entries.values():
        subset = replace(static, ders=entry.ders, w={i: 1.0 for i in entry.ders})
        cascade = cascade_of(sites, subset, t_meas_s)
        found, fig = back_off(cascade, static.kp * factor, static.ki * factor,
                              constraints.disk_margin_min, constraints.overshoot_max_pct,
                              constraints.settling_band_pct)
        if found is None:
            return _certified(static, None, fig, constraints)
        factor *= found
    # a lower factor found for a later subset: the earlier ones are checked again at it; the
    # figures are the worst over every subset at the final factor
    figs = []
    for entry in table.entries.values():
        cascade = cascade_of(sites, replace(static, ders=entry.ders,
                                            w={i: 1.0 for i in entry.ders}), t_meas_s)
        fig = cascade_figures(cascade, static.kp * factor, static.ki * factor,
                              constraints.settling_band_pct)
        if fig.problem(constraints.disk_margin_min, constraints.overshoot_max_pct):
            return _certified(static, None, fig, constraints)
        figs.append((entry.ders, fig))
    slowest = max(figs, key=lambda f: f[1].rise_time_s)
    certified = _certified(static, factor, slowest[1], constraints)
    certified.figures.update(
        worst_rise_time_s=_finite(slowest[1].rise_time_s),
        worst_rise_time_subset=list(slowest[0]),
        min_disk_margin=min(f.disk_margin for _, f in figs),
        max_overshoot_pct=_finite(max(f.overshoot_pct for _, f in figs)),
        max_settling_time_s=_finite(max(f.settling_time_s for _, f in figs)))
    return certified
