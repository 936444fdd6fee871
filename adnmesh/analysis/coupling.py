"""The P and Q loops together: the coupled 2×2 loop on the linearised grid, exact delays
(docs/method.md#coupling-of-p-and-q).

Each loop is designed alone: P_Y moves the DERs' active power, Q_Y their reactive power, and
tuning assumes each moves only its own quantity at the interconnection point. Through the
grid each moves the other too: ``∂P_IP/∂Q_d`` (losses) and ``∂Q_IP/∂P_d`` (the lines' and
transformers' reactive losses), :mod:`adnmesh.grid.sensitivity`. With

    G_xy(s) = Σ_d (∂x_IP/∂y_d) · w_d^y C_d^y · e^(−s T_delay,d^y) / (1 + s T_d^y)

(output y ∈ {P_Y, Q_Y} to measured x ∈ {P_IP, Q_IP}), the PIs ``C_P``, ``C_Q`` and the ICT
delays ``τ = T_com + T_meas``, the loop matrix is

    L(s) = e^(−sτ) [[G_PP C_P, G_PQ C_Q], [G_QP C_P, G_QQ C_Q]],

and ``det(I + L) = (1 + L_P)(1 + L_Q)(1 − M)`` with the diagonal loops ``L_P = e^(−sτ) G_PP C_P``,
``L_Q = e^(−sτ) G_QQ C_Q`` and the **coupling function**

    M(s) = [e^(−sτ) G_PQ C_Q / (1 + L_Q)] · [e^(−sτ) G_QP C_P / (1 + L_P)].

If both diagonal loops are stable (checked here with the grid's gains ``∂P_IP/∂P_d`` and
``∂Q_IP/∂Q_d``, not the unit gains of the design), M is stable (each factor is a closed-loop
transfer function; the PI's integrator cancels against the zero of ``1/(1 + L)`` at s = 0),
and ``max_ω |M(jω)| < 1`` means ``1 − M`` cannot encircle the origin: the coupled loop is
stable (small-gain theorem). ``μ = max |M|`` is evaluated exactly (delays as ``e^(−jωT)``) on
a dense logarithmic grid refined around its peak; the tests check the verdict and ``det(I +
L)`` against a python-control model of the whole 2×2 loop with high-order Padé delays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.loopmodel.frequency_response import log_grid
from adnmesh.loopmodel.plant import Actuator, plant_from_ders

__all__ = ["CouplingResult", "LoopSide", "coupled_loop", "loop_side"]


@dataclass(frozen=True)
class LoopSide:
    """One loop as deployed: its DERs' dynamics and weighted capacities, its PI gains.

    Attributes
    ----------
    ids : tuple of str
        The DERs of its table entry.
    actuators : tuple of Actuator
        Each DER's dynamics (its reaction time and reference time constant for this quantity).
    capacity : ndarray
        ``w_d C_d`` per DER, W or var per unit output.
    kp, ki : float
        PI gains, 1/W (1/var) and 1/(W s) (1/(var s)).
    """

    ids: tuple[str, ...]
    actuators: tuple[Actuator, ...]
    capacity: np.ndarray
    kp: float
    ki: float

    def pi(self, omega: np.ndarray) -> np.ndarray:
        return self.kp + self.ki / (1j * omega)

    def forward(self, omega: np.ndarray, gains: np.ndarray) -> np.ndarray:
        """``Σ_d gains_d w_d C_d H_d(jω)`` (the DERs' delays included), shape (N,)."""
        responses = np.stack([a.response(omega) for a in self.actuators])
        return (gains * self.capacity) @ responses


def loop_side(config, entry) -> LoopSide:
    """The :class:`LoopSide` of ``entry`` (a table entry) of ``config`` (a loop's config: as
    written for P, :func:`adnmesh.reactive.reactive_view` for Q)."""
    ders = config.ders_by_id(entry.ders)
    acts = tuple(Actuator(d.t_delay_s, config.t_lag_s(d)) for d in ders)
    capacity = np.array([float(entry.w.get(d.id, 1.0)) * d.p_inst_w for d in ders])
    return LoopSide(tuple(entry.ders), acts, capacity, float(entry.kp), float(entry.ki))


@dataclass(frozen=True)
class CouplingResult:
    """The coupled loop (see the module docstring).

    Attributes
    ----------
    omega : ndarray
        Frequencies, rad/s.
    m : ndarray, complex
        ``M(jω)``.
    q_into_p, p_into_q : ndarray
        ``|e^(−jωτ) G_PQ C_Q / (1 + L_Q)|`` (W of P_IP per var of Q_ref) and
        ``|e^(−jωτ) G_QP C_P / (1 + L_P)|`` (var of Q_IP per W of P_ref): how a reference of
        one loop reaches the other quantity.
    mu, mu_omega : float
        ``max |M|`` and where, rad/s.
    p_stable, q_stable : bool
        The diagonal loops, with the grid's gains, certified stable.
    p_disk_margin, q_disk_margin : float
        Their disk margins with the grid's gains.
    stable : bool
        Both diagonal loops stable and ``mu < 1``: the coupled loop is stable.
    """

    omega: np.ndarray
    m: np.ndarray
    q_into_p: np.ndarray
    p_into_q: np.ndarray
    mu: float
    mu_omega: float
    p_stable: bool
    q_stable: bool
    p_disk_margin: float
    q_disk_margin: float

    @property
    def stable(self) -> bool:
        return bool(self.p_stable and self.q_stable and self.mu < 1.0)


def _diagonal(side: LoopSide, gains: np.ndarray, t_com_s: float, t_meas_s: float):
    """Stability and disk margin of one loop with the grid's gains on its own quantity."""
    if np.any(gains <= 0):
        return False, 0.0
    ders = [_Der(f"d{i}", c * g, a.t_delay_s, a.t_lag_s)
            for i, (c, g, a) in enumerate(zip(side.capacity, gains, side.actuators))]
    plant = plant_from_ders(ders, t_com_s, t_meas_s, rise_per_lag=1.0)
    figures = evaluate(plant, side.kp, side.ki, classical=False, time_domain=False)
    return bool(figures.stable[0] and figures.certified[0]), float(figures.disk_margin[0])


@dataclass(frozen=True)
class _Der:
    id: str
    p_inst_w: float
    t_delay_s: float
    t_rise_s: float


def coupled_loop(p: LoopSide, q: LoopSide, sensitivity: dict[str, np.ndarray],
                 t_com_s: float, t_meas_s: float, per_decade: int = 400) -> CouplingResult:
    """Evaluate the coupled loop.

    Parameters
    ----------
    p, q : LoopSide
        The P loop and the Q loop.
    sensitivity : dict
        DER id -> ``[∂P_IP/∂P_d, ∂P_IP/∂Q_d, ∂Q_IP/∂P_d, ∂Q_IP/∂Q_d]``
        (:func:`adnmesh.grid.sensitivity.interface_sensitivities`).
    t_com_s, t_meas_s : float
        The design's ICT delays, s (T_com with the sampled PI's hold).
    per_decade : int
        Grid density, points per decade, from 1e-5 to 1e4 rad/s.
    """
    def gains(side: LoopSide, row: int) -> np.ndarray:
        return np.array([sensitivity[d][row] for d in side.ids])

    omega = log_grid(1e-5, 1e4, per_decade)
    m, q_into_p, p_into_q = _coupling(p, q, gains, omega, t_com_s + t_meas_s)
    k = int(np.argmax(np.abs(m)))
    lo, hi = omega[max(k - 1, 0)], omega[min(k + 1, omega.size - 1)]
    fine = np.geomspace(lo, hi, 2001)            # the peak, refined between its neighbours
    m_fine = _coupling(p, q, gains, fine, t_com_s + t_meas_s)[0]
    j = int(np.argmax(np.abs(m_fine)))
    p_stable, p_disk = _diagonal(p, gains(p, 0), t_com_s, t_meas_s)
    q_stable, q_disk = _diagonal(q, gains(q, 3), t_com_s, t_meas_s)
    return CouplingResult(omega, m, q_into_p, p_into_q, float(abs(m_fine[j])),
                          float(fine[j]), p_stable, q_stable, p_disk, q_disk)


def _coupling(p: LoopSide, q: LoopSide, gains, omega: np.ndarray, tau: float):
    delay = np.exp(-1j * omega * tau)
    l_p = delay * p.pi(omega) * p.forward(omega, gains(p, 0))
    l_q = delay * q.pi(omega) * q.forward(omega, gains(q, 3))
    q_to_p = delay * q.pi(omega) * q.forward(omega, gains(q, 1)) / (1 + l_q)
    p_to_q = delay * p.pi(omega) * p.forward(omega, gains(p, 2)) / (1 + l_p)
    return q_to_p * p_to_q, np.abs(q_to_p), np.abs(p_to_q)
