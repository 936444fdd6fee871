"""The uncertainty set a DER's fits imply: the intervals of ``constraints.robust``
(docs/tuning.md#robust-tables) that cover the configured reference model and every fit.

Per DER type, over its DERs' fits (a whole run's and, with ``--steps``, each window's): the
factor ``b`` of the time constant from the lowest to the highest end of the fits' 95 %
intervals of ``T_rise`` over the configured ``t_rise_s``, and the added dead time likewise
(fitted minus configured ``t_delay_s``), each interval stretched to hold the configured model
itself (``b = 1``, nothing added). The structures are those fitted.
"""
from __future__ import annotations

import math

__all__ = ["implied_set", "B_FLOOR"]

#: the lowest factor written (an interval reaching 0 s of rise time is no actuator)
B_FLOOR = 0.01
#: a factor this close to 1, or an added dead time this close to 0 s, is the configured
#: model (the fits' intervals of an exactly matching DER end a rounding error away)
B_SAME = 1e-3
DELAY_SAME_S = 1e-3


def _round_out(low: float, high: float) -> tuple[float, float]:
    """``[low, high]`` widened to 4 significant digits (never narrower than found)."""

    def rounded(x: float, to) -> float:
        if x == 0:
            return 0.0
        step = 10 ** (math.floor(math.log10(abs(x))) - 3)
        return float(f"{to(x / step) * step:.6g}")

    return rounded(low, math.floor), rounded(high, math.ceil)


def implied_set(config, fits) -> dict:
    """``constraints.robust`` (plain data) covering ``fits``: an iterable of ``(der id,
    ModelFit)``; DER ids must be the config's."""
    given = {d.id: d for d in config.ders}
    models: dict[str, None] = {}
    types: dict[str, list] = {}
    for der, fit in fits:
        d = given[der]
        models.setdefault(fit.model)
        b = [r / d.t_rise_s for r in fit.rise_ci_s]
        shift = [x - d.t_delay_s for x in fit.delay_ci_s]
        box = types.setdefault(d.type, [1.0, 1.0, 0.0, 0.0])
        b = [1.0 if abs(x - 1.0) < B_SAME else x for x in b]
        shift = [0.0 if abs(x) < DELAY_SAME_S else x for x in shift]
        box[0], box[1] = min(box[0], b[0]), max(box[1], b[1])
        box[2], box[3] = min(box[2], shift[0]), max(box[3], shift[1])
    out = {}
    for t, (b_lo, b_hi, d_lo, d_hi) in types.items():
        lag = _round_out(max(b_lo, B_FLOOR), b_hi)
        delay = _round_out(d_lo, d_hi)
        out[t] = {"lag_scale": list(lag), "delay_add_s": list(delay)}
    return {"models": list(models), "types": out}
