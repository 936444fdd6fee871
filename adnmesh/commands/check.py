"""``adnmesh check CONFIG``: validate a config and print a short summary of it."""

from __future__ import annotations

import argparse
from collections.abc import Iterable

from rich.console import Console
from rich.table import Table

from adnmesh.commands import add_config_argument
from adnmesh.commands.up_tables import operating_point
from adnmesh.config import DER_TYPES, Config, load_config

__all__ = ["add_parser", "run", "summary_tables"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``check`` subparser."""
    parser = subparsers.add_parser(
        "check",
        help="validate a config and summarise it",
        description="Validate CONFIG and print its grid, DERs, delays, constraints and scenario. "
        "With a grid_model, also the checks 'adnmesh up' makes of the grid before it starts "
        "(SimBench code, study case, every sgen in the net, schedules the DERs can deliver, "
        "the power flow at the schedules). Exit code 0 if valid, 2 with a one-line error "
        "otherwise.",
    )
    add_config_argument(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    """Load ``args.config`` and check it as ``up`` does before it starts (the grid model,
    the DERs' model parameters: :func:`adnmesh.commands.up_tables.operating_point`); print the
    summary to stdout."""
    config = load_config(args.config)
    available = operating_point(config, log=lambda line: None)
    # no markup: "[s]" is a unit, not a style; soft wrap: long paths stay on one line
    console = Console(highlight=False, markup=False, soft_wrap=True)
    c = config.constraints
    console.print(f"{config.path}: valid (sha256 {config.sha256[:12]})")
    source = (f"pandapower net {config.pandapower_net_path()}" if config.pandapower_net_path()
              else f"SimBench {config.simbench_code}" if config.simbench_code else "no grid model")
    console.print(f"grid: {config.grid} ({source})")
    console.print(f"delays: T_com {config.t_com_s:g} s, T_meas {config.t_meas_s:g} s")
    if config.grid_model is not None:
        from adnmesh.control.operating_point import grid_source, initial_p_ip_w

        model = config.grid_model
        from adnmesh.grid.simbench_net import case_words

        point = case_words(grid_source(config)[2])
        console.print(f"grid model: {point}, {model.load_model} loads: "
                      f"P_IP {initial_p_ip_w(config) / 1e6:.4f} MW at the schedules, the DERs "
                      f"can deliver {sum(available.values()) / 1e6:.3f} MW")
        from adnmesh.control.operating_point import reachable_ranges, tap_changer_words

        lim, guard = model.limits, model.guard
        console.print(f"grid limits: {lim.v_min_pu:g} to {lim.v_max_pu:g} p.u., loading "
                      f"<= {lim.loading_max_pct:g} %; guard {guard.mode}"
                      + {"off": " (watches only)",
                         "block": " (holds the control while a limit is violated)"}.get(
                          guard.mode, f" (blocks DERs {guard.v_margin_pu:g} p.u. / "
                                      f"{guard.loading_margin_pct:g} % from a limit)"))
        ranges = reachable_ranges(config)
        if isinstance(ranges, str):
            console.print(f"reachable within the limits: not known, references are not "
                          f"clipped ({ranges})")
        else:
            (p_lo, p_hi), (q_lo, q_hi) = ranges
            console.print(f"reachable within the limits: P_IP {p_lo / 1e6:.3f} to "
                          f"{p_hi / 1e6:.3f} MW, Q_IP {q_lo / 1e6:.3f} to {q_hi / 1e6:.3f} "
                          "Mvar (references beyond are clipped)")
        tap = tap_changer_words(config)
        if tap is not None:
            console.print(tap)
    if config.reactive is not None:
        from adnmesh.control.operating_point import initial_q_ip_var
        from adnmesh.reactive import reactive_view

        r, view = config.reactive, reactive_view(config)
        console.print(f"reactive power: mode {r.mode}, capability {r.capability}, priority "
                      f"{r.priority}; {len(view.ders)} DER(s) with a reactive range of "
                      f"{sum(d.p_inst_w for d in view.ders) / 1e6:.3f} Mvar in all; Q_IP "
                      f"{initial_q_ip_var(config) / 1e6:.4f} Mvar at the schedules")
    devices = [d for d in config.ders if d.plant is not None]
    if devices:
        from adnmesh.devices.connect import link_for

        for der in devices:
            link_for(der, config)          # its points and TLS files, as its gateway takes them
        words = [f"{der.id} {der.plant.protocol} {der.plant.host}:{der.plant.port}"
                 + (" (simulated by up)" if der.plant.simulator else "") for der in devices]
        console.print(f"plant devices: {len(devices)} of {len(config.ders)} DERs behind a "
                      f"protocol, wall clock only (up --clock realtime): {', '.join(words)}")
    console.print(
        f"constraints: disk margin >= {c.disk_margin_min:g}, "
        f"overshoot < {c.overshoot_max_pct:g} %, settling band {c.settling_band_pct:g} %"
    )
    for table in summary_tables(config):
        console.print(table)
    return 0


def _span(values: Iterable[float]) -> str:
    """Format a set of numbers as ``"a"`` or ``"min-max"``."""
    values = sorted(set(values))
    return f"{values[0]:g}" if len(values) == 1 else f"{values[0]:g}-{values[-1]:g}"


def summary_tables(config: Config) -> tuple[Table, Table]:
    """Return the DER table (one row per type) and the scenario event table of ``config``."""
    ders = Table(title=f"{len(config.ders)} DERs", title_justify="left")
    for column in ("type", "count", "P_inst [MW]", "T_delay [s]", "T_rise [s]"):
        ders.add_column(column, justify="left" if column == "type" else "right")
    for der_type in DER_TYPES:
        group = [d for d in config.ders if d.type == der_type]
        if group:
            ders.add_row(
                der_type,
                str(len(group)),
                f"{sum(d.p_inst_w for d in group) / 1e6:.3f}",
                _span(d.t_delay_s for d in group),
                _span(d.t_rise_s for d in group),
            )
    total_mw = sum(d.p_inst_w for d in config.ders) / 1e6
    ders.add_row("total", str(len(config.ders)), f"{total_mw:.3f}", "", "", style="bold")

    scenario = config.scenario
    events = Table(title=f"scenario, {scenario.duration_s:g} s", title_justify="left")
    events.add_column("t [s]", justify="right")
    events.add_column("event")
    rows = [(s.t_s, 0, f"P_ref {s.delta_w / 1e6:+.3f} MW") for s in scenario.p_ref_steps]
    available = set(config.der_ids())
    for change in scenario.availability:
        if change.available:
            available |= set(change.ders)
        else:
            available -= set(change.ders)
        state = "available" if change.available else "unavailable"
        text = f"{state}: {', '.join(change.ders)} -> {len(available)} of {len(config.ders)} left"
        rows.append((change.t_s, 1, text))
    for t_s, _, text in sorted(rows):
        events.add_row(f"{t_s:g}", text)
    if not rows:
        events.add_row("", "no events")
    return ders, events
