"""One MV ADN as an actuator of the level above: its active table entry's exact closed loop.

The lower CPFC closes ``L_i = C_i exp(-s T_com,i) G_i exp(-s T_meas,i)`` over its available
DERs (``G_i = sum_g K_g H_g exp(-s T_delay,g)``, weights applied). The level above adds an
offset ``dP_ref,i`` to the ADN's reference, so what it drives is the closed loop from that
offset to the DERs' infeed,

    T_i(s) = C_i exp(-s T_com,i) G_i / (1 + L_i),       T_i(0) = 1,

the ``G_CL`` of the ADN's own certificate (grid and loads left out, as in the reference model:
the change of ``P_IP`` is the change of the DERs' infeed).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from adnmesh.loopmodel.frequency_response import loop_response
from adnmesh.loopmodel.plant import Actuator, Plant

__all__ = ["LowerAdn", "announced"]


@dataclass(frozen=True)
class LowerAdn:
    """An ADN under its own PI, seen from the level above.

    Parameters
    ----------
    name : str
        The ADN's name (its grid's bus segment).
    plant : Plant
        The available DERs of its active entry, weights applied: gains of shape (G,), W; its
        own ``t_com_s`` and ``t_meas_s``, s.
    kp, ki : float
        The active entry's PI gains, 1/W and 1/(W s).
    capacity_w : float
        What one unit of the upper controller's ``P_Y`` asks of the ADN before weighting, W
        (the installed power of its available DERs: the ADN's ``C_i``).
    """

    name: str
    plant: Plant
    kp: float
    ki: float
    capacity_w: float

    def __post_init__(self) -> None:
        if np.ndim(self.plant.gains_w) != 1:
            raise ValueError(f"ADN {self.name}: its plant needs one gain per group (shape (G,))")
        if not (self.kp > 0 and self.ki > 0):
            raise ValueError(f"ADN {self.name}: K_P and K_I must be positive")
        if not self.capacity_w > 0:
            raise ValueError(f"ADN {self.name}: capacity_w must be positive")

    @property
    def delays_s(self) -> tuple[float, ...]:
        """Every delay of its loop: the forward paths ``T_com + T_delay,g`` and ``T_meas``, s."""
        return (*self.plant.path_delays_s.tolist(), float(self.plant.t_meas_s))

    def closed_loop(self, omega: np.ndarray) -> np.ndarray:
        """``T_i(j omega)``, complex, shape (N,), at ``omega`` (rad/s, > 0); exact delays."""
        omega = np.asarray(omega, dtype=float)
        loop = loop_response(self.plant, self.kp, self.ki, omega)[0]
        return loop * np.exp(1j * omega * self.plant.t_meas_s) / (1.0 + loop)


def announced(name: str, message) -> LowerAdn:
    """The ADN as its CPFC announced itself in an ``adn_actuator`` message (an object with the
    fields of :class:`adnmesh.wire.messages.AdnActuator`: ``groups`` of ``t_delay_s``,
    ``t_lag_s``, ``model``, ``gain_w``; ``t_com_s``, ``t_meas_s``, ``kp``, ``ki``,
    ``capacity_w``)."""
    groups = [g for g in message.groups if g.gain_w > 0]
    plant = Plant(tuple(Actuator(g.t_delay_s, g.t_lag_s, g.model) for g in groups),
                  np.array([g.gain_w for g in groups]), message.t_com_s, message.t_meas_s)
    return LowerAdn(name, plant, message.kp, message.ki, message.capacity_w)
