"""A DER's dynamics on the wall clock: what a device simulator serves behind its protocol.

:class:`RealtimePlant` holds the DER's model as the DER agent would run it (its detailed model
or the reference PT1 for P, :func:`adnmesh.control.der_model.der_params`; the reference PT1 with
its reactive dynamics for Q) and evaluates it at the wall-clock time of each write and read: a
set-point written at ``t`` takes effect at ``t``, the infeed read at ``t`` is the model's
exact value there. Thread-safe (the protocol servers call it from their own threads).
"""

from __future__ import annotations

import threading
import time

from adnmesh.config import DER, Config
from adnmesh.control.der_model import der_params, usable_available_w
from adnmesh.dermodels import infeed_at, reference_pt1, set_point, steady_state
from adnmesh.reactive import capability_of, limit_pq, q_dynamics

__all__ = ["RealtimePlant"]


class RealtimePlant:
    """The model of ``der`` run on the wall clock from now (see the module docstring).

    Parameters
    ----------
    der, config
        The DER and its config.
    p_avail_w : float, optional
        Its available power, W (default ``p_inst_w``).
    params : optional
        Its model's parameters (default: from the config, as the DER agent gets them).
    clock_ns : callable, optional
        The wall clock, ns (default :func:`time.monotonic_ns`; tests give their own).
    """

    def __init__(self, der: DER, config: Config, p_avail_w: float | None = None,
                 params=None, clock_ns=time.monotonic_ns) -> None:
        self.der = der
        self.p_avail_w = usable_available_w(der, p_avail_w)
        self.params = der_params(der, config, self.p_avail_w) if params is None else params
        self.capability = capability_of(der, config.reactive)
        self.priority = config.reactive.priority if config.reactive is not None else "p"
        delay, rise = q_dynamics(der)
        self.q_params = reference_pt1(self.capability.capacity_var or 1.0, delay,
                                      rise / config.rise_per_lag)
        self._clock_ns = clock_ns
        self._t0_ns = clock_ns()
        self._lock = threading.Lock()
        self.p_setpoint_w = der.p_sched_w
        self.q_setpoint_var = der.q_sched_var
        self._p = steady_state(self.params, der.p_sched_w, 0)
        self._q = steady_state(self.q_params, der.q_sched_var, 0)
        self._last_ns = 0

    def _now_ns(self) -> int:
        """Model time, ns since the plant began (never backwards)."""
        self._last_ns = max(self._last_ns, self._clock_ns() - self._t0_ns)
        return self._last_ns

    def write(self, p_w: float | None = None, q_var: float | None = None) -> tuple[float, float]:
        """New set-points from now (None: unchanged), limited to the DER's range and P-Q
        capability; return the set-points taken, ``(W, var)``."""
        with self._lock:
            t = self._now_ns()
            p = self.p_setpoint_w if p_w is None else float(p_w)
            q = self.q_setpoint_var if q_var is None else float(q_var)
            p, q, _, _ = limit_pq(self.capability, p, q, self.p_avail_w, self.priority)
            if p != self.p_setpoint_w:
                self.p_setpoint_w = p
                set_point(self.params, self._p, t, p)
            if q != self.q_setpoint_var:
                self.q_setpoint_var = q
                set_point(self.q_params, self._q, t, q)
            return p, q

    def read(self) -> tuple[float, float, float]:
        """``(P W, Q var, model time s)`` now."""
        with self._lock:
            t = self._now_ns()
            return infeed_at(self.params, self._p, t), infeed_at(self.q_params, self._q, t), \
                t / 1e9
