"""Fast, warm-started AC power flow of one grid with a few actuator generators.

:class:`GridSolver` takes a :class:`~adnmesh.grid.data.GridData` and the names of the actuator
static generators, and solves the power flow for one vector of their active powers at a time
(:meth:`GridSolver.solve`) with lightsim2grid's Newton-Raphson solver (single slack, KLU sparse
LU) on pandapower's own admittance matrices, starting from the previous solution. Everything
else in the grid is a constant injection (or, for constant-impedance loads, a shunt in
``Ybus``); the actuators' reactive power stays at its study-case value.

Results (:class:`GridSample`) follow pandapower's definitions: ``P_IP``/``Q_IP`` are the external
grid's injection with the sign turned, so that power flowing from the MV grid into the 110 kV
grid is positive; voltage extremes over the net's buses (``res_bus.vm_pu``); loadings as
``res_line.loading_percent`` (current over ``max_i_ka · df · parallel``) and
``res_trafo.loading_percent`` (pandapower's default ``trafo_loading="current"``: the larger of the
two ends' currents times rated voltage over ``sn_mva``, over ``parallel · df``).

Accuracy: Newton-Raphson to a power mismatch below ``tol_pu`` (default 1e-8 p.u., i.e. 0.01 W
and 0.01 var at ``base_mva`` = 1), the tolerance pandapower's ``runpp`` uses by default.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from adnmesh.grid.data import GridData
from adnmesh.grid.errors import GridError

__all__ = ["GridSample", "GridSolver", "available_power_w"]


@dataclass(frozen=True)
class GridSample:
    """One power-flow solution, as the measurement at the interconnection point sees it.

    Attributes
    ----------
    p_ip_w, q_ip_var : float
        Active and reactive power at the interconnection point (the slack, 110 kV side),
        positive from the MV grid to the HV grid, W and var.
    vm_min_pu, vm_max_pu : float
        Lowest and highest bus voltage, p.u.
    line_loading_max_pct, trafo_loading_max_pct : float
        Highest line and transformer loading, % (pandapower's definitions; NaN if none).
    converged : bool
        Whether Newton-Raphson converged; if not, every number is NaN.
    iterations : int
        Newton-Raphson iterations of the (last) attempt.
    """

    p_ip_w: float
    q_ip_var: float
    vm_min_pu: float
    vm_max_pu: float
    line_loading_max_pct: float
    trafo_loading_max_pct: float
    converged: bool
    iterations: int


def available_power_w(data: GridData, sgen_names) -> np.ndarray:
    """Available active power of the named static generators at the study case, W.

    It is their SimBench ``p_mw`` times the study case's scaling for their type (``Wind_p`` for
    wind, ``PV_p`` for PV, ``RES_p`` for the rest) times their ``scaling``, as
    :func:`adnmesh.grid.simbench_net.apply_study_case` set it.
    """
    return data.sgen_p_mw[data.sgen_index(sgen_names)] * 1e6


def _nr_solver():
    """lightsim2grid's single-slack Newton-Raphson, KLU if this build has it."""
    from lightsim2grid import algorithm
    cls = getattr(algorithm, "NRSing_KLU", None) or algorithm.NRSing_SparseLU
    return cls()


