"""Text outputs of the analyses: markdown tables, CSV rows and JSON documents (no I/O)."""
from __future__ import annotations

import math

from adnmesh.analysis.robustness import ALL_EQUAL, METRICS, RobustnessResult
from adnmesh.analysis.uncertainty import B_RANGE, MODEL_LABELS, QUANTITY_LABELS, Limit, UncertaintyResult

__all__ = ["csv_number", "uncertainty_markdown", "uncertainty_rows", "robustness_markdown", "worst_text",
           "fmt", "REFERENCE_NOTE"]

REFERENCE_NOTE = (
    "b scales every DER time constant (T_unc = b·T). Stability limit: b_min is the largest "
    "b < 1 and b_max the smallest b > 1 at which the closed loop of at least one subset is "
    "unstable. 2·rise time / 2·settling time: the b nearest 1 (below / above) at which the rise "
    "time (10–90 %) or the settling time ({band:g} % band) of at least one subset reaches twice "
    "its nominal value; the nominal value is that of the reference PT1 model at b = 1 for all "
    "three model types, because the table was designed on PT1. An unstable loop counts as "
    "doubled (†: the subset named is unstable there). Scanned range "
    f"[{B_RANGE[0]:g}, {B_RANGE[1]:g}]; limits to 3 significant digits.")


def fmt(value, digits: int = 4) -> str:
    """A number for a table: ``3.142``, ``inf``, ``—`` for missing."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return f"{value:.{digits}g}"


def csv_number(value, digits: int = 6) -> str:
    """A number for a CSV cell that pandas reads as a float: ``3.14159``, ``inf``, empty for
    missing (NaN)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return fmt(value, digits)


def _cell(limit: Limit) -> str:
    dagger = limit.unstable and limit.status == "found" and limit.quantity != "stability"
    return limit.text() + (" †" if dagger else "")


def _who(limit: Limit) -> str:
    if not limit.subsets:
        return "—"
    more = len(limit.subsets) - 1
    return "{" + limit.subsets[0] + "}" + (f" (+{more} more)" if more else "")


def uncertainty_rows(result: UncertaintyResult) -> tuple[list[str], list[list[str]],
                                                         list[list[str]]]:
    """Header, value rows and first-failing-subset rows of the paper-shaped table."""
    header = ["model"] + [f"{QUANTITY_LABELS[q]} {end}" for q in result.quantities
                          for end in ("b_min", "b_max")]
    values, who = [], []
    for ml in result.models:
        label = MODEL_LABELS[ml.model]
        values.append([label] + [_cell(lim) for q in result.quantities for lim in ml.limits[q]])
        who.append([label] + [_who(lim) for q in result.quantities for lim in ml.limits[q]])
    return header, values, who


def _md_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def uncertainty_markdown(results: list[UncertaintyResult]) -> str:
    """Markdown: per controller, the limits table and the subsets that fail first."""
    parts = []
    for res in results:
        header, values, who = uncertainty_rows(res)
        n = len(res.names) - len(res.excluded) - len(res.without_gains)
        parts.append(f"### {res.controller.capitalize()} controller ({n} subsets, "
                     f"{res.loop_classes} distinct loops)\n")
        parts.append(_md_table(header, values) + "\n")
        parts.append("Subsets that fail first:\n")
        parts.append(_md_table(header, who) + "\n")
        if res.without_gains:
            parts.append(f"Left out (no PI pair in the table): {len(res.without_gains)} "
                         f"subset(s), e.g. {{{res.without_gains[0]}}}\n")
        if res.excluded:
            parts.append(f"Left out (nominal loop unstable or not settling): "
                         f"{', '.join('{' + e + '}' for e in res.excluded)}\n")
    band = results[0].band_pct if results else 5.0
    parts.append(REFERENCE_NOTE.format(band=band) + "\n")
    return "\n".join(parts)


def worst_text(s) -> str:
    if not s.worst_subset:
        return "—"
    if s.worst_subset == ALL_EQUAL:
        return f"{fmt(s.worst_value)} (all equal)"
    return f"{fmt(s.worst_value)} ({{{s.worst_subset}}})"


def robustness_markdown(result: RobustnessResult) -> str:
    """Markdown table: per metric and controller, median and worst subset."""
    header = ["figure"]
    for c in result.controllers:
        header += [f"{c} median", f"{c} worst (subset)"]
    rows = []
    summaries = {c: result.summary(c) for c in result.controllers}
    for m in METRICS:
        label = m.label.replace("(band)", f"({result.band_pct:g} % band)")
        row = [label]
        for c in result.controllers:
            s = summaries[c][m.key]
            row += [fmt(s.median), worst_text(s)]
        rows.append(row)
    lines = [_md_table(header, rows)]
    none = result.without_gains()
    if none:
        lines.append(f"\nadaptive: {len(none)} subset(s) without a PI pair in the table "
                     "(not evaluated): " + ", ".join("{" + b + "}" for b in none[:10])
                     + (" …" if len(none) > 10 else ""))
    for c in result.controllers:
        bad = result.unstable(c)
        if bad:
            lines.append(f"\n{c}: {len(bad)} unstable subset(s): "
                         + ", ".join("{" + b + "}" for b in bad[:10])
                         + (" …" if len(bad) > 10 else ""))
    return "\n".join(lines) + "\n"
