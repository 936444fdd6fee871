"""``adnmesh study --verify N``: the distributed runtime on the year's most demanding intervals.

The N intervals are the most demanding ones in which a step up of the service's size stays
linear (no DER saturates; :mod:`adnmesh.study.ranges`), whatever its speed: the fewest
available DERs first, then the slowest entry (the longest predicted settling time), one per
distinct set of available DERs. For each, a config of that operating point is written
(the grid model at the interval's time step, each DER's schedule the study's, the DERs the
study found unavailable leaving at t = 0, the reference DER models, no faults) with one step
of P_ref by ``study.service_w`` at t = 5 s, and ``adnmesh up`` runs it on the sim clock as its
own process tree. The step's measured rise time, settling time and overshoot (the run's
summary) stand beside the study's predicted ones.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

from adnmesh.errors import UsageError

__all__ = ["demanding", "verify_config", "verify", "STEP_AT_S", "RUN_TIMEOUT_S"]

STEP_AT_S = 5.0
#: the longest a verifying run may take, s (wall)
RUN_TIMEOUT_S = 600


def demanding(result, n: int) -> list[int]:
    """Row indices of the ``n`` most demanding intervals (module docstring)."""
    col = result.columns
    linear = col["linear_up_w"] >= result.service_w
    rows = np.flatnonzero(linear & np.isfinite(col["settling_up_s"]) & (col["n_available"] > 0))
    order = np.lexsort((-np.nan_to_num(col["settling_up_s"][rows]),
                        col["n_available"][rows]))
    chosen, seen = [], set()
    for row in rows[order].tolist():
        key = col["available"][row]
        if key in seen:
            continue
        seen.add(key)
        chosen.append(row)
        if len(chosen) == n:
            break
    return chosen


def verify_config(config, result, row: int) -> dict:
    """The config document (plain data) of interval ``row``'s operating point with one step
    of the service size (module docstring)."""
    from adnmesh.config import ConfigFile

    document = config.model_dump(mode="json", exclude_unset=True,
                                 include=set(ConfigFile.model_fields) - {"extends"})
    step = int(result.columns["interval"][row])
    grid_model = dict(document.get("grid_model", {}))
    grid_model.pop("study_case", None)
    grid_model["time_step"] = step
    document["grid_model"] = grid_model
    unavailable = [d for d, reason in zip(result.der_ids, result.reason[row]) if reason != 0]
    ders = []
    for d, der in enumerate(document["ders"]):
        der = dict(der)
        der["p_sched_w"] = float(np.floor(result.p_sched_w[row, d]))
        ders.append(der)
    document["ders"] = ders
    settling = result.columns["settling_up_s"][row]
    duration = STEP_AT_S + max(20.0, 4.0 * (settling if settling == settling else 20.0))
    document["scenario"] = {
        "duration_s": float(min(duration, 900.0)),
        "p_ref_steps": [{"t_s": STEP_AT_S, "delta_w": config.study.service_w}],
        **({"availability": [{"t_s": 0.0, "available": False, "ders": unavailable}]}
           if unavailable else {}),
    }
    runtime = dict(document.get("runtime", {}))
    runtime.pop("faults", None)
    runtime["der_models"] = "reference"
    document["runtime"] = runtime
    document.pop("study", None)
    return document


def _run(path: Path, table: Path, out: Path) -> dict:
    summary = out.with_suffix(".summary.json")
    argv = [sys.executable, "-m", "adnmesh", "up", str(path), "--table", str(table), "--out",
            str(out), "--summary-json", str(summary)]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=RUN_TIMEOUT_S,
                          check=False)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise UsageError(f"study --verify: the run of {path.name} failed: {last}")
    return json.loads(summary.read_text())


def verify(config, result, n: int, out_dir: Path, table: Path, console) -> dict:
    """Run the ``n`` most demanding intervals (module docstring); the rows of predicted and
    measured figures, also written to ``out_dir/verify/``."""
    folder = Path(out_dir) / "verify"
    folder.mkdir(parents=True, exist_ok=True)
    col = result.columns
    rows = []
    for row in demanding(result, n):
        step = int(col["interval"][row])
        path = folder / f"interval-{step}.yaml"
        path.write_text(yaml.safe_dump(verify_config(config, result, row), sort_keys=False))
        console.print(f"verify: interval {step} ({col['time'][row]}, "
                      f"{col['n_available'][row]} DERs available): adnmesh up {path}")
        summary = _run(path, table, folder / f"interval-{step}.mcap")
        figures = (summary.get("steps") or [{}])[0].get("figures", {})
        rows.append({
            "interval": step, "time": str(col["time"][row]),
            "available": col["available"][row],
            "predicted_rise_s": float(col["rise_up_s"][row]),
            "predicted_settling_s": float(col["settling_up_s"][row]),
            "predicted_overshoot_pct": float(col["overshoot_up_pct"][row]),
            "measured_rise_s": figures.get("rise_time_s"),
            "measured_settling_s": figures.get("settling_time_s"),
            "measured_overshoot_pct": figures.get("overshoot_pct"),
            "speed_factor": summary.get("speed_factor"),
        })
    return {"rows": rows, "folder": str(folder)}
