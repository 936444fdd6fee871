"""Range, linear range and service of intervals that share their subsets (pure numpy).

For the DERs a direction may use (the available ones the grid guard does not block that
way), in one interval:

- **range** (``range_up_w``, ``range_down_w``): the sum of their headrooms, what the CPFC
  reaches at last (DERs that saturate are held, the integrator drives the others on);
- **linear range**: the largest step the entry delivers with none of them saturating, at its
  certified dynamics: in steady state DER d delivers ``share_d`` of a step
  (:class:`~adnmesh.study.entries.Figures`), and on the way up to ``1 + overshoot`` times
  that, so ``min_d headroom_d / share_d / (1 + overshoot/100)``;
- **service** of size S within T s: the entry is feasible, its settling time is at most T,
  and its linear range is at least S.
"""

from __future__ import annotations

import numpy as np

from adnmesh.study.entries import Figures

__all__ = ["linear_range", "direction"]


def linear_range(headroom_w: np.ndarray, figures: Figures) -> np.ndarray:
    """The linear range of each row of ``headroom_w`` (shape (G, n), W) under ``figures``'s
    entry, W (0 for the empty subset)."""
    used = figures.share > 0
    if not used.any():
        return np.zeros(headroom_w.shape[0])
    overshoot = figures.overshoot_pct if figures.overshoot_pct == figures.overshoot_pct else 0.0
    ratio = headroom_w[:, used] / figures.share[used][None, :]
    return np.maximum(ratio.min(axis=1), 0.0) / (1.0 + max(overshoot, 0.0) / 100.0)


def direction(headroom_w: np.ndarray, mask: np.ndarray, figures: Figures, service_w: float,
              service_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(range_w, linear_w, service)`` of one direction for rows of ``headroom_w`` (shape
    (G, n), W) whose usable DERs are ``mask`` (shape (n,)) with entry ``figures``."""
    range_w = headroom_w[:, mask].sum(axis=1) if mask.any() else np.zeros(headroom_w.shape[0])
    linear = linear_range(headroom_w, figures)
    fast = figures.feasible and figures.settling_s <= service_s
    return range_w, linear, fast & (linear >= service_w)
