"""DER subsets of a config as one batch of loops, with the gains a table deploys for them.

Every analysis evaluates many subsets at once: all of them share the config's actuator groups
(DERs with identical dynamics), and subset ``n`` is row ``n`` of a group-gain matrix
``K[n, g] = sum_{d in A_n, d in g} w_d P_inst,d`` (W), so one :func:`adnmesh.loopmodel.evaluation.evaluate`
call covers every subset (absent groups have gain 0).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from adnmesh.loopmodel.plant import Actuator, Plant

__all__ = ["SubsetBatch", "subset_name", "deployed_batch", "config_actuators"]


def subset_name(ders: Sequence[str]) -> str:
    """``"SGen1,SGen5"``: the DER ids joined as ``--solution-space`` and ``--ders`` take them."""
    return ",".join(ders)


def config_actuators(config) -> tuple[tuple[Actuator, ...], dict[str, int]]:
    """The config's PT1 actuator groups and the group index of every DER id."""
    groups: dict[Actuator, int] = {}
    group_of = {}
    for der in config.ders:
        act = Actuator(float(der.t_delay_s), config.t_lag_s(der), "pt1")
        group_of[der.id] = groups.setdefault(act, len(groups))
    return tuple(groups), group_of


@dataclass(frozen=True)
class SubsetBatch:
    """M subsets with one PI pair and weight vector each, as a batch of loops.

    Attributes
    ----------
    subsets : tuple of tuple of str
        The subsets (DER ids in config order).
    actuators : tuple of Actuator
        The config's actuator groups (reference PT1 model, nominal time constants).
    gains_w : ndarray, shape (M, G)
        Group gains ``sum w_d P_inst,d`` per subset, W.
    kp : ndarray, shape (M,)
        Proportional gains, 1/W.
    ki : ndarray, shape (M,)
        Integral gains, 1/(W s).
    t_com_s, t_meas_s : float
        ICT delays, s.
    """

    subsets: tuple[tuple[str, ...], ...]
    actuators: tuple[Actuator, ...]
    gains_w: np.ndarray
    kp: np.ndarray
    ki: np.ndarray
    t_com_s: float
    t_meas_s: float

    def __len__(self) -> int:
        return len(self.subsets)

    @property
    def names(self) -> list[str]:
        """Subset names (:func:`subset_name`)."""
        return [subset_name(s) for s in self.subsets]

    def plant(self, model: str = "pt1", lag_scale: float = 1.0, rows=None) -> Plant:
        """The loops' plants with actuator model ``model`` and time constants times ``lag_scale``.

        ``rows`` (indices or mask) selects some subsets; gains shape (len(rows), G).
        """
        gains = self.gains_w if rows is None else self.gains_w[rows]
        return Plant(self.actuators, gains, self.t_com_s, self.t_meas_s).with_model(
            model, lag_scale)

    def gains(self, rows=None) -> tuple[np.ndarray, np.ndarray]:
        """``(kp, ki)`` of all subsets or of ``rows``; 1/W and 1/(W s)."""
        if rows is None:
            return self.kp, self.ki
        return self.kp[rows], self.ki[rows]

    @property
    def has_gains(self) -> np.ndarray:
        """Subsets with a usable PI pair (a table marks an entry without one by NaN gains)."""
        return np.isfinite(self.kp) & np.isfinite(self.ki) & (self.kp > 0) & (self.ki > 0)

    def loop_classes(self) -> tuple[np.ndarray, np.ndarray]:
        """Subsets whose loops are identical (same ``K_P K_g`` and ``K_I K_g`` per group).

        E.g. two DERs with equal parameters, or (for a table tuned on normalised plants) every
        subset with the same shares of each actuator group. Returns ``(first, cls)``: the
        index of one representative per class (in batch order) and the class of every subset
        (``first[cls[i]]`` is the representative of subset i).
        """
        key = np.concatenate([self.kp[:, None] * self.gains_w, self.ki[:, None] * self.gains_w],
                             axis=1)
        key = np.array([[float(f"{x:.11e}") for x in row] for row in key])
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        order = np.argsort(first)               # classes numbered in batch order
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        return first[order], rank[np.ravel(inverse)]

    def select(self, rows) -> "SubsetBatch":
        """The batch of the subsets ``rows`` only."""
        rows = np.asarray(rows)
        if rows.dtype == bool:
            rows = np.nonzero(rows)[0]
        return SubsetBatch(tuple(self.subsets[i] for i in rows), self.actuators,
                           self.gains_w[rows], self.kp[rows], self.ki[rows], self.t_com_s,
                           self.t_meas_s)


def deployed_batch(config, subsets: Sequence[Sequence[str]], kp, ki,
                   weights: Sequence[dict] | dict | None = None) -> SubsetBatch:
    """Batch of ``subsets`` with PI gains ``kp, ki`` (scalars or one per subset).

    Parameters
    ----------
    config : adnmesh.config.Config
    subsets : sequence of sequences of DER ids
    kp, ki : float or array_like, shape (M,)
        PI gains, 1/W and 1/(W s).
    weights : dict or sequence of dicts, optional
        Weight ``w_d`` per DER id (one dict for all subsets, or one per subset); missing ids
        and ``None`` mean 1. This is the as-deployed loop: DER d gets gain ``w_d P_inst,d``.
    """
    actuators, group_of = config_actuators(config)
    p_inst = {d.id: float(d.p_inst_w) for d in config.ders}
    order = {d: i for i, d in enumerate(config.der_ids())}
    subs = tuple(tuple(sorted(s, key=order.__getitem__)) for s in subsets)
    m = len(subs)
    if weights is None or isinstance(weights, dict):
        weights = [weights or {}] * m
    gains = np.zeros((m, len(actuators)))
    for i, (s, w) in enumerate(zip(subs, weights)):
        for d in s:
            gains[i, group_of[d]] += float((w or {}).get(d, 1.0)) * p_inst[d]
    kp = np.broadcast_to(np.asarray(kp, float), (m,)).copy()
    ki = np.broadcast_to(np.asarray(ki, float), (m,)).copy()
    return SubsetBatch(subs, actuators, gains, kp, ki, float(config.design_t_com_s),
                       float(config.t_meas_s))
