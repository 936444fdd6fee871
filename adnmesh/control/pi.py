"""The CPFC's sampled PI controller with bumpless gain switching and anti-windup
(docs/method.md#runtime-behaviour).

Parallel form, sampled every ``h`` seconds::

    x_I[k] = x_I[k-1] + h/2 (e[k-1] + e[k])          (trapezoidal rule)
    P_Y[k] = K_P e[k] + K_I x_I[k]                   (held until the next sample)

with ``e = P_ref - P_meas`` in W, ``K_P`` in 1/W, ``K_I`` in 1/(W s), ``x_I`` in W s and ``P_Y``
dimensionless. The trapezoidal rule makes ``P_Y[k]`` a second-order accurate sample of the
continuous PI of the reference model, so the only first-order difference between the runtime and
the continuous-time analysis is the zero-order hold of ``P_Y`` (about half a period of extra
delay).

**Anti-windup** (conditional integration): the output is limited to ``[y_min, y_max]``, the range
in which at least one actuator is not saturated; while the unlimited output lies beyond a limit
and the error pushes further out, the integrator holds.

**Bumpless switching**: :meth:`SampledPI.switch` replaces the gains at sample ``k`` after the
output has been computed with the old ones, and sets ``x_I' = (P_Y[k] - K_P' e[k]) / K_I'`` so that
``K_P' e[k] + K_I' x_I' = P_Y[k]``: the whole output stays continuous, not only the integral part
(for ``K_P' = K_P`` this is the paper's ``K_I' x_I' = K_I x_I``). An output outside the new
actuators' range is first limited to it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["SampledPI", "SwitchRecord"]


@dataclass(frozen=True)
class SwitchRecord:
    """What a gain switch did.

    Attributes
    ----------
    p_y_before, p_y_after : float
        Output with the old gains and with the new gains at the switching sample (equal up to
        rounding unless the old output lies outside the new limits).
    kp_before, ki_before : float
        The old gains, 1/W and 1/(W s).
    p_y_limited : float
        The old output, scaled, limited to the new output range: what the new gains continue
        from.
    scale : float
        Factor applied to the old output first (1: the output itself is continuous; see the
        CPFC for when it differs).
    """

    p_y_before: float
    p_y_after: float
    kp_before: float
    ki_before: float
    p_y_limited: float
    scale: float = 1.0


class SampledPI:
    """Sampled PI controller (see the module docstring).

    Parameters
    ----------
    kp : float
        Proportional gain, 1/W (> 0).
    ki : float
        Integral gain, 1/(W s) (> 0).
    period_s : float
        Sampling period ``h``, s.
    y_min, y_max : float
        Output limits (dimensionless).
    """

    def __init__(self, kp: float, ki: float, period_s: float, y_min: float = -math.inf,
                 y_max: float = math.inf) -> None:
        if not (kp > 0 and ki > 0 and period_s > 0):
            raise ValueError("need kp > 0, ki > 0 and period_s > 0")
        self.kp, self.ki, self.h = float(kp), float(ki), float(period_s)
        self.y_min, self.y_max = float(y_min), float(y_max)
        self.x_i = 0.0          # integrator state, W s
        self.e_prev = 0.0       # error at the previous sample, W
        self.output = 0.0       # P_Y at the last sample
        self.holding = False    # integrator held at the last sample (anti-windup)

    def update(self, error_w: float, freeze: bool = False) -> float:
        """Take the error of the current sample, W; return ``P_Y``. ``freeze``: hold the
        integrator this sample (the actuators cannot follow it)."""
        x_trial = self.x_i + 0.5 * self.h * (self.e_prev + error_w)
        u_trial = self.kp * error_w + self.ki * x_trial
        self.holding = (freeze or (u_trial > self.y_max and error_w > 0)
                        or (u_trial < self.y_min and error_w < 0))
        if not self.holding:
            self.x_i = x_trial
        self.e_prev = error_w
        u = self.kp * error_w + self.ki * self.x_i
        self.output = min(max(u, self.y_min), self.y_max)
        return self.output

    def reenter(self, error_w: float) -> None:
        """Continue after a hold from the held output, with the error of this sample: set
        ``x_I = (P_Y - K_P e) / K_I`` and the previous error to ``e``, so that the output does
        not jump when control resumes (the same rule as a gain switch)."""
        self.output = min(max(self.output, self.y_min), self.y_max) + 0.0
        self.x_i = (self.output - self.kp * error_w) / self.ki
        self.e_prev = error_w

    def set_limits(self, y_min: float, y_max: float) -> None:
        """Change the output limits (they depend on the actuators in use)."""
        self.y_min, self.y_max = float(y_min), float(y_max)

    def switch(self, kp: float, ki: float, scale: float = 1.0) -> SwitchRecord:
        """Switch to new gains right after :meth:`update`, continuing from ``scale`` times the
        output (``scale`` 1: ``P_Y`` continuous).

        Uses the error of the last sample: ``x_I' = (s P_Y - K_P' e) / K_I'``. If the limits
        changed with the switch (other actuators) and ``s P_Y`` lies outside the new range, the
        new gains continue from the nearest limit (every new actuator was saturated there
        anyway), so the integrator never starts wound up.
        """
        if not (kp > 0 and ki > 0 and scale >= 0):
            raise ValueError("need kp > 0, ki > 0 and scale >= 0")
        before = self.output
        limited = min(max(before * scale, self.y_min), self.y_max)
        record_kp, record_ki = self.kp, self.ki
        self.kp, self.ki = float(kp), float(ki)
        self.x_i = (limited - self.kp * self.e_prev) / self.ki
        after = self.kp * self.e_prev + self.ki * self.x_i
        self.output = min(max(after, self.y_min), self.y_max) + 0.0       # no -0.0
        return SwitchRecord(before, self.output, record_kp, record_ki, limited, float(scale))

    def snapshot(self) -> tuple[float, float, float]:
        """The state ``(x_I, previous error, output)``, for :meth:`restore`."""
        return self.x_i, self.e_prev, self.output

    def restore(self, state: tuple[float, float, float]) -> None:
        """Go back to a state taken by :meth:`snapshot` (undo the samples since)."""
        self.x_i, self.e_prev, self.output = state
