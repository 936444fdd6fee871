"""The year study as tidy files (docs/study.md#files): one row per interval, one per DER, and
the headline figures.

- ``intervals.csv``: one row per interval, the columns of :data:`INTERVAL_COLUMNS` (name,
  unit in the name: ``_mw``, ``_mvar``, ``_s``, ``_pu``, ``_pct``; booleans as 0/1; DER lists
  space-separated). Floats in full precision (Python's shortest round-trip form).
- ``ders.csv``: one row per DER: its share of the year available and why not, its mean
  available power and schedule, and what the year loses without it (:func:`der_rows`).
- ``summary.json``: the headline figures (:func:`summary`).
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np

from adnmesh.files import write_atomic
from adnmesh.study.availability import ICT, LOW_OUTPUT, MAINTENANCE

__all__ = ["INTERVAL_COLUMNS", "write_intervals", "der_rows", "write_ders", "summary",
           "write_summary"]

#: (file column, result column, scale): the interval file's columns in order
INTERVAL_COLUMNS = (
    ("time", "time", None), ("interval", "interval", None),
    ("n_available", "n_available", None), ("available", "available", None),
    ("range_up_mw", "range_up_w", 1e-6), ("range_down_mw", "range_down_w", 1e-6),
    ("linear_up_mw", "linear_up_w", 1e-6), ("linear_down_mw", "linear_down_w", 1e-6),
    ("service", "service", None), ("service_up", "service_up", None),
    ("service_down", "service_down", None),
    ("feasible", "feasible", None), ("rise_s", "rise_s", None),
    ("settling_s", "settling_s", None), ("overshoot_pct", "overshoot_pct", None),
    ("disk_margin", "disk_margin", None), ("settling_up_s", "settling_up_s", None),
    ("settling_down_s", "settling_down_s", None), ("rise_up_s", "rise_up_s", None),
    ("overshoot_up_pct", "overshoot_up_pct", None), ("tuned_on_demand", "tuned_on_demand", None),
    ("p_ip_mw", "p_ip_w", 1e-6), ("q_ip_mvar", "q_ip_var", 1e-6),
    ("vm_min_pu", "vm_min_pu", None), ("vm_min_at", "vm_min_at", None),
    ("vm_max_pu", "vm_max_pu", None), ("vm_max_at", "vm_max_at", None),
    ("line_max_pct", "line_max_pct", None), ("line_max_at", "line_max_at", None),
    ("trafo_max_pct", "trafo_max_pct", None), ("trafo_max_at", "trafo_max_at", None),
    ("converged", "converged", None), ("limited", "limited", None),
    ("violated", "violated", None), ("blocked_up", "blocked_up", None),
    ("blocked_down", "blocked_down", None),
)


def _cells(values: np.ndarray, scale) -> list[str]:
    if values.dtype == bool:
        return ["1" if v else "0" for v in values.tolist()]
    if np.issubdtype(values.dtype, np.datetime64):
        return [str(v) for v in values.astype("datetime64[m]")]
    if np.issubdtype(values.dtype, np.integer):
        return [str(v) for v in values.tolist()]
    if values.dtype == object:
        return ["" if v is None else str(v) for v in values.tolist()]
    scaled = values * scale if scale is not None else values
    return ["" if v != v else repr(v) for v in scaled.tolist()]


def _write_csv(path: Path, header: list[str], rows) -> Path:
    """``header`` and ``rows`` (sequences of cells) as a CSV file, written atomically."""
    def write(fh) -> None:
        text = io.TextIOWrapper(fh, encoding="utf-8", newline="")
        out = csv.writer(text, lineterminator="\n")
        out.writerow(header)
        out.writerows(rows)
        text.flush()
        text.detach()
    return write_atomic(path, write)


def write_intervals(result, path: Path) -> Path:
    """``intervals.csv`` of ``result`` (:class:`adnmesh.study.year.StudyResult`)."""
    columns = [_cells(np.asarray(result.columns[key]), scale)
               for _, key, scale in INTERVAL_COLUMNS]
    return _write_csv(path, [name for name, _, _ in INTERVAL_COLUMNS], zip(*columns))


def der_rows(result) -> list[dict]:
    """One dict per DER: availability shares (of the intervals studied), mean available power
    and schedule (MW), and per interval it was available, the mean range and linear range lost
    up and down without it (MW), the share of those intervals whose service it alone made,
    and the settling time its loss adds (s)."""
    rows = []
    c = result.contribution
    total = len(result)
    for d, der in enumerate(result.der_ids):
        reason = result.reason[:, d]
        n = max(c["intervals_available"][d], 1.0)
        rows.append({
            "der": der,
            "available_share": float(np.mean(reason == 0)),
            "low_output_share": float(np.mean(reason == LOW_OUTPUT)),
            "maintenance_share": float(np.mean(reason == MAINTENANCE)),
            "ict_share": float(np.mean(reason == ICT)),
            "p_avail_mean_mw": float(result.p_avail_w[:, d].mean() * 1e-6) if total else 0.0,
            "p_sched_mean_mw": float(result.p_sched_w[:, d].mean() * 1e-6) if total else 0.0,
            "range_up_lost_mw": float(c["range_up_lost_w"][d] / n * 1e-6),
            "range_down_lost_mw": float(c["range_down_lost_w"][d] / n * 1e-6),
            "linear_up_lost_mw": float(c["linear_up_lost_w"][d] / n * 1e-6),
            "linear_down_lost_mw": float(c["linear_down_lost_w"][d] / n * 1e-6),
            "service_lost_share": float(c["service_lost"][d] / n),
            "settling_added_s": float(c["settling_added_s"][d] / n),
        })
    return rows


def write_ders(result, path: Path) -> Path:
    """``ders.csv`` (:func:`der_rows`)."""
    rows = der_rows(result)
    return _write_csv(path, list(rows[0]), ([repr(v) if isinstance(v, float) else v
                                             for v in r.values()] for r in rows))


def _percentiles(values: np.ndarray, scale: float) -> dict:
    finite = values[np.isfinite(values)]
    if not finite.size:
        return {}
    return {f"p{q}": float(np.percentile(finite, q) * scale) for q in (5, 25, 50, 75, 95)}


def summary(result, config, extra: dict | None = None) -> dict:
    """The headline figures: intervals, the service's share of the year, range and rise time
    percentiles, intervals limited by the grid, subsets met and tuned."""
    col = result.columns
    s = config.study
    times = col["time"]
    out = {
        "intervals": len(result), "interval_s": result.step_s,
        "first": str(times[0]) if len(result) else None,
        "last": str(times[-1]) if len(result) else None,
        "service": {"size_mw": s.service_w / 1e6, "within_s": s.service_s,
                    "share": float(np.mean(col["service"])) if len(result) else 0.0,
                    "share_up": float(np.mean(col["service_up"])) if len(result) else 0.0,
                    "share_down": float(np.mean(col["service_down"])) if len(result) else 0.0},
        "range_up_mw": _percentiles(col["range_up_w"], 1e-6),
        "range_down_mw": _percentiles(col["range_down_w"], 1e-6),
        "linear_up_mw": _percentiles(col["linear_up_w"], 1e-6),
        "linear_down_mw": _percentiles(col["linear_down_w"], 1e-6),
        "rise_s": _percentiles(col["rise_s"], 1.0),
        "settling_s": _percentiles(col["settling_s"], 1.0),
        "limited_share": float(np.mean(col["limited"])) if len(result) else 0.0,
        "violated_share": float(np.mean(col["violated"])) if len(result) else 0.0,
        "not_converged": int(np.sum(~col["converged"])),
        "no_der_available": int(np.sum(col["n_available"] == 0)),
        "subsets": result.subsets, "tuned_on_demand": result.tuned,
    }
    if extra:
        out.update(extra)
    return out


def write_summary(data: dict, path: Path) -> Path:
    """``summary.json`` (NaN written as null)."""
    def clean(v):
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list):
            return [clean(x) for x in v]
        return v
    return write_atomic(path, json.dumps(clean(data), indent=1, allow_nan=False) + "\n")
