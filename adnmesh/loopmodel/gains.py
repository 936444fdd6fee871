"""The PI gains the loop numerics take: checked before any of them runs.

Gains are ``K_P`` in 1/W and ``K_I`` in 1/(W s), ~1e-9 for MW-scale plants; normalised by the
installed power ``P`` of the loop's DERs they are ``K_P P`` (dimensionless) and ``K_I P``
(1/s), the numbers the loop's behaviour depends on (docs/method.md#tuning-the-gain-table).
The bounds follow from the numerics:

- finite and positive (a PI with a zero or negative gain is not the design's controller);
- normalised gains at most :data:`MAX_NORMALISED_GAIN`: the tuning searches 0.01-1.2, a loop
  with a dead time is unstable far below 1e6, and beyond it products of the gains with the
  frequency responses overflow (``K_P = 1e300``: ``inf`` and NumPy warnings);
- ``K_P / K_I`` (the PI zero's time constant, s) at most :data:`MAX_PI_ZERO_S`: the certified
  Nyquist argument (:mod:`adnmesh.loopmodel.stability`) bounds the loop below its lowest grid
  frequency, 1e-12 rad/s, which holds only while the PI zero lies well above it (it fails from
  ~1e12 s).

Foundation of the loop model: the standard library only (``adnmesh up`` checks tables with it
without loading the compiled kernels).
"""
from __future__ import annotations

import math

__all__ = ["MAX_NORMALISED_GAIN", "MAX_PI_ZERO_S", "gain_problem"]

MAX_NORMALISED_GAIN = 1e6
"""Largest ``K_P P`` (dimensionless) and ``K_I P`` (1/s) the numerics take."""

MAX_PI_ZERO_S = 1e9
"""Largest ``K_P / K_I``, s."""


def gain_problem(kp: float, ki: float, power_w: float | None = None) -> str | None:
    """Why the PI pair ``kp`` (1/W), ``ki`` (1/(W s)) is outside what the numerics take, as a
    few words (None: it is inside); ``power_w``, the loop's installed power in W, enables the
    check of the normalised gains."""
    for name, value, unit in (("K_P", kp, "1/W"), ("K_I", ki, "1/(W s)")):
        if not (math.isfinite(_float(value)) and _float(value) > 0):
            text = repr(value) if len(repr(value)) <= 40 else repr(value)[:37] + "..."
            return f"{name} must be a finite positive gain ({unit}), got {text}"
    kp, ki = float(kp), float(ki)
    if power_w is not None:
        for name, value, unit in (("K_P", kp, ""), ("K_I", ki, " 1/s")):
            if value * power_w > MAX_NORMALISED_GAIN:
                return (f"{name} {value:.4g} times the {power_w:.4g} W installed is "
                        f"{value * power_w:.4g}{unit}, more than the numerics take "
                        f"({MAX_NORMALISED_GAIN:g}{unit}; tuned loops are near 1)")
    if kp / ki > MAX_PI_ZERO_S:
        return (f"K_P / K_I is {kp / ki:.4g} s, more than the numerics take ({MAX_PI_ZERO_S:g} "
                "s: the stability certificate needs the PI zero above 1e-9 rad/s)")
    return None


def _float(value) -> float:
    """``value`` as a float; NaN for what is no number (booleans included), inf for an integer
    too large for a float (a table's JSON may hold 10**400)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return math.nan
    try:
        return float(value)
    except OverflowError:
        return math.inf
