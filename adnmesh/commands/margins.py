"""``adnmesh margins CONFIG --kp KP --ki KI``: every figure of merit of one loop."""
from __future__ import annotations

import argparse
import json

from rich.console import Console

from adnmesh.commands import (add_config_argument, add_quantity_argument, der_id_list,
                              load_loop_config)
from adnmesh.errors import UsageError
from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.loopmodel.gains import gain_problem
from adnmesh.loopmodel.plant import plant_from_ders

__all__ = ["add_parser", "run", "loop_report", "parse_der_list"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``margins`` subparser."""
    parser = subparsers.add_parser(
        "margins",
        help="stability, margins and step info of one loop",
        description="Evaluate the reference loop (docs/method.md#reference-model, exact delays) of a "
        "DER subset with PI "
        "gains KP (1/W) and KI (1/(W s)): certified stability, disk margin, classical margins "
        "at all crossovers, step info of P_ref -> P_DERs. Exit code 0 with the figures (an "
        "unstable loop too: it is a figure), 2 for a user error (config, gains, DER ids).",
    )
    add_config_argument(parser)
    add_quantity_argument(parser)
    parser.add_argument("--kp", type=float, required=True, help="proportional gain, 1/W")
    parser.add_argument("--ki", type=float, required=True, help="integral gain, 1/(W s)")
    parser.add_argument("--ders", help="comma-separated DER ids (default: all DERs)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    return parser


def parse_der_list(config, text: str | None) -> list[str]:
    """DER ids from ``"SGen1,SGen5"`` (all DERs for None); one-line error for unknown ids."""
    if text is None:
        return list(config.der_ids())
    return der_id_list(config, text, "--ders")


def loop_report(config, ids: list[str], kp: float, ki: float,
                weights: dict | None = None) -> dict:
    """Figures of merit of the loop (JSON-ready; margins None when unstable)."""
    plant = plant_from_ders(config.ders_by_id(ids), config.design_t_com_s, config.t_meas_s, weights,
                            rise_per_lag=config.rise_per_lag)
    f = evaluate(plant, kp, ki, band_pct=config.constraints.settling_band_pct).row(0)
    c = config.constraints
    stable = f["stable"]
    report = {
        "ders": ids, "kp": kp, "ki": ki, "stable": stable, "certified": f["certified"],
        "unstable_poles": f["unstable_poles"],
        "disk_margin": f["disk_margin"] if stable else None,
        "disk_margin_omega_rad_s": f["disk_omega"],
        "disk_gain_margin": f["disk_gain_margin"] if stable else None,
        "disk_phase_margin_deg": f["disk_phase_margin_deg"] if stable else None,
        "gain_margin": f["gain_margin"], "gain_margin_omega_rad_s": f["gain_margin_omega"],
        "phase_margin_deg": f["phase_margin_deg"],
        "phase_margin_omega_rad_s": f["phase_margin_omega"],
        "delay_margin_s": f["delay_margin_s"],
        "overshoot_pct": f["overshoot_pct"], "rise_time_s": f["rise_time_s"],
        "settling_time_s": f["settling_time_s"], "settling_band_pct": c.settling_band_pct,
        "settling_time_2pct_s": f["settling_time_2pct_s"], "peak": f["peak"],
        "peak_time_s": f["peak_time_s"],
    }
    report["meets_constraints"] = bool(
        stable and f["disk_margin"] >= c.disk_margin_min
        and f["overshoot_pct"] is not None and f["overshoot_pct"] < c.overshoot_max_pct)
    return report


def _fmt(value, unit: str = "", digits: int = 4) -> str:
    if value is None:
        return "—"
    if value == float("inf"):
        return "inf"
    return f"{value:.{digits}g}{unit}"


def run(args: argparse.Namespace) -> int:
    """Print the figures of one loop."""
    problem = gain_problem(args.kp, args.ki)
    if problem is not None:
        raise UsageError(f"--kp/--ki: {problem}")
    config = load_loop_config(args)
    unit = "var" if config.quantity == "Q" else "W"
    ids = parse_der_list(config, args.ders)
    problem = gain_problem(args.kp, args.ki, sum(d.p_inst_w for d in config.ders_by_id(ids)))
    if problem is not None:
        raise UsageError(f"--kp/--ki: {problem}")
    r = loop_report(config, ids, args.kp, args.ki)
    if args.json:
        print(json.dumps(r, allow_nan=False))
        return 0
    out = Console(highlight=False, markup=False, soft_wrap=True)
    out.print(f"{config.quantity} loop of {len(ids)} DER(s): {', '.join(ids)}; K_P "
              f"{args.kp:.4g} 1/{unit}, K_I {args.ki:.4g} 1/({unit} s)")
    if not r["stable"]:
        poles = r["unstable_poles"]
        out.print("closed loop UNSTABLE" + (f" ({poles} poles in the right half-plane)"
                                            if poles > 0 else " (not certifiable: near-marginal)"))
        return 0
    c = config.constraints
    lo, hi = r["disk_gain_margin"]
    out.print(f"stable (certified)        constraints met: {'yes' if r['meets_constraints'] else 'no'}")
    out.print(f"disk margin alpha         {_fmt(r['disk_margin'])}  (>= {c.disk_margin_min:g}) "
              f"at {_fmt(r['disk_margin_omega_rad_s'], ' rad/s')}")
    out.print(f"disk gain margin          [{_fmt(lo)}, {_fmt(hi)}]")
    out.print(f"disk phase margin         ±{_fmt(r['disk_phase_margin_deg'], ' deg')}")
    out.print(f"gain margin               {_fmt(r['gain_margin'])} at "
              f"{_fmt(r['gain_margin_omega_rad_s'], ' rad/s')}")
    out.print(f"phase margin              {_fmt(r['phase_margin_deg'], ' deg')} at "
              f"{_fmt(r['phase_margin_omega_rad_s'], ' rad/s')}")
    out.print(f"delay margin              {_fmt(r['delay_margin_s'], ' s')}")
    out.print(f"overshoot                 {_fmt(r['overshoot_pct'], ' %')}  "
              f"(< {c.overshoot_max_pct:g} %)")
    out.print(f"rise time 10-90 %         {_fmt(r['rise_time_s'], ' s')}")
    out.print(f"settling time {c.settling_band_pct:g} %         {_fmt(r['settling_time_s'], ' s')}")
    out.print(f"settling time 2 %         {_fmt(r['settling_time_2pct_s'], ' s')}")
    out.print(f"peak                      {_fmt(r['peak'])} at {_fmt(r['peak_time_s'], ' s')}")
    return 0
