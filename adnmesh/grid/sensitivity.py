"""How the power at the interconnection point moves with each actuator's P and Q.

:func:`interface_sensitivities` linearises the AC power flow (:class:`adnmesh.grid.GridSolver`)
around an operating point by central differences: for every actuator d the four derivatives
``∂P_IP/∂P_d``, ``∂P_IP/∂Q_d``, ``∂Q_IP/∂P_d`` and ``∂Q_IP/∂Q_d`` (dimensionless: W/W, W/var,
var/W, var/var; P_IP and Q_IP MV → HV positive, P_d and Q_d injections). They are the grid in
the coupled P-Q loop (:mod:`adnmesh.analysis.coupling`). A difference of ``step`` (1 kW / 1
kvar) against a power flow solved to its tolerance leaves an error far below 1e-4 (tests
compare with pandapower's ``runpp``).
"""

from __future__ import annotations

import numpy as np

from adnmesh.errors import GridError

__all__ = ["interface_sensitivities"]


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
