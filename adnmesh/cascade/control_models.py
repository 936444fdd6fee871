"""A cascade as python-control models: to take the nested loop into python-control.

:func:`cascade_models` gives the upper open loop ``L_up`` and the closed loop (upper
reference -> the ADNs' summed infeed) as ``control.StateSpace`` models: each ADN's closed loop
from :func:`adnmesh.loopmodel.control_models.loop_models`, every delay an order-``order``
Padé approximant, the results diagonally balanced (unbalanced, the nested realisation's
frequency response is off by percents at the crossover). The package's own numerics keep the
delays exact; these models are their independent reference in the tests.
"""
from __future__ import annotations

import control as ct

from adnmesh.cascade.structure import Cascade
from adnmesh.loopmodel.control_models import balanced, loop_models, pade_ss

__all__ = ["cascade_models"]


def cascade_models(cascade: Cascade, kp: float, ki: float,
                   order: int = 10) -> tuple[ct.StateSpace, ct.StateSpace]:
    """``(L_up, G_CL,up)`` with the upper PI ``(kp, ki)`` (1/W, 1/(W s)), delays as Padé."""
    forward = None
    for adn, gain, delay in zip(cascade.adns, cascade.gains_w, cascade.t_com_s):
        _, closed = loop_models(adn.plant, adn.kp, adn.ki, order)
        path = gain * closed
        if delay > 0:
            path = path * pade_ss(delay, order)
        forward = path if forward is None else forward + path
    pi = ct.ss(ct.tf([kp, ki], [1.0, 0.0]))
    meas = (pade_ss(cascade.t_meas_s, order) if cascade.t_meas_s > 0
            else ct.ss([], [], [], [[1.0]]))
    return balanced(pi * forward * meas), balanced(ct.feedback(pi * forward, meas))
