"""The structure of a cascade: which ADNs the upper PI drives, with what gains and delays.

The upper CPFC's output ``P_Y`` (dimensionless) reaches ADN i after the inter-site delay
``T_com,i`` as the offset ``dP_ref,i = P_Y K_i`` (``K_i = w_i C_i``, W), and the sum of the
ADNs' infeed changes comes back after ``T_meas``:

    L_up(s) = C_up(s) exp(-s T_meas) sum_i K_i exp(-s T_com,i) T_i(s).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from adnmesh.cascade.lower_adn import LowerAdn

__all__ = ["Cascade"]


@dataclass(frozen=True)
class Cascade:
    """The ADNs of an upper loop.

    Parameters
    ----------
    adns : tuple of LowerAdn
        The available ADNs (at least one).
    gains_w : tuple of float
        ``K_i = w_i C_i`` per ADN, W (> 0).
    t_com_s : tuple of float
        Inter-site delay upper CPFC -> ADN i, s (>= 0).
    t_meas_s : float
        Delay of the upper measurement, s (>= 0).
    """

    adns: tuple[LowerAdn, ...]
    gains_w: tuple[float, ...]
    t_com_s: tuple[float, ...]
    t_meas_s: float

    def __post_init__(self) -> None:
        n = len(self.adns)
        if n == 0:
            raise ValueError("a cascade needs at least one ADN")
        if len(self.gains_w) != n or len(self.t_com_s) != n:
            raise ValueError("a cascade needs one gain and one delay per ADN")
        if not all(g > 0 for g in self.gains_w):
            raise ValueError("every ADN's gain K_i must be positive")
        if not (all(d >= 0 for d in self.t_com_s) and self.t_meas_s >= 0):
            raise ValueError("the upper loop's delays must be >= 0")

    @property
    def total_gain_w(self) -> float:
        """``sum_i K_i``, W: the DC gain of the upper plant."""
        return float(sum(self.gains_w))

    @property
    def delays_s(self) -> tuple[float, ...]:
        """Every delay of the nested loop (upper and lower), s."""
        lower = tuple(d for adn in self.adns for d in adn.delays_s)
        return (*self.t_com_s, self.t_meas_s, *lower)

    def plant_response(self, omega: np.ndarray) -> np.ndarray:
        """``sum_i K_i exp(-j omega T_com,i) T_i(j omega)``, W, shape (N,); omega in rad/s."""
        omega = np.asarray(omega, dtype=float)
        out = np.zeros(omega.shape, complex)
        for adn, gain, delay in zip(self.adns, self.gains_w, self.t_com_s):
            out += gain * np.exp(-1j * omega * delay) * adn.closed_loop(omega)
        return out

    def open_loop(self, kp: float, ki: float, omega: np.ndarray) -> np.ndarray:
        """``L_up(j omega)``, complex, for the upper PI ``kp`` (1/W), ``ki`` (1/(W s))."""
        omega = np.asarray(omega, dtype=float)
        return ((kp + ki / (1j * omega)) * np.exp(-1j * omega * self.t_meas_s)
                * self.plant_response(omega))
