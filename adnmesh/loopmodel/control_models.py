"""A loop of adnmesh as python-control models: to take it into python-control.

:func:`loop_models` gives the open loop L(s) and the closed loop G_CL(s) of a
:class:`~adnmesh.loopmodel.plant.Plant` under a PI pair as ``control.StateSpace`` models, each
delay replaced by a Padé approximant, so that python-control's tools (``bode_plot``,
``disk_margins``, ``step_response``, ``feedback`` with a controller of one's own) apply. The
package's own numerics keep the delays exact (docs/method.md); these models are approximations
whose accuracy grows with ``order`` (the tests use them, order 10, as the independent reference
of the exact numerics).

Units as in :class:`~adnmesh.loopmodel.plant.Plant`: P_Y in, P_IP out, W; ``kp`` in 1/W,
``ki`` in 1/(W s); time in s.

Realisation: a forward path's two delays (T_com + T_delay,g) share one approximant, since an
order-10 Padé of a 10 ms delay alone has coefficients near 1e-20; the state-space models are
diagonally balanced (without it, the companion realisation of a 1.1 s order-10 Padé overflows
in a matrix exponential).
"""
from __future__ import annotations

import control as ct
import numpy as np
import scipy.linalg

from adnmesh.loopmodel.plant import Actuator, Plant

__all__ = ["actuator_tf", "balanced", "loop_models", "pade_ss"]


def pade_ss(delay_s: float, order: int) -> ct.StateSpace:
    """The Padé approximant of order ``order`` of a delay of ``delay_s`` s, as state space."""
    num, den = ct.pade(delay_s, order)
    return ct.ss(ct.tf(num, den))


def actuator_tf(act: Actuator) -> ct.TransferFunction:
    """A group's normalised actuator dynamics (without its delay) as a transfer function."""
    return ct.tf(act.numerator[::-1], act.denominator[::-1])


def balanced(sys: ct.StateSpace) -> ct.StateSpace:
    """``sys`` with its A matrix diagonally balanced (the same transfer function)."""
    _, (scale, _) = scipy.linalg.matrix_balance(sys.A, permute=False, separate=True)
    return ct.ss(sys.A / scale[:, None] * scale[None, :], sys.B / scale[:, None],
                 sys.C * scale[None, :], sys.D)


def loop_models(plant: Plant, kp: float, ki: float,
                order: int = 10) -> tuple[ct.StateSpace, ct.StateSpace]:
    """``(L, G_CL)``: the open loop PI · forward paths · measurement and the closed loop from
    P_ref to P_IP, with every delay as an order-``order`` Padé approximant."""
    pi = ct.ss(ct.tf([kp, ki], [1.0, 0.0]))
    forward = None
    for act, gain, delay in zip(plant.actuators, np.atleast_1d(plant.gains_w),
                                plant.path_delays_s):
        if gain == 0:
            continue
        path = ct.ss(gain * actuator_tf(act)) * pade_ss(delay, order)
        forward = path if forward is None else forward + path
    meas = pade_ss(plant.t_meas_s, order) if plant.t_meas_s > 0 else ct.ss([], [], [], [[1.0]])
    return balanced(pi * forward * meas), balanced(ct.feedback(pi * forward, meas))
