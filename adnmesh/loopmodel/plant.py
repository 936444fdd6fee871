"""Reference-model plant of a DER subset (docs/method.md#reference-model), grouped by identical
dynamics.

A DER d contributes ``G_d(s) = exp(-T_delay,d s) K_d H(s; T_d)`` with ``K_d = w_d P_inst,d`` (W).
DERs whose dynamics (model, delay, time constant) coincide add up to one *actuator group*
``K_g H_g(s) exp(-T_delay,g s)`` with ``K_g`` the sum of their gains; the loop only ever sees
the groups. This is what makes subsets with identical normalised plants identical problems.

The actuator models (unit DC gain, ``T`` in s):

- ``pt1``:  ``1 / (1 + T s)`` — the reference model, ``T = T_rise / ln 9``,
- ``pt2``:  ``1 / ((T/1.5291)^2 s^2 + (T/0.7645) s + 1)``,
- ``rhpz``: ``(1 - 0.25 s) / ((T/3.7348)^2 s^2 + (T/0.9337) s + 1)`` (0.25 in s),

the last two from the model-uncertainty study (docs/method.md#model-uncertainty). Every
denominator has real roots,
which the certified bounds of :mod:`adnmesh.loopmodel.stability` rely on.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from functools import cached_property
from typing import Iterable, Sequence

import numpy as np

__all__ = ["MODELS", "Actuator", "Plant", "plant_from_ders", "RISE_PER_LAG"]

#: 10-90 % rise time of a first-order lag divided by its time constant (ln 9 = 2.1972).
RISE_PER_LAG = math.log(9.0)

MODELS = ("pt1", "pt2", "rhpz")


@dataclass(frozen=True)
class Actuator:
    """Dynamics of one actuator group (unit DC gain).

    Parameters
    ----------
    t_delay_s : float
        Reaction (dead) time of the DER, s.
    t_lag_s : float
        Time constant ``T`` of the model, s (``T_rise / ln 9`` for the reference PT1).
    model : str
        ``"pt1"``, ``"pt2"`` or ``"rhpz"``.
    """

    t_delay_s: float
    t_lag_s: float
    model: str = "pt1"

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"unknown actuator model {self.model!r} (known: {', '.join(MODELS)})")
        if not (self.t_lag_s > 0 and self.t_delay_s >= 0):
            raise ValueError("actuator needs t_lag_s > 0 and t_delay_s >= 0")

    @cached_property
    def numerator(self) -> np.ndarray:
        """Numerator coefficients in ascending powers of s (``n0 + n1 s``)."""
        return np.array([1.0, -0.25]) if self.model == "rhpz" else np.array([1.0])

    @cached_property
    def denominator(self) -> np.ndarray:
        """Denominator coefficients in ascending powers of s."""
        t = self.t_lag_s
        if self.model == "pt1":
            return np.array([1.0, t])
        if self.model == "pt2":
            return np.array([1.0, t / 0.7645, (t / 1.5291) ** 2])
        return np.array([1.0, t / 0.9337, (t / 3.7348) ** 2])

    @cached_property
    def time_constants_s(self) -> np.ndarray:
        """``tau_i`` of the factorisation ``den(s) = prod(1 + tau_i s)`` (all real, s)."""
        roots = np.roots(self.denominator[::-1])
        if np.any(np.abs(roots.imag) > 1e-9 * np.abs(roots)):
            raise ValueError(f"{self.model} denominator has complex roots")
        return np.sort(-1.0 / roots.real)

    def response(self, omega: np.ndarray) -> np.ndarray:
        """``H(j omega) exp(-j omega T_delay)`` at ``omega`` (rad/s), complex, unit DC gain."""
        s = 1j * np.asarray(omega, dtype=float)
        den = self.denominator
        if den.size == 2:                         # pt1: the hot path of tuning
            return np.exp(-s * self.t_delay_s) / (den[0] + den[1] * s)
        num = self.numerator
        return (num[0] + (num[1] * s if num.size > 1 else 0.0)) \
            / (den[0] + s * (den[1] + s * den[2])) * np.exp(-s * self.t_delay_s)

    def state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Controllable canonical form ``(A, B, C)`` of ``H`` (strictly proper, D = 0)."""
        den = self.denominator / self.denominator[-1]
        num = self.numerator / self.denominator[-1]
        n = den.size - 1
        a = np.zeros((n, n))
        a[:-1, 1:] = np.eye(n - 1)
        a[-1, :] = -den[:-1]
        b = np.zeros(n)
        b[-1] = 1.0
        c = np.zeros(n)
        c[: num.size] = num
        return a, b, c

    def foh_discretisation(self, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Exact discretisation for an input linear between samples (first-order hold).

        Returns ``(Phi, gamma_left, gamma_right, C)`` such that
        ``x[k+1] = Phi x[k] + gamma_left u[k] + gamma_right u[k+1]`` is exact whenever ``u``
        is linear on ``[t_k, t_k + h]`` (h in s). Cached per (actuator, h).
        """
        return _foh(self, float(h))


@functools.lru_cache(maxsize=4096)
def _foh(act: Actuator, h: float):
    """Augmented-matrix exponential: input u(t) = u0 + v t on [0, h] with v = (u1 - u0)/h."""
    import scipy.linalg     # here: a plant's structure (the CPFC's announcement) needs no scipy
    a, b, c = act.state_space()
    n = a.shape[0]
    aug = np.zeros((n + 2, n + 2))
    aug[:n, :n] = a
    aug[:n, n] = b
    aug[n, n + 1] = 1.0
    e = scipy.linalg.expm(aug * h)
    phi, g_u, g_v = e[:n, :n], e[:n, n], e[:n, n + 1] / h
    return phi, g_u - g_v, g_v, c


@dataclass(frozen=True)
class Plant:
    """Loop structure of a DER subset: actuator groups, their gains and the ICT delays.

    Parameters
    ----------
    actuators : tuple of Actuator
        One entry per group of identical dynamics.
    gains_w : ndarray, shape (G,) or (M, G)
        ``K_g = sum_d w_d P_inst,d`` per group, W. A 2-D array gives every one of M candidates
        its own gains (e.g. many subsets evaluated in lock-step); zero gains are allowed.
    t_com_s, t_meas_s : float
        ICT delay CPFC -> DERs and measurement delay, s.
    """

    actuators: tuple[Actuator, ...]
    gains_w: np.ndarray
    t_com_s: float
    t_meas_s: float

    def __post_init__(self) -> None:
        gains = np.asarray(self.gains_w, dtype=float)
        object.__setattr__(self, "gains_w", gains)
        if gains.shape[-1] != len(self.actuators):
            raise ValueError("gains_w must have one column per actuator group")
        if np.any(gains < 0) or np.any(gains.sum(axis=-1) <= 0):
            raise ValueError("actuator gains must be >= 0 with a positive sum")
        if not (self.t_com_s >= 0 and self.t_meas_s >= 0):
            raise ValueError("ICT delays must be >= 0")

    def with_gains(self, gains_w: np.ndarray) -> "Plant":
        """The same groups and delays with the gains ``gains_w`` (W), taken as they are:
        rows or active columns of this plant's already validated gains (the numerics' hot
        paths build thousands of such plants; a new plant of other gains is ``Plant(...)``,
        which checks them)."""
        plant = object.__new__(Plant)
        object.__setattr__(plant, "actuators", self.actuators)
        object.__setattr__(plant, "gains_w", gains_w)
        object.__setattr__(plant, "t_com_s", self.t_com_s)
        object.__setattr__(plant, "t_meas_s", self.t_meas_s)
        return plant

    @property
    def total_gain_w(self) -> np.ndarray:
        """``sum_g K_g`` (W), the DC gain of the plant; shape () or (M,)."""
        return self.gains_w.sum(axis=-1)

    @property
    def path_delays_s(self) -> np.ndarray:
        """Forward delay ``T_com + T_delay,g`` of each group, s."""
        return np.array([self.t_com_s + a.t_delay_s for a in self.actuators])

    @property
    def loop_delays_s(self) -> np.ndarray:
        """Whole loop delay ``T_com + T_delay,g + T_meas`` of each group, s."""
        return self.path_delays_s + self.t_meas_s

    def group_responses(self, omega: np.ndarray) -> np.ndarray:
        """``H_g(j omega) exp(-j omega (T_com + T_delay,g + T_meas))``, shape (G, N)."""
        omega = np.asarray(omega, dtype=float)
        return np.stack([a.response(omega) for a in self.actuators]) * np.exp(
            -1j * omega * (self.t_com_s + self.t_meas_s)
        )

    def scaled(self, factor: float) -> "Plant":
        """The same plant with every gain multiplied by ``factor``."""
        return Plant(self.actuators, self.gains_w * factor, self.t_com_s, self.t_meas_s)

    def with_model(self, model: str, lag_scale: float = 1.0) -> "Plant":
        """Same groups with another actuator model and time constants scaled by ``lag_scale``."""
        acts = tuple(Actuator(a.t_delay_s, a.t_lag_s * lag_scale, model) for a in self.actuators)
        return Plant(acts, self.gains_w, self.t_com_s, self.t_meas_s)


def plant_from_ders(
    ders: Sequence,
    t_com_s: float,
    t_meas_s: float,
    weights: dict[str, float] | Iterable[float] | None = None,
    model: str = "pt1",
    lag_scale: float = 1.0,
    rise_per_lag: float = RISE_PER_LAG,
) -> Plant:
    """Group DERs (objects with ``id, p_inst_w, t_delay_s, t_rise_s``) into a :class:`Plant`.

    Parameters
    ----------
    ders : sequence
        The DERs of the subset.
    t_com_s, t_meas_s : float
        ICT delays, s.
    weights : mapping id -> w or sequence, optional
        Weights ``w_d`` (dimensionless, default 1).
    model : str
        Actuator model for every DER (``pt1`` is the reference model).
    lag_scale : float
        Factor ``b`` on every time constant (model-uncertainty study).
    rise_per_lag : float
        ``t_rise_s`` over the time constant: ln 9 (``t_rise_s`` is the 10-90 % rise time, the
        default) or 1 (it is the time constant); see the config's ``t_rise_is``.
    """
    if weights is None:
        w = [1.0] * len(ders)
    elif isinstance(weights, dict):
        w = [float(weights.get(d.id, 1.0)) for d in ders]
    else:
        w = [float(x) for x in weights]
    groups: dict[Actuator, float] = {}
    for der, wd in zip(ders, w):
        act = Actuator(float(der.t_delay_s), float(der.t_rise_s) / rise_per_lag * lag_scale, model)
        groups[act] = groups.get(act, 0.0) + wd * float(der.p_inst_w)
    return Plant(tuple(groups), np.array(list(groups.values())), float(t_com_s), float(t_meas_s))
