"""How the grid moves with each actuator's P and Q: at the interconnection point and at its limits.

:func:`interface_sensitivities` linearises the AC power flow (:class:`adnmesh.grid.GridSolver`)
around an operating point by central differences: for every actuator d the four derivatives
``∂P_IP/∂P_d``, ``∂P_IP/∂Q_d``, ``∂Q_IP/∂P_d`` and ``∂Q_IP/∂Q_d`` (dimensionless: W/W, W/var,
var/W, var/var; P_IP and Q_IP MV → HV positive, P_d and Q_d injections). They are the grid in
the coupled P-Q loop (:mod:`adnmesh.analysis.coupling`). A difference of ``step`` (1 kW / 1
kvar) against a power flow solved to its tolerance leaves an error far below 1e-4 (tests
compare with pandapower's ``runpp``).

:func:`limit_sensitivities` gives what the grid guard needs (:mod:`adnmesh.control.grid_guard`):
the derivative of every reported bus voltage (p.u. per W and per var; 1-MV-rural: up to 2e-8
p.u./W), every line loading and every transformer loading (% per W and per var; up to 2e-5
%/W) by each actuator's P and Q, with the values at the point (:class:`LimitSensitivities`).

By default (``method="jacobian"``) they are exact at the solution, to the power flow's
tolerance: ``J · Δx = ΔS``, with ``x`` the angles of the PV and PQ buses and the magnitudes of
the PQ buses and J the Newton-Raphson Jacobian built from the model's ``Ybus`` and the solved
voltages (MATPOWER's ``dSbus_dV``; everything voltage-dependent, constant-impedance loads
included, is in ``Ybus``), so the voltages' derivatives are the columns of J⁻¹ at the
actuators' buses. A loading's derivative follows by the chain rule through the branch current
of the side that sets it (``I₁ = y11·V₁ + y12·V₂``, ``d|I| = Re(conj(I)·dI)/|I|``; where both
sides carry the same loading, side 1's). One sparse LU of J per call; tests: equal to
central differences of ``runpp`` to 1e-5 of each column's largest (small net) and 1e-4
(1-MV-rural, where runpp's differences are the coarser). ``method="differences"`` takes central
differences of the warm-started solver instead (4 power flows per actuator, error ~1e-5);
``benchmarks/sensitivity_speed.py`` times both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from adnmesh.errors import GridError

__all__ = ["LimitSensitivities", "interface_sensitivities", "limit_sensitivities", "METHODS"]

METHODS = ("jacobian", "differences")
_SQRT3 = math.sqrt(3.0)


def interface_sensitivities(solver, p_w, q_var, step: float = 1e3) -> np.ndarray:
    """The derivatives of (P_IP, Q_IP) by each actuator's (P, Q) at ``(p_w, q_var)``.

    Parameters
    ----------
    solver : GridSolver
    p_w, q_var : sequence of float
        The operating point: each actuator's active (W) and reactive (var) power, in the
        solver's order.
    step : float
        Half the central difference, W and var.

    Returns
    -------
    ndarray, shape (4, n)
        Rows ``∂P_IP/∂P_d``, ``∂P_IP/∂Q_d``, ``∂Q_IP/∂P_d``, ``∂Q_IP/∂Q_d``.

    Raises
    ------
    GridError
        A power flow of the differences does not converge.
    """
    p = np.asarray(p_w, dtype=float)
    q = np.asarray(q_var, dtype=float)
    out = np.empty((4, p.size))

    def at(pp, qq) -> tuple[float, float]:
        sample = solver.solve(pp, qq)
        if not sample.converged:
            raise GridError("the power flow does not converge near the operating point")
        return sample.p_ip_w, sample.q_ip_var

    for d in range(p.size):
        for column, moved in ((0, "p"), (1, "q")):
            up_p, up_q, down_p, down_q = p.copy(), q.copy(), p.copy(), q.copy()
            (up_p if moved == "p" else up_q)[d] += step
            (down_p if moved == "p" else down_q)[d] -= step
            (p_hi, q_hi), (p_lo, q_lo) = at(up_p, up_q), at(down_p, down_q)
            out[column, d] = (p_hi - p_lo) / (2 * step)
            out[2 + column, d] = (q_hi - q_lo) / (2 * step)
    at(p, q)                                   # leave the solver at the operating point
    return out


@dataclass(frozen=True, eq=False)
class LimitSensitivities:
    """The grid's limit quantities at one operating point and their derivatives by each
    actuator's P and Q (columns in the solver's actuator order).

    Attributes
    ----------
    vm_pu : ndarray, shape (n_bus,)
        Voltage of every reported bus (:meth:`GridSolver.bus_vm_pu`'s order), p.u.
    line_pct, trafo_pct : ndarray, shape (n_line,) and (n_trafo,)
        Every line's and transformer's loading, %.
    dv_dp, dv_dq : ndarray, shape (n_bus, n_actuators)
        ``∂V/∂P_d`` and ``∂V/∂Q_d``, p.u. per W and p.u. per var.
    dline_dp, dline_dq : ndarray, shape (n_line, n_actuators)
        Loading derivatives, % per W and % per var.
    dtrafo_dp, dtrafo_dq : ndarray, shape (n_trafo, n_actuators)
        Loading derivatives, % per W and % per var.
    method : str
        How they were taken (:data:`METHODS`).
    """

    vm_pu: np.ndarray
    line_pct: np.ndarray
    trafo_pct: np.ndarray
    dv_dp: np.ndarray
    dv_dq: np.ndarray
    dline_dp: np.ndarray
    dline_dq: np.ndarray
    dtrafo_dp: np.ndarray
    dtrafo_dq: np.ndarray
    method: str


def limit_sensitivities(solver, p_w, q_var, method: str = "jacobian",
                        step: float = 1e3) -> LimitSensitivities:
    """Bus voltages and branch loadings at ``(p_w, q_var)`` and their derivatives by each
    actuator's P and Q (see the module docstring); the solver is left at that point.

    Parameters
    ----------
    solver : GridSolver
    p_w, q_var : sequence of float
        Each actuator's active (W) and reactive (var) power, in the solver's order.
    method : str
        ``"jacobian"`` (exact at the solution) or ``"differences"`` (central differences of
        the solver, half-width ``step``).
    step : float
        Half the central difference of ``"differences"``, W and var.

    Raises
    ------
    GridError
        An unknown method, or a power flow that does not converge.
    """
    if method not in METHODS:
        raise GridError(f"limit sensitivities: method must be one of {', '.join(METHODS)}, "
                        f"got {method!r}")
    p = np.asarray(p_w, dtype=float)
    q = np.asarray(q_var, dtype=float)
    _solve(solver, p, q)
    values = (solver.bus_vm_pu(), solver.line_loading_pct(), solver.trafo_loading_pct())
    if method == "jacobian":
        derivatives = _by_jacobian(solver)
    else:
        derivatives = _by_differences(solver, p, q, step)
        _solve(solver, p, q)                    # leave the solver at the operating point
    n = p.size
    split = [(d[:, :n], d[:, n:]) for d in derivatives]
    return LimitSensitivities(*values, *split[0], *split[1], *split[2], method=method)


def _solve(solver, p: np.ndarray, q: np.ndarray) -> None:
    if not solver.solve(p, q).converged:
        raise GridError("limit sensitivities: the power flow does not converge at or near the "
                        "operating point")


def _by_differences(solver, p, q, step) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Central differences of the solver: (voltages, line, trafo) × (P columns, Q columns)."""
    n = p.size
    out = [np.empty((len(solver.bus_names), 2 * n)), np.empty((len(solver.line_names), 2 * n)),
           np.empty((len(solver.trafo_names), 2 * n))]
    for column in range(2 * n):
        ends = []
        for sign in (1.0, -1.0):
            pp, qq = p.copy(), q.copy()
            (pp if column < n else qq)[column % n] += sign * step
            _solve(solver, pp, qq)
            ends.append((solver.bus_vm_pu(), solver.line_loading_pct(),
                         solver.trafo_loading_pct()))
        for k in range(3):
            out[k][:, column] = (ends[0][k] - ends[1][k]) / (2.0 * step)
    return out[0], out[1], out[2]


def _by_jacobian(solver) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The derivatives from the Jacobian at the solver's last solution: (voltages, line, trafo)
    × (P columns, Q columns), per W and per var."""
    from scipy.sparse.linalg import splu

    grid = solver.model
    to_solver = np.asarray(grid.id_me_to_ac_solver(), dtype=np.int64)
    v = np.asarray(grid.get_V_solver(), dtype=complex)
    pv = np.asarray(grid.get_pv_solver(), dtype=np.int64)
    pq = np.asarray(grid.get_pq_solver(), dtype=np.int64)
    jacobian, angle_col, magnitude_col = _jacobian(grid.get_Ybus_solver(), v, pv, pq)
    # one p.u. of P (then of Q) injected at each actuator's bus: the rows of its P and Q
    # equations (the slack's are not in J: there the slack takes it, nothing moves)
    n = solver.n_actuators
    sgens = grid.get_static_generators()
    actuators = solver.data.sgen_index(solver.actuator_sgens)
    buses = np.array([to_solver[sgens[int(i)].bus_id] for i in actuators], dtype=np.int64)
    rhs = np.zeros((jacobian.shape[0], 2 * n))
    for d, bus in enumerate(buses.tolist()):
        if angle_col[bus] >= 0:
            rhs[angle_col[bus], d] = 1.0
        if magnitude_col[bus] >= 0:
            rhs[magnitude_col[bus], n + d] = 1.0
    dx = splu(jacobian).solve(rhs) if jacobian.shape[0] else rhs
    padded = np.vstack([dx, np.zeros((1, 2 * n))])         # row -1: a fixed angle or magnitude
    d_angle, d_magnitude = padded[angle_col], padded[magnitude_col]
    d_v = v[:, None] * (d_magnitude / np.abs(v)[:, None] + 1j * d_angle)   # per p.u. injected
    sn_mva = grid.get_sn_mva()
    per_w = 1.0 / (sn_mva * 1e6)
    dv = d_magnitude[to_solver[solver.reported_buses]] * per_w
    vn_kv = np.asarray(grid.get_bus_vn_kv(), dtype=float)
    (lines, trafos), (line_pct, trafo_pct) = solver.branches(), solver.loading_pct_per_ka()
    line = _loading_derivative(lines, line_pct, to_solver, v, d_v, vn_kv, sn_mva)
    trafo = _loading_derivative(trafos, trafo_pct, to_solver, v, d_v, vn_kv, sn_mva)
    return dv, line * per_w, trafo * per_w


def _jacobian(ybus, v: np.ndarray, pv: np.ndarray, pq: np.ndarray):
    """The Newton-Raphson Jacobian at ``v`` (polar; MATPOWER's ``dSbus_dV``), CSC.

    Rows and columns are numbered alike: the P equations and the angles of ``pv`` then
    ``pq``, then the Q equations and the magnitudes of ``pq``. Returns it with each solver
    bus's angle and magnitude column (-1: fixed, the slack's and the PV buses' magnitudes).
    """
    from scipy import sparse

    n_bus = v.size
    angle_col = np.full(n_bus, -1, dtype=np.int64)
    angle_col[np.concatenate([pv, pq])] = np.arange(pv.size + pq.size)
    magnitude_col = np.full(n_bus, -1, dtype=np.int64)
    magnitude_col[pq] = pv.size + pq.size + np.arange(pq.size)
    y = sparse.coo_matrix(ybus)
    i, j, y_ij = y.row.astype(np.int64), y.col.astype(np.int64), y.data
    v_norm = v / np.abs(v)
    current = np.asarray(sparse.csr_matrix(ybus) @ v)
    # dS_i/dVm_j = V_i conj(Y_ij Vn_j) (+ conj(I_i) Vn_i on the diagonal)
    # dS_i/dVa_j = -j V_i conj(Y_ij V_j) (+ j V_i conj(I_i) on the diagonal)
    ds_dvm = v[i] * np.conj(y_ij * v_norm[j])
    ds_dva = -1j * v[i] * np.conj(y_ij * v[j])
    diag = np.arange(n_bus)
    i, j = np.concatenate([i, diag]), np.concatenate([j, diag])
    ds_dvm = np.concatenate([ds_dvm, np.conj(current) * v_norm])
    ds_dva = np.concatenate([ds_dva, 1j * v * np.conj(current)])
    rows, cols, values = [], [], []
    for row_of, col_of, part in ((angle_col, angle_col, ds_dva.real),
                                 (angle_col, magnitude_col, ds_dvm.real),
                                 (magnitude_col, angle_col, ds_dva.imag),
                                 (magnitude_col, magnitude_col, ds_dvm.imag)):
        keep = (row_of[i] >= 0) & (col_of[j] >= 0)
        rows.append(row_of[i[keep]])
        cols.append(col_of[j[keep]])
        values.append(part[keep])
    size = pv.size + 2 * pq.size
    jacobian = sparse.csc_matrix((np.concatenate(values), (np.concatenate(rows),
                                                           np.concatenate(cols))),
                                 shape=(size, size))
    return jacobian, angle_col, magnitude_col


def _loading_derivative(branches, pct_per_ka, to_solver, v, d_v, vn_kv,
                        sn_mva) -> np.ndarray:
    """d(loading %)/d(injection p.u.) of every branch (:class:`~adnmesh.grid.solver.Branches`)
    on the side that sets its loading (``pct_per_ka``: % per kA of side 1 and side 2); 0 for
    a branch out of service or without current."""
    s1, s2 = to_solver[branches.bus1], to_solver[branches.bus2]
    on = branches.connected & (s1 >= 0) & (s2 >= 0)
    s1, s2 = np.where(on, s1, 0), np.where(on, s2, 0)
    out = np.zeros((s1.size, d_v.shape[1]))
    sides = []
    for y_a, y_b, bus, factor in ((branches.y11, branches.y12, branches.bus1, pct_per_ka[0]),
                                  (branches.y21, branches.y22, branches.bus2, pct_per_ka[1])):
        current = y_a * v[s1] + y_b * v[s2]
        pct_per_pu = factor * sn_mva / (_SQRT3 * vn_kv[bus])      # % per p.u. of current
        sides.append((np.abs(current) * pct_per_pu, current, y_a, y_b, pct_per_pu))
    second = sides[1][0] > sides[0][0]
    for side, use in ((sides[0], ~second), (sides[1], second)):
        _, current, y_a, y_b, pct_per_pu = side
        rows = np.flatnonzero(use & on & (np.abs(current) > 0.0))
        d_current = y_a[rows, None] * d_v[s1[rows]] + y_b[rows, None] * d_v[s2[rows]]
        out[rows] = (pct_per_pu[rows, None] * np.real(np.conj(current[rows, None]) * d_current)
                     / np.abs(current[rows, None]))
    return out