class GridSolver:
    """Warm-started AC power flow for the actuators' active powers (see the module docstring).

    Parameters
    ----------
    data : GridData
        The grid at its study case.
    actuator_sgens : sequence of str
        Names of the actuator static generators; :meth:`solve` takes their powers in this order.
    max_iter : int
        Newton-Raphson iterations per attempt.
    tol_pu : float
        Convergence tolerance on the power mismatch, p.u. of ``data.base_mva``.
    """

    def __init__(self, data: GridData, actuator_sgens, max_iter: int = 20,
                 tol_pu: float = 1e-8) -> None:
        self.data = data
        self.actuator_sgens = tuple(actuator_sgens)
        act = data.sgen_index(self.actuator_sgens)
        others = np.setdiff1d(np.arange(len(data.sgen_names)), act)
        base = data.base_mva
        s = data.s_fixed_pu.astype(complex).copy()
        np.add.at(s, data.sgen_bus[others],
                  (data.sgen_p_mw[others] + 1j * data.sgen_q_mvar[others]) / base)
        np.add.at(s, data.sgen_bus[act], 1j * data.sgen_q_mvar[act] / base)
        self._s_base = s
        self._act_bus = data.sgen_bus[act]
        self._w_to_pu = 1e-6 / base
        self._ybus = data.ybus.tocsc()
        # both ends' currents in one product: rows [Yf; Yt], times % per p.u. of current
        self._y_ends = sp.vstack([data.yf, data.yt]).tocsr()
        self._loading_ends = np.concatenate([data.loading_f, data.loading_t])
        self._n_branch = data.yf.shape[0]
        ref = int(data.ref[0])
        self._ref = ref
        row = data.ybus[ref]
        self._ref_cols, self._ref_vals = row.indices.copy(), row.data.copy()
        self._ids = (data.ref.astype(np.int32), data.pv.astype(np.int32),
                     data.pq.astype(np.int32))
        self._weights = np.zeros(data.n_bus)
        self._weights[ref] = 1.0
        self._max_iter, self._tol = int(max_iter), float(tol_pu)
        self._solver = _nr_solver()
        self._v = data.v_init.astype(complex).copy()

    @property
    def n_actuators(self) -> int:
        """Number of actuator generators."""
        return len(self.actuator_sgens)

    @property
    def voltages_pu(self) -> np.ndarray:
        """Complex bus voltages of the last converged solution (internal bus order), p.u."""
        return self._v.copy()

    def solve(self, p_actuator_w) -> GridSample:
        """Solve the power flow with the actuators at ``p_actuator_w`` (W, construction order).

        Starts from the last converged solution (the study case's at first); if Newton-Raphson
        fails from there it tries once more from the study case's solution.
        """
        p = np.asarray(p_actuator_w, dtype=float)
        if p.shape != (self.n_actuators,) or not np.all(np.isfinite(p)):
            raise GridError(f"grid solver: expected {self.n_actuators} finite actuator powers "
                            f"in W, got {p_actuator_w!r}")
        sbus = self._s_base + np.bincount(self._act_bus, p * self._w_to_pu,
                                          minlength=self.data.n_bus)
        v, ok = self._run(self._v, sbus)
        if not ok:
            v, ok = self._run(self.data.v_init, sbus)
        iterations = self._solver.get_nb_iter()
        if not ok:
            return _not_converged(iterations)
        self._v = v
        return self._sample(v, sbus, iterations)

    def _run(self, v0: np.ndarray, sbus: np.ndarray) -> tuple[np.ndarray, bool]:
        ref, pv, pq = self._ids
        ok = self._solver.compute_pf(self._ybus, v0.copy(), sbus, ref, self._weights, pv, pq,
                                     self._max_iter, self._tol)
        # get_V is a view of the solver's own memory, which the next solve overwrites
        return np.array(self._solver.get_V(), dtype=complex), bool(ok)

    def _sample(self, v: np.ndarray, sbus: np.ndarray, iterations: int) -> GridSample:
        d, ref = self.data, self._ref
        s_ref = v[ref] * np.conj(self._ref_vals @ v[self._ref_cols])
        s_ext = (s_ref - sbus[ref]) * d.base_mva * 1e6          # external grid's injection, VA
        vm = np.abs(v[d.report_bus])
        ends = np.abs(self._y_ends @ v) * self._loading_ends
        loading = np.maximum(ends[:self._n_branch], ends[self._n_branch:])
        return GridSample(p_ip_w=float(-s_ext.real), q_ip_var=float(-s_ext.imag),
                          vm_min_pu=float(vm.min()), vm_max_pu=float(vm.max()),
                          line_loading_max_pct=_max(loading, d.line_rows),
                          trafo_loading_max_pct=_max(loading, d.trafo_rows),
                          converged=True, iterations=int(iterations))


def _max(values: np.ndarray, rows: tuple[int, int]) -> float:
    part = values[rows[0]:rows[1]]
    return float(part.max()) if part.size else math.nan


def _not_converged(iterations: int) -> GridSample:
    nan = math.nan
    return GridSample(nan, nan, nan, nan, nan, nan, converged=False, iterations=int(iterations))
