"""The commented YAML of a config ``adnmesh init`` writes (pure: text from plain data)."""

from __future__ import annotations

import json
import re

from adnmesh.adn.selection import Selection
from adnmesh.adn.survey import Survey
from adnmesh.adn.template import Planned

__all__ = ["grid_name", "config_text", "T_COM_S", "T_MEAS_S"]

#: the paper's ICT delays, s (docs/method.md#reference-case)
T_COM_S = 0.1
T_MEAS_S = 0.1


def grid_name(code: str) -> str:
    """The config's ``grid`` (bus key segment) for SimBench ``code``: ``simbench-`` and the
    code without its scenario and switch suffix where that is ``--0-no_sw`` (as the reference
    config), else the whole code with other characters as ``-``."""
    base = code[:-len("--0-no_sw")] if code.endswith("--0-no_sw") else code
    return "simbench-" + re.sub(r"[^A-Za-z0-9_-]+", "-", base).strip("-")


def _mw(w: float) -> str:
    return f"{w / 1e6:.3f}"


def _number(value: float) -> str:
    """A power as YAML: ``2.0e+6``-style scientific notation (what the reference config uses)."""
    text = f"{value:.6e}"
    mantissa, exponent = text.split("e")
    mantissa = mantissa.rstrip("0")
    if mantissa.endswith("."):
        mantissa += "0"
    return f"{mantissa}e{int(exponent):+d}"


def config_text(survey: Survey, selection: Selection, dynamics: dict, ids: list[str],
                schedules: list[float], planned: Planned, command: str,
                rules: str, schema: str | None = None, net_file: str | None = None,
                grid: str | None = None) -> str:
    """The config file's text.

    ``dynamics``: DER id -> ``(t_delay_s, t_rise_s, source)``; ``ids`` and ``schedules`` in
    the order of ``selection.actuators``; ``schema``: the path of ``config.schema.json``
    relative to the file, named on its first line for editors (None: no such line);
    ``net_file``: a pandapower net file's path relative to the config (None: SimBench
    ``survey.code``), and ``grid`` the config's grid name then.
    """
    from adnmesh.grid.simbench_net import case_words, time_step_of

    step = time_step_of(survey.case)

    source = f"pandapower net {net_file}" if net_file else f"SimBench {survey.code}"
    acts = selection.actuators
    lines = [f"# yaml-language-server: $schema={schema}"] if schema else []
    lines += [
        f"# Written by: {command}",
        f"# {source} at {case_words(survey.case)}{survey.when}: {survey.buses} buses, "
        f"{len(survey.generators)} static generators, {survey.ext_grids} external grid(s).",
        f"# Actuators ({rules}): {len(acts)}; the other {len(survey.generators) - len(acts)} "
        "generators stay constant injections there.",
    ]
    if survey.ext_grids > 1:
        lines.append(f"# The {survey.ext_grids} external grids are one interconnection point: "
                     "P_IP is their exchange summed (docs/models.md#what-the-grid-model-accepts).")
    if selection.idle:
        lines.append(f"# Left out for producing nothing at {survey.case}: "
                     + ", ".join(g.name for g in selection.idle) + ".")
    lines += [
        f"# Each actuator is scheduled at half its infeed at {case_words(survey.case)} (p_sched_w), "
        "so it can",
        "# move both ways: up to that infeed (its available power), down to 0.",
        "# Dynamics: docs/models.md#der-types (per type; override per DER here or with",
        "# adnmesh init --dynamics / --der-dynamics).",
        "#",
        f"#   {'DER':<10} {'sgen':<26} {'bus':>5} {'SimBench type':<13} {'P_inst MW':>9} "
        f"{'at case MW':>10}  dynamics",
    ]
    for der_id, act in zip(ids, acts):
        g = act.generator
        source = dynamics[der_id][2]
        lines.append(f"#   {der_id:<10} {g.name[:26]:<26} {g.bus:>5} {g.kind[:13]:<13} "
                     f"{_mw(g.p_inst_w):>9} {_mw(g.p_case_w):>10}  {source}")
    lines += [
        "",
        f"grid: {grid or grid_name(survey.code)}",
        *([] if net_file else [f"simbench_code: {survey.code}"]),
        "",
        f"t_com_s: {T_COM_S}    # CPFC -> DER setpoint delay T_com (the paper's)",
        f"t_meas_s: {T_MEAS_S}   # measurement delay T_meas (the paper's)",
        "",
        "constraints:",
        "  disk_margin_min: 1.5      # balanced disk margin alpha",
        "  overshoot_max_pct: 1.0    # overshoot of G_CL step response must stay below this",
        "  settling_band_pct: 5.0",
        "",
        "ders:",
    ]
    for der_id, act, sched in zip(ids, acts, schedules):
        g = act.generator
        t_delay, t_rise, _ = dynamics[der_id]
        lines.append(f"  - {{id: {der_id}, type: {act.der_type}, p_inst_w: {_number(g.p_inst_w)}, "
                     f"t_delay_s: {t_delay:g}, t_rise_s: {t_rise:g}, sgen: {json.dumps(g.name)}, "
                     f"p_sched_w: {_number(sched) if sched else '0.0'}}}")
    lines += ["", "# Sized to the controllable range (docs/configuration.md#adnmesh-init).",
              "scenario:", f"  duration_s: {planned.duration_s:g}", "  p_ref_steps:"]
    for t_s, delta in planned.steps:
        lines.append(f"    - {{t_s: {t_s:g}, delta_w: {'+' if delta > 0 else ''}{_number(delta)}}}")
    if planned.unavailable:
        lines.append("  availability:")
        for t_s, ders in planned.unavailable:
            lines.append(f"    - {{t_s: {t_s:g}, available: false, ders: [{', '.join(ders)}]}}"
                         f"  # the {planned.dropped_type}s")
    lines += [
        "",
        f"# The grid behind P_IP: the AC power flow of the {'net' if net_file else 'SimBench net'} "
        f"at {case_words(survey.case)}, loads as",
        "# constant impedances, every DER's sgen at its infeed.",
        "grid_model:",
        *([f"  pandapower_net: {json.dumps(net_file)}"] if net_file else []),
        *([f"  time_step: {step}"] if step is not None else
          [f"  study_case: {survey.case}"] if survey.cases or not net_file else []),
        "  load_model: impedance",
        "",
    ]
    return "\n".join(lines)
