"""Exact frequency response of the reference loop (delays as ``exp(-j omega T)``, no Padé).

``L(j omega) = (K_P + K_I / (j omega)) exp(-j omega (T_com + T_meas)) sum_g K_g H_g(j omega)
exp(-j omega T_delay,g)`` for M candidate gain pairs at once. Gains ``K_P`` (1/W) and
``K_I`` (1/(W s)) are ~1e-9 for MW-scale plants; only the products ``K_P K_g`` matter.
"""
from __future__ import annotations

import numpy as np

from adnmesh.loopmodel.plant import Plant

__all__ = ["as_candidates", "loop_response", "loop_at", "loop_points", "log_grid"]


def as_candidates(plant: Plant, kp, ki) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Broadcast gains to shape (M,) and plant gains to shape (M, G).

    Parameters
    ----------
    plant : Plant
    kp, ki : float or array_like
        Proportional gain (1/W) and integral gain (1/(W s)), > 0.

    Returns
    -------
    kp, ki : ndarray, shape (M,)
    gains : ndarray, shape (M, G)
        Group gains ``K_g`` in W.
    """
    kp = np.atleast_1d(np.asarray(kp, dtype=float))
    ki = np.atleast_1d(np.asarray(ki, dtype=float))
    gains = np.atleast_2d(plant.gains_w)
    if not ((kp > 0).all() and (ki > 0).all()):
        raise ValueError("K_P and K_I must be positive")
    if kp.ndim == 1 and kp.shape == ki.shape and gains.shape[0] == kp.shape[0]:
        # already one of each per candidate (the hot paths): read-only views as below
        views = [a.view() for a in (kp, ki, gains)]
        for v in views:
            v.flags.writeable = False
        return views[0], views[1], views[2]
    m = np.broadcast_shapes(kp.shape, ki.shape, gains.shape[:1])[0]
    return (np.broadcast_to(kp, (m,)), np.broadcast_to(ki, (m,)),
            np.broadcast_to(gains, (m, gains.shape[1])))


def log_grid(omega_lo: float, omega_hi: float, per_decade: int) -> np.ndarray:
    """Log-spaced frequencies from ``omega_lo`` to ``omega_hi`` (rad/s) inclusive."""
    n = max(2, int(np.ceil(np.log10(omega_hi / omega_lo) * per_decade)) + 1)
    return np.geomspace(omega_lo, omega_hi, n)


def loop_response(plant: Plant, kp, ki, omega: np.ndarray) -> np.ndarray:
    """``L(j omega)`` on a common frequency grid.

    Parameters
    ----------
    plant : Plant
    kp, ki : float or array_like, shape (M,)
        PI gains, 1/W and 1/(W s).
    omega : ndarray, shape (N,)
        Frequencies, rad/s, > 0.

    Returns
    -------
    ndarray, complex, shape (M, N)
    """
    kp, ki, gains = as_candidates(plant, kp, ki)
    omega = np.asarray(omega, dtype=float)
    plant_resp = gains @ plant.group_responses(omega)          # (M, N), W
    return (kp[:, None] + ki[:, None] / (1j * omega)) * plant_resp


def loop_at(plant: Plant, kp, ki, omega: np.ndarray) -> np.ndarray:
    """``L(j omega)`` where every candidate has its own frequencies.

    Parameters
    ----------
    omega : ndarray, shape (M,) or (M, K)
        Frequencies per candidate, rad/s.

    Returns
    -------
    ndarray, complex, same shape as ``omega``
    """
    kp, ki, gains = as_candidates(plant, kp, ki)
    return loop_points(plant, kp, ki, gains, omega)


def loop_points(plant: Plant, kp: np.ndarray, ki: np.ndarray, gains: np.ndarray,
                omega: np.ndarray) -> np.ndarray:
    """:func:`loop_at` for gains already broadcast by :func:`as_candidates` (hot loops)."""
    omega = np.asarray(omega, dtype=float)
    flat = omega.reshape(omega.shape[0], -1)
    resp = plant.group_responses(flat.ravel()).reshape(len(plant.actuators), *flat.shape)
    plant_resp = np.einsum("mg,gmk->mk", gains, resp)
    out = (kp[:, None] + ki[:, None] / (1j * flat)) * plant_resp
    return out.reshape(omega.shape)
