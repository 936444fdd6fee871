"""The feasible P-Q region of the ADN at the interconnection point
(docs/method.md#feasible-p-q-region).

Which ``(P_IP, Q_IP)`` the DERs can reach together, with every reported bus voltage in
``[v_min_pu, v_max_pu]`` and every line and transformer loading at most ``loading_max_pct``
(the config's ``grid_model.limits``), each DER d within

- ``0 ≤ P_d ≤ P_avail,d`` (its available power at the study case, W),
- ``Q_min,d ≤ Q_d ≤ Q_max,d`` and ``P_d² + Q_d² ≤ S_inst,d²`` (its capability,
  :func:`adnmesh.reactive.capability_of`; var, VA),

and everything else in the grid as at the study case. DERs left out of ``available`` stay at
their schedules ``(P_sched,d, Q_sched,d)``, as the runtime runs an unavailable DER.

**Method: the support function.** For K evenly spread directions ``θ_k = 2πk/K`` the DERs'
set-points maximise ``cos θ_k · P_IP + sin θ_k · Q_IP`` on the AC power flow
(:class:`adnmesh.grid.GridSolver`), by scipy's SLSQP: the DER box as bounds, the apparent-power
circles as analytic constraints, P_IP, Q_IP and the grid limits through forward differences of
the power flow (one solve per free set-point, 1e-3 of the DER's rating). Each direction starts
from the last one's optimum.

- *Screening.* SLSQP sees the grid constraints within :data:`SCREEN_BAND` of their limit at a
  point reached; one found within the band at the optimum joins them and the direction is
  solved again.
- *Safeguards.* Where SLSQP ends outside the limits or short of a valid point it met on its
  way, that point is taken; where another direction's point reaches further in a direction
  (a local optimum: minimising P_IP maximises the losses), the direction is solved again from
  it.
- *Refinement.* For every edge of the polygon the optimum toward its outward normal is found;
  if the region reaches more than :data:`BOUNDARY_TOL_W` beyond the edge, that point becomes a
  vertex, until every edge is checked (or :data:`MAX_SUPPORT` points).
  :attr:`PQRegion.boundary_error_w` is the farthest the region reaches beyond an edge.
- *Without limits first.* The region under DER capability alone is computed first; its point
  in a direction that keeps the grid limits is the optimum under them too (a relaxation's
  optimum that is feasible), so only the other directions are optimised again.
- *Validation.* Every support point's set-points (within the DER limits) are solved again and
  must keep every voltage and loading within :data:`VOLTAGE_TOL_PU` and
  :data:`LOADING_TOL_PCT` of its limit, else :class:`~adnmesh.errors.GridError`.

The region is the convex hull of the support points (W, var): a polygon whose corners are
feasible operating points. Its edges are as accurate as the optimiser's optima are global; a
non-convex part of the true region would be bridged by an edge.

Run-time helpers, pure functions of a region: :func:`clip_reference` (the rule: see there),
:func:`p_range_w` and :func:`q_range_var`. What the CPFC clips its references to at run time
is cheaper: :func:`reference_bounds`, the region's extent in P and in Q (its support in the
four directions ±P, ±Q, no refinement: a fraction of a second).

Signs: ``P_IP``, ``Q_IP`` MV → HV positive (as :class:`~adnmesh.grid.GridSample`); DER P and Q
are injections (generator convention).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from adnmesh.config import DER, GridLimits, Reactive
from adnmesh.errors import GridError
from adnmesh.reactive import capability_of

__all__ = ["BINDING_TOL", "BOUNDARY_TOL_W", "DEFAULT_DIRECTIONS", "DER_CAPABILITY",
           "LOADING_TOL_PCT", "MAX_SUPPORT", "PRIORITIES", "SCREEN_BAND", "VOLTAGE_TOL_PU",
           "PQRegion", "SupportPoint", "binding_words", "clip_reference", "edge_words",
           "p_range_w", "pq_region", "q_range_var", "reference_bounds"]

DEFAULT_DIRECTIONS = 24
"""Evenly spread directions of the support function (every 15°) before the refinement."""

VOLTAGE_TOL_PU = 1e-6
"""How far a validated support point's bus voltage may lie outside its band, p.u."""

LOADING_TOL_PCT = 1e-4
"""How far a validated support point's line or transformer loading may exceed its limit, %."""

BINDING_TOL = (1e-4, 1e-2)
"""A grid limit *binds* at a support point within (voltage p.u., loading %) of it."""

SCREEN_BAND = (0.05, 50.0)
"""A grid constraint enters the optimisation once within (voltage p.u., loading %) of its limit
at a point the optimiser reached."""

BOUNDARY_TOL_W = 1e3
"""The refinement adds a support point where the region reaches further than this beyond an
edge of the polygon, W (var)."""

MAX_SUPPORT = 256
"""At most this many support points per region (the refinement stops there)."""

DER_CAPABILITY = "DER capability"
"""The binding label of a support point where no grid limit binds."""

PRIORITIES = ("p", "q", "nearest")
"""Rules of :func:`clip_reference`."""

_SCALE = (0.01, 10.0)               # one unit of a constraint for SLSQP: 0.01 p.u., 10 %
_STEP = 1e-3                                          # forward difference, of the DER's rating
_CONSISTENT_W = 1.0                  # a point this much further in a direction: optimise again
_ROUNDS = 6                                           # screening rounds per direction
_MAXITER = 200
_FTOL = 1e-9                         # of the objective over the DERs' summed rating: ~0.01 W


@dataclass(frozen=True)
class SupportPoint:
    """The optimum in one direction, validated by the power flow.

    Attributes
    ----------
    direction_rad : float
        θ: the point maximises ``cos θ · P_IP + sin θ · Q_IP``, rad.
    p_ip_w, q_ip_var : float
        P_IP and Q_IP there, W and var (MV → HV positive).
    der_p_w, der_q_var : ndarray
        Every DER's set-point there (:attr:`PQRegion.der_ids` order), W and var.
    binding : tuple of str
        The grid limits within :data:`BINDING_TOL` of their value, ``"<kind> <element>"``:
        ``"v_max bus 14"``, ``"v_min bus 3"``, ``"loading line 7"``, ``"loading trafo 0"``
        (buses, lines and transformers by their number in the grid model: pandapower's
        order); ``(DER_CAPABILITY,)`` if none.
    vm_min_pu, vm_max_pu, loading_max_pct : float
        The re-solved power flow's extremes (loading: lines and transformers), p.u. and %.
    optimal : bool
        SLSQP reported success (else the point is valid but maybe short of the optimum).
    """

    direction_rad: float
    p_ip_w: float
    q_ip_var: float
    der_p_w: np.ndarray
    der_q_var: np.ndarray
    binding: tuple[str, ...]
    vm_min_pu: float
    vm_max_pu: float
    loading_max_pct: float
    optimal: bool

    @property
    def value(self) -> float:
        """The support function's value ``cos θ · P_IP + sin θ · Q_IP``, W."""
        return math.cos(self.direction_rad) * self.p_ip_w + \
            math.sin(self.direction_rad) * self.q_ip_var


@dataclass(frozen=True)
class PQRegion:
    """The feasible P-Q region at the interconnection point (module docstring).

    Attributes
    ----------
    der_ids : tuple of str
        The DERs, in the order of each support point's set-points.
    moving : tuple of str
        Those that move (available); the others stay at their schedules.
    support : tuple of SupportPoint
        One per direction (the evenly spread ones and the refinement's), by direction.
    vertices : ndarray, shape (m, 2)
        The polygon, counter-clockwise, (P_IP W, Q_IP var); m < 3 if the region is a segment
        or a point.
    boundary_error_w : float
        How far the region reaches beyond the polygon's farthest edge, W (var): the support
        value toward the edge's normal where it was checked, else the corner of its end
        points' support lines.
    limits : GridLimits or None
        The grid limits applied (None: DER capability only).
    without_limits : PQRegion or None
        The region under the DERs' capability alone (None in that region itself).
    notes : tuple of str
        What a reader should know (e.g. the default capability preset used).
    power_flows : int
        Power flows solved for this region (and its comparison region).
    """

    der_ids: tuple[str, ...]
    moving: tuple[str, ...]
    support: tuple[SupportPoint, ...]
    vertices: np.ndarray
    boundary_error_w: float
    limits: GridLimits | None
    without_limits: PQRegion | None
    notes: tuple[str, ...]
    power_flows: int

    def p_span_w(self) -> tuple[float, float]:
        """Lowest and highest P_IP of the region, W."""
        return float(self.vertices[:, 0].min()), float(self.vertices[:, 0].max())

    def q_span_var(self) -> tuple[float, float]:
        """Lowest and highest Q_IP of the region, var."""
        return float(self.vertices[:, 1].min()), float(self.vertices[:, 1].max())

    def binding_limits(self) -> dict[str, tuple[str, ...]]:
        """The grid limits that bind at some support point: kind (``v_max``, ``v_min``,
        ``loading``) -> the elements (``bus 45``, ``line 7``, ``trafo 0``), in the model's
        order; empty if none binds."""
        out: dict[str, list[str]] = {}
        for label in sorted({b for s in self.support for b in s.binding},
                            key=_label_order):
            if label != DER_CAPABILITY:
                kind, element = label.split(" ", 1)
                out.setdefault(kind, []).append(element)
        return {kind: tuple(elements) for kind, elements in out.items()}

    def extremes(self) -> tuple[float, float, float]:
        """Lowest and highest bus voltage (p.u.) and highest loading (%) over the support
        points: how close to its limits the grid comes at the region's edge."""
        return (min(s.vm_min_pu for s in self.support), max(s.vm_max_pu for s in self.support),
                max(s.loading_max_pct for s in self.support))

    def contains(self, p_w: float, q_var: float, tol_w: float = 1e-3) -> bool:
        """Whether ``(p_w, q_var)`` lies in the polygon, to ``tol_w`` (W and var alike)."""
        return _distance_outside(self.vertices, np.array([p_w, q_var], float)) <= tol_w


def _label_order(label: str) -> tuple:
    """``v_max MV1.101 Bus 45`` before ``v_max MV1.101 Bus 64``: kind, element, number."""
    words = label.split()
    return (*words[:-1], int(words[-1])) if words[-1].isdigit() else (label, 0)


def binding_words(binding: dict[str, tuple[str, ...]], most: int = 4) -> str:
    """:meth:`PQRegion.binding_limits` in words: ``v_max at bus 13, bus 45, bus 64, bus 65 and
    1 more; loading at line 0`` (``none`` if empty)."""
    parts = []
    for kind, elements in binding.items():
        shown = ", ".join(elements[:most]) + (f" and {len(elements) - most} more"
                                               if len(elements) > most else "")
        parts.append(f"{kind} at {shown}")
    return "; ".join(parts) or "none"


def edge_words(region: PQRegion) -> str:
    """The binding limits and how close the grid comes to its limits at the region's edge,
    in words (one line; the summary of ``analyze --pq-region`` and its figure)."""
    vm_lo, vm_hi, loading = region.extremes()
    binding = region.binding_limits()
    return (f"binding grid limits: {binding_words(binding)}"
            + ("" if binding else " (the DERs' capability bounds it)")
            + f"; at the edge voltages {vm_lo:.4f} to {vm_hi:.4f} p.u., loading up to "
              f"{loading:.1f} %")


# --- the optimisation ---------------------------------------------------------------------------


class _Problem:
    """The DERs' set-points as SLSQP's variables, the power flow behind them."""

    def __init__(self, solver, ders: Sequence[DER], p_avail_w: Mapping[str, float],
                 reactive: Reactive | None, moving: set[str]) -> None:
        self.solver, self.n = solver, len(ders)
        self.rating = np.array([capability_of(d, reactive).s_va for d in ders])
        lo, hi = np.empty(2 * self.n), np.empty(2 * self.n)
        for i, der in enumerate(ders):
            cap = capability_of(der, reactive)
            if der.id in moving:
                lo[i], hi[i] = 0.0, min(max(float(p_avail_w[der.id]), 0.0), der.p_inst_w)
                lo[self.n + i], hi[self.n + i] = cap.q_min_var, cap.q_max_var
            else:
                lo[i] = hi[i] = der.p_sched_w
                lo[self.n + i] = hi[self.n + i] = der.q_sched_var
        self._box_within_circle(lo, hi)
        self.lo, self.hi = lo, hi
        self.free = np.flatnonzero(hi > lo)
        self.scale = np.tile(self.rating, 2)[self.free]
        self.circles = [i for i in range(self.n) if i in self.free and self.n + i in self.free]
        self.power_flows = 0
        self._rows, self.labels, kinds = _constraint_rows(solver)
        self.unit = np.array(_SCALE)[kinds]
        self.band = np.array(SCREEN_BAND)[kinds]
        self.binding_tol = np.array(BINDING_TOL)[kinds]
        self.tolerance = np.array([VOLTAGE_TOL_PU, LOADING_TOL_PCT])[kinds]
        self.x_lo, self.x_hi = self.lo[self.free] / self.scale, self.hi[self.free] / self.scale
        self.limits = _LOOSE
        self.watch(None)
        self.forget()

    def forget(self) -> None:
        """Drop the kept values (the limits or the constraints asked for changed)."""
        self._value: tuple = (None,)
        self._jacobian: tuple = (None,)

    def _box_within_circle(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Narrow a free Q to the circle where its P is fixed (and a free P where Q is)."""
        n, s2 = self.n, self.rating ** 2
        for i in range(n):
            if lo[i] == hi[i] and hi[n + i] > lo[n + i]:
                room = math.sqrt(max(s2[i] - lo[i] ** 2, 0.0))
                lo[n + i], hi[n + i] = max(lo[n + i], -room), min(hi[n + i], room)
            elif lo[n + i] == hi[n + i] and hi[i] > lo[i]:
                hi[i] = min(hi[i], math.sqrt(max(s2[i] - lo[n + i] ** 2, 0.0)))

    # set-points <-> SLSQP's variables (each free set-point over its DER's rating)

    def full(self, x: np.ndarray) -> np.ndarray:
        out = self.lo.copy()
        out[self.free] = x * self.scale
        return out

    def start(self, full: np.ndarray) -> np.ndarray:
        return np.clip(full, self.lo, self.hi)[self.free] / self.scale

    def bounds(self) -> list[tuple[float, float]]:
        return list(zip(self.x_lo, self.x_hi))

    # the power flow

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``((P_IP, Q_IP), grid constraints' slacks)`` at ``x`` (:attr:`limits`)."""
        setpoints = self.full(x)
        sample = self.solver.solve(setpoints[:self.n], setpoints[self.n:])
        self.power_flows += 1
        if not sample.converged:
            raise GridError("P-Q region: the power flow does not converge at DER set-points "
                            f"P {_mw(setpoints[:self.n])} MW, Q {_mw(setpoints[self.n:])} Mvar")
        z, slack = np.array([sample.p_ip_w, sample.q_ip_var]), self._rows(self.limits)
        if self._direction is not None:
            self._keep_best(x, z, slack)
        return z, slack

    def watch(self, theta: float | None) -> None:
        """Keep the best valid point :meth:`evaluate` meets toward ``theta`` (None: stop)."""
        self._direction = None if theta is None else np.array([math.cos(theta),
                                                               math.sin(theta)])
        self.best: tuple = (-math.inf, None)

    def _keep_best(self, x: np.ndarray, z: np.ndarray, slack: np.ndarray) -> None:
        value = float(self._direction @ z)
        if value > self.best[0] and np.all(slack >= -self.tolerance) and \
                np.all(x >= self.x_lo - 1e-9) and np.all(x <= self.x_hi + 1e-9) and \
                (not self.circles or self.circle(x).min() >= -1e-9):
            self.best = (value, x.copy())

    def near(self, slack: np.ndarray) -> np.ndarray:
        """The grid constraints within :data:`SCREEN_BAND` of their limit."""
        return np.flatnonzero(slack < self.band)

    def value(self, x: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P_IP, Q_IP) and the grid constraints ``rows`` (slacks over :data:`_SCALE`) at
        ``x``; the last point's are kept (SLSQP asks for the objective and the constraints
        at the same point)."""
        key = x.tobytes()
        if self._value[0] != key:
            z, slack = self.evaluate(x)
            self._value = (key, z, slack)
        _, z, slack = self._value
        return z, slack[rows] / self.unit[rows]

    def jacobian(self, x: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward-difference Jacobians of :meth:`value` at ``x`` (the last point's kept)."""
        key = x.tobytes()
        if self._jacobian[0] != key:
            z, g = self.value(x, rows)
            jz, jg = np.empty((2, x.size)), np.empty((rows.size, x.size))
            for j in range(x.size):
                moved = x.copy()
                moved[j] += _STEP
                z_j, slack_j = self.evaluate(moved)
                jz[:, j] = (z_j - z) / _STEP
                jg[:, j] = (slack_j[rows] / self.unit[rows] - g) / _STEP
            self._jacobian = (key, jz, jg)
        return self._jacobian[1], self._jacobian[2]

    def circle(self, x: np.ndarray) -> np.ndarray:
        """``(S² − P² − Q²) / S²`` of every DER whose P and Q both move."""
        full = self.full(x) / np.tile(self.rating, 2)
        i = np.array(self.circles, dtype=int)
        return 1.0 - full[i] ** 2 - full[self.n + i] ** 2

    def circle_jacobian(self, x: np.ndarray) -> np.ndarray:
        full = self.full(x) / np.tile(self.rating, 2)
        out = np.zeros((len(self.circles), x.size))
        position = {int(k): j for j, k in enumerate(self.free)}
        for row, i in enumerate(self.circles):
            for k in (i, self.n + i):
                out[row, position[k]] = -2.0 * full[k] * self.scale[position[k]] / \
                    self.rating[i]
        return out

    def on_capability(self, x: np.ndarray) -> np.ndarray:
        """``x`` inside the DER limits exactly: the box, then Q (not P) to the circle."""
        full = np.clip(self.full(x), self.lo, self.hi)
        for i in self.circles:
            room = math.sqrt(max(self.rating[i] ** 2 - full[i] ** 2, 0.0))
            full[self.n + i] = min(max(full[self.n + i], -room), room)
        return full[self.free] / self.scale


def _constraint_rows(solver):
    """A function of the grid limits returning the slack of every grid constraint at the
    solver's last solve (p.u. for voltages, % for loadings; ≥ 0 where met), the constraints'
    labels and their kinds (0 voltage, 1 loading). Buses that share a model bus count once."""
    buses, first = np.unique(solver.reported_buses, return_index=True)
    n_line = solver.line_loading_pct().size
    n_trafo = solver.trafo_loading_pct().size
    names = [solver.bus_names[i] for i in first]          # the net's names (else "bus N")
    labels = ([f"v_max {n}" for n in names] + [f"v_min {n}" for n in names]
              + [f"loading {n}" for n in solver.line_names[:n_line]]
              + [f"loading {n}" for n in solver.trafo_names[:n_trafo]])
    kinds = np.array([0] * (2 * buses.size) + [1] * (n_line + n_trafo))

    def rows(limits: GridLimits) -> np.ndarray:
        vm = solver.bus_vm_pu()[first]
        loading = np.concatenate([solver.line_loading_pct(), solver.trafo_loading_pct()])
        return np.concatenate([limits.v_max_pu - vm, vm - limits.v_min_pu,
                               limits.loading_max_pct - loading])
    return rows, tuple(labels), kinds


def _mw(values: np.ndarray) -> str:
    return "[" + ", ".join(f"{v / 1e6:.3f}" for v in values) + "]"


_LOOSE = GridLimits.model_construct(v_min_pu=0.0, v_max_pu=1e9, loading_max_pct=1e12)
"""Limits that never bind: the region under DER capability alone."""


def _optimum(problem: _Problem, theta: float, x: np.ndarray, working: np.ndarray,
             with_limits: bool):
    """SLSQP in direction ``theta`` from ``x``; grid constraints screened (module
    docstring). Returns ``(x, working set, SLSQP success)``."""
    from scipy.optimize import minimize

    c = np.array([math.cos(theta), math.sin(theta)])
    norm = 1.0 / problem.rating.sum()
    success = False
    for _ in range(_ROUNDS):
        rows = working
        constraints = []
        if problem.circles:
            constraints.append({"type": "ineq", "fun": problem.circle,
                                "jac": problem.circle_jacobian})
        if with_limits and rows.size:
            constraints.append({"type": "ineq",
                                "fun": lambda x: problem.value(x, rows)[1],
                                "jac": lambda x: problem.jacobian(x, rows)[1]})
        problem.forget()
        result = minimize(lambda x: -norm * c @ problem.value(x, rows)[0], x,
                          jac=lambda x: -norm * c @ problem.jacobian(x, rows)[0],
                          method="SLSQP", bounds=problem.bounds(), constraints=constraints,
                          options={"maxiter": _MAXITER, "ftol": _FTOL})
        x, success = problem.on_capability(result.x), bool(result.success)
        if not with_limits:
            break
        _, slack = problem.evaluate(x)
        new = np.setdiff1d(problem.near(slack), working)
        if new.size == 0:
            break
        working = np.union1d(working, new)
    return x, working, success


def _outside(problem: _Problem, limits: GridLimits) -> str | None:
    """How the last solve breaks ``limits`` beyond the tolerances, in words (None: it
    does not)."""
    solver = problem.solver
    vm = solver.bus_vm_pu()
    loading = np.concatenate([solver.line_loading_pct(), solver.trafo_loading_pct()])
    highest = float(loading.max()) if loading.size else -math.inf
    if max(limits.v_min_pu - vm.min(), vm.max() - limits.v_max_pu) > VOLTAGE_TOL_PU or \
            highest - limits.loading_max_pct > LOADING_TOL_PCT:
        return (f"voltages {vm.min():.4f} to {vm.max():.4f} p.u. for [{limits.v_min_pu:g}, "
                f"{limits.v_max_pu:g}], loading up to {highest:.2f} % for "
                f"{limits.loading_max_pct:g} %")
    return None


def _validated(problem: _Problem, theta: float, x: np.ndarray, optimal: bool
               ) -> SupportPoint | None:
    """The support point at ``x``, re-solved; None if it breaks :attr:`_Problem.limits`."""
    setpoints = problem.full(x)
    z, _ = problem.evaluate(x)
    if _outside(problem, problem.limits) is not None:
        return None
    solver = problem.solver
    vm = solver.bus_vm_pu()
    loading = np.concatenate([solver.line_loading_pct(), solver.trafo_loading_pct()])
    return SupportPoint(theta % (2 * math.pi), float(z[0]), float(z[1]),
                        setpoints[:problem.n].copy(), setpoints[problem.n:].copy(),
                        _binding(problem), float(vm.min()), float(vm.max()),
                        float(loading.max()) if loading.size else math.nan, optimal)


def _binding(problem: _Problem) -> tuple[str, ...]:
    """Labels of the grid limits within :data:`BINDING_TOL` at the last solve."""
    slack = problem._rows(problem.limits)
    labels = tuple(problem.labels[i] for i in np.flatnonzero(slack <= problem.binding_tol))
    return labels or (DER_CAPABILITY,)


class _Progress:
    """Counts optimisations for the ``progress(done, total)`` callback; the refinement adds
    to the total as it goes."""

    def __init__(self, total: int, report: Callable[[int, int], None] | None) -> None:
        self.done, self.total, self.report = 0, total, report

    def step(self, more: int = 0) -> None:
        self.done += 1
        self.total += more
        if self.report is not None:
            self.report(self.done, self.total)


class _Search:
    """The support points of one region: the optimisation's working set of grid constraints,
    the last optimum (where the next direction starts) and which edges were checked."""

    def __init__(self, problem: _Problem, limits: GridLimits | None, x0: np.ndarray,
                 progress: _Progress) -> None:
        self.problem, self.grid, self.progress = problem, limits is not None, progress
        problem.limits = limits if limits is not None else _LOOSE
        _, slack = problem.evaluate(x0)
        self.working = problem.near(slack) if self.grid else np.zeros(0, dtype=int)
        self.x = x0
        self.gaps: dict = {}

    def toward(self, theta: float, x: np.ndarray | None = None) -> SupportPoint:
        """The validated optimum toward ``theta``, from ``x`` (default: the last optimum).
        Where SLSQP ends outside the limits (it can cycle at the kink of a loading, the larger
        of a branch's two end currents) or short of a point it met on the way, the best valid
        set-points it met (iterates and difference steps) are taken."""
        problem = self.problem
        problem.watch(theta)
        x, self.working, success = _optimum(problem, theta, self.x if x is None else x,
                                            self.working, self.grid)
        value, met = problem.best
        problem.watch(None)
        point = _validated(problem, theta, x, success)
        if met is not None and (point is None or value > point.value + _CONSISTENT_W):
            other = _validated(problem, theta, problem.on_capability(met), False)
            if other is not None and (point is None or other.value > point.value):
                point, x = other, problem.on_capability(met)
        if point is None:
            raise GridError("P-Q region: no DER set-points found that keep the grid within "
                            f"its limits toward {math.degrees(theta):.0f}° ("
                            f"{_outside(self.problem, self.problem.limits)})")
        self.x = x
        return point

    def at(self, theta: float, point: SupportPoint) -> SupportPoint | None:
        """``point``'s set-points as the support point toward ``theta`` if they keep this
        region's limits (None if not): an optimum without grid limits that keeps them is the
        optimum under them too."""
        return _validated(self.problem, theta, _variables(self.problem, point), point.optimal)

    def consistent(self, points: list) -> None:
        """Where another point reaches further in a point's direction (the optimiser stopped
        at a local optimum: minimising P_IP maximises the losses), optimise that direction
        again from it; as long as that helps, at most :data:`_ROUNDS` times."""
        for _ in range(_ROUNDS):
            values = np.array([[math.cos(p.direction_rad) * o.p_ip_w
                                + math.sin(p.direction_rad) * o.q_ip_var for o in points]
                               for p in points])
            best = values.argmax(axis=1)
            again = [k for k in range(len(points))
                     if values[k, best[k]] > values[k, k] + _CONSISTENT_W]
            if not again:
                return
            for k in again:
                theta, donor = points[k].direction_rad, points[best[k]]
                point = self.toward(theta, _variables(self.problem, donor))
                if _value_in(theta, point) < _value_in(theta, donor):
                    point = self.at(theta, donor)
                points[k] = point

    def refine(self, points: list) -> tuple[tuple[SupportPoint, ...], float]:
        """For every edge of the polygon, the support point toward its outward normal; one
        more than :data:`BOUNDARY_TOL_W` beyond the edge becomes a vertex (up to
        :data:`MAX_SUPPORT` points, the widest gaps first). Returns the points by direction
        and the widest distance the region reaches beyond an edge: the normal's support value
        where an edge was checked, else the corner of its end points' support lines."""
        while len(points) < MAX_SUPPORT:
            todo = [e for e in _hull_edges(points) if _key(*e) not in self.gaps]
            if not todo:
                break
            a, b = max(todo, key=lambda e: _corner_gap(*e))
            normal = math.atan2(-(b.p_ip_w - a.p_ip_w), b.q_ip_var - a.q_ip_var)
            point = self.toward(normal, _between(self.problem, a, b))
            gap = max(point.value - (math.cos(normal) * a.p_ip_w
                                     + math.sin(normal) * a.q_ip_var), 0.0)
            self.gaps[_key(a, b)] = gap
            if gap > BOUNDARY_TOL_W:
                points.append(point)
            self.progress.step(more=1)
        error = max([self.gaps.get(_key(a, b), _corner_gap(a, b))
                     for a, b in _hull_edges(points)], default=0.0)
        return tuple(sorted(points, key=lambda p: p.direction_rad)), error


def _value_in(theta: float, point: SupportPoint) -> float:
    return math.cos(theta) * point.p_ip_w + math.sin(theta) * point.q_ip_var


def _key(a: SupportPoint, b: SupportPoint) -> tuple:
    """An edge by its end points' coordinates (the same in a region that reuses them)."""
    return (a.p_ip_w, a.q_ip_var, b.p_ip_w, b.q_ip_var)


def _hull_edges(points: Sequence[SupportPoint]) -> list[tuple[SupportPoint, SupportPoint]]:
    order = _hull_indices([[p.p_ip_w, p.q_ip_var] for p in points])
    return [(points[i], points[j]) for i, j in zip(order, order[1:] + order[:1]) if i != j]


def _without_limits(problem: _Problem, thetas: np.ndarray, x0: np.ndarray,
                    progress: _Progress):
    """The support points under DER capability alone (each direction from the last one's
    optimum, then the refinement), the boundary error and the checked edges."""
    search = _Search(problem, None, x0, progress)
    points = []
    for theta in thetas:
        points.append(search.toward(float(theta)))
        progress.step()
    search.consistent(points)
    support, error = search.refine(points)
    return support, error, search.gaps


def _within_limits(problem: _Problem, loose: Sequence[SupportPoint], gaps: dict,
                   limits: GridLimits, x0: np.ndarray, progress: _Progress):
    """The support points under the grid limits: in each direction of ``loose`` (the region
    without them), its point where it keeps the limits, else the optimum under them; then
    the refinement. An edge checked without limits between two points kept needs no check:
    the region under limits reaches no further."""
    search = _Search(problem, limits, x0, progress)
    points, kept = [], set()
    for point in loose:
        same = search.at(point.direction_rad, point)
        if same is not None:                   # the same point, the limits' binding labels
            kept.add((point.p_ip_w, point.q_ip_var))
            points.append(replace(point, binding=same.binding))
        else:
            points.append(search.toward(point.direction_rad))
        progress.step()
    search.consistent(points)
    search.gaps = {key: gap for key, gap in gaps.items()
                   if key[:2] in kept and key[2:] in kept}
    support, error = search.refine(points)
    return support, error


def _between(problem: _Problem, a: SupportPoint, b: SupportPoint) -> np.ndarray:
    """Where the optimum toward the normal of the edge ``a``–``b`` starts: halfway between
    their set-points, each DER that is on its circle at both taken out onto it (the arc
    between them)."""
    p = (a.der_p_w + b.der_p_w) / 2
    q = (a.der_q_var + b.der_q_var) / 2
    s = problem.rating
    on = (np.hypot(a.der_p_w, a.der_q_var) > s * (1 - 1e-6)) & \
        (np.hypot(b.der_p_w, b.der_q_var) > s * (1 - 1e-6)) & (np.hypot(p, q) > 0)
    scale = np.where(on, s / np.maximum(np.hypot(p, q), 1e-300), 1.0)
    return problem.on_capability(problem.start(np.concatenate([p * scale, q * scale])))


def _variables(problem: _Problem, point: SupportPoint) -> np.ndarray:
    return problem.start(np.concatenate([point.der_p_w, point.der_q_var]))


def pq_region(solver, ders: Sequence[DER], p_avail_w: Mapping[str, float],
              limits: GridLimits, reactive: Reactive | None = None, *,
              available: Iterable[str] | None = None, directions: int = DEFAULT_DIRECTIONS,
              progress: Callable[[int, int], None] | None = None) -> PQRegion:
    """The feasible P-Q region at the interconnection point (module docstring).

    Parameters
    ----------
    solver : GridSolver
        The grid at its study case, with ``ders``' sgens as its actuators in this order.
    ders : sequence of DER
        The config's DERs.
    p_avail_w : mapping
        DER id -> available power, W (:func:`adnmesh.control.operating_point.available_power_w`).
    limits : GridLimits
        Voltage band (p.u.) and loading limit (%).
    reactive : Reactive or None
        The config's reactive section (None: every DER's own preset, else the default one).
    available : iterable of str, optional
        The DERs that move (default all); the others stay at their schedules.
    directions : int
        Directions of the support function, at least 4.
    progress : callable, optional
        ``progress(done, total)`` after each optimisation (``total``: 2 × ``directions``
        plus the refinement's so far).

    Returns
    -------
    PQRegion
        With its :attr:`~PQRegion.without_limits` comparison.

    Raises
    ------
    GridError
        No set-points keep the grid within its limits, or the power flow does not converge.
    ValueError
        ``directions`` below 4, an unknown DER id, or a solver of other actuators.
    """
    if directions < 4:
        raise ValueError(f"directions: at least 4, got {directions}")
    if tuple(solver.actuator_sgens) != tuple(d.sgen for d in ders):
        raise ValueError("the solver's actuators are not the DERs' sgens in their order")
    ids = tuple(d.id for d in ders)
    moving = set(ids if available is None else available)
    unknown = sorted(moving - set(ids))
    if unknown:
        raise ValueError(f"unknown DER id {unknown[0]!r} (known: {', '.join(ids)})")
    problem = _Problem(solver, ders, p_avail_w, reactive, moving)
    schedules = np.array([d.p_sched_w for d in ders] + [d.q_sched_var for d in ders], float)
    x0 = problem.start(schedules)
    thetas = 2.0 * math.pi * np.arange(directions) / directions
    notes = _notes(ders, reactive, moving)
    if problem.free.size == 0:
        notes += ("no DER moves: the region is the one operating point",)
    counter = _Progress(2 * directions, progress)
    loose, loose_error, gaps = _without_limits(problem, thetas, x0, counter)
    counter.total += len(loose) - directions
    with_limits, error = _within_limits(problem, loose, gaps, limits, x0, counter)
    solver.solve(schedules[:problem.n], schedules[problem.n:])   # left at the schedules
    kept = tuple(i for i in ids if i in moving)
    bare = _region(ids, kept, loose, loose_error, None, None, notes, 0)
    return _region(ids, kept, with_limits, error, limits, bare, notes, problem.power_flows)


def reference_bounds(solver, ders: Sequence[DER], p_avail_w: Mapping[str, float],
                     limits: GridLimits, reactive: Reactive | None = None
                     ) -> tuple[tuple[float, float], tuple[float, float]]:
    """The region's extent: ``((P_min, P_max), (Q_min, Q_max))`` of ``(P_IP, Q_IP)`` the DERs
    can reach within the grid limits and their capability (W, var), each the validated
    support point toward ±P or ±Q (as :func:`pq_region` finds them, without the refinement).
    A reference beyond it cannot be reached by any set-points; the CPFC clips to it. The
    solver is left at the schedules.

    Raises
    ------
    GridError
        No set-points keep the grid within its limits, or the power flow does not converge.
    """
    if tuple(solver.actuator_sgens) != tuple(d.sgen for d in ders):
        raise ValueError("the solver's actuators are not the DERs' sgens in their order")
    problem = _Problem(solver, ders, p_avail_w, reactive, {d.id for d in ders})
    schedules = np.array([d.p_sched_w for d in ders] + [d.q_sched_var for d in ders], float)
    x0 = problem.start(schedules)
    search = _Search(problem, limits, x0, _Progress(4, None))
    points = [search.toward(theta) for theta in (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi)]
    search.consistent(points)
    solver.solve(schedules[:problem.n], schedules[problem.n:])   # left at the schedules
    p = [point.p_ip_w for point in points]
    q = [point.q_ip_var for point in points]
    return (min(p), max(p)), (min(q), max(q))


def _notes(ders: Sequence[DER], reactive: Reactive | None, moving: set[str]) -> tuple[str, ...]:
    notes = []
    if reactive is None:
        preset = Reactive().capability
        own = [d.id for d in ders if d.q_capability or d.cos_phi_under or d.cos_phi_over]
        notes.append(f"no reactive section: the DERs' reactive range is the default capability "
                     f"preset {preset}" + (f" (but {', '.join(own)}: their own)" if own else ""))
    still = [d.id for d in ders if d.id not in moving]
    if still:
        notes.append(f"not available, at their schedules: {', '.join(still)}")
    return tuple(notes)


def _region(ids, moving, support, error, limits, bare, notes, power_flows) -> PQRegion:
    points = np.array([[s.p_ip_w, s.q_ip_var] for s in support])
    return PQRegion(ids, moving, support, _hull(points), error, limits, bare, notes,
                    power_flows)


# --- geometry -----------------------------------------------------------------------------------


def _hull(points: np.ndarray) -> np.ndarray:
    """Convex hull, counter-clockwise, without repeated or collinear points (Andrew's
    monotone chain); a segment or a point if the points are."""
    return np.asarray(points, float).reshape(-1, 2)[_hull_indices(points)]


def _hull_indices(points) -> list[int]:
    """Indices of :func:`_hull`'s vertices in ``points`` (the first of equal points)."""
    first: dict = {}
    for k, (p, q) in enumerate(np.asarray(points, float).reshape(-1, 2).tolist()):
        first.setdefault((p, q), k)
    keys = sorted(first)
    if len(keys) <= 2:
        return [first[k] for k in keys]

    def half(seq):
        out: list = []
        for point in seq:
            while len(out) >= 2 and _cross(out[-2], out[-1], point) <= 0:
                out.pop()
            out.append(point)
        return out
    lower, upper = half(keys), half(reversed(keys))
    return [first[k] for k in lower[:-1] + upper[:-1]]


def _cross(o, a, b) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _corner_gap(a: SupportPoint, b: SupportPoint) -> float:
    """Distance from the chord ``a``–``b`` to the corner of their support lines, W: the
    region's boundary between them lies in that triangle (inf if the lines are parallel)."""
    za, zb = np.array([a.p_ip_w, a.q_ip_var]), np.array([b.p_ip_w, b.q_ip_var])
    ca = np.array([math.cos(a.direction_rad), math.sin(a.direction_rad)])
    cb = np.array([math.cos(b.direction_rad), math.sin(b.direction_rad)])
    if abs(ca[0] * cb[1] - ca[1] * cb[0]) < 1e-12:
        return math.inf
    corner = np.linalg.solve(np.array([ca, cb]), np.array([a.value, b.value]))
    return _segment_distance(za, zb, corner)


def _segment_distance(a: np.ndarray, b: np.ndarray, z: np.ndarray) -> float:
    return float(np.linalg.norm(z - _project_segment(a, b, z)))


def _project_segment(a: np.ndarray, b: np.ndarray, z: np.ndarray) -> np.ndarray:
    d = b - a
    length2 = float(d @ d)
    t = 0.0 if length2 == 0 else min(max(float((z - a) @ d) / length2, 0.0), 1.0)
    return a + t * d


def _edges(vertices: np.ndarray):
    m = len(vertices)
    return [(vertices[i], vertices[(i + 1) % m]) for i in range(m)] if m > 1 else \
        [(vertices[0], vertices[0])]


def _distance_outside(vertices: np.ndarray, z: np.ndarray) -> float:
    """0 inside the polygon, else the distance to it."""
    if len(vertices) >= 3 and all(_cross(a, b, z) >= 0 for a, b in _edges(vertices)):
        return 0.0
    return min(_segment_distance(a, b, z) for a, b in _edges(vertices))


def _nearest(vertices: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The polygon's point nearest ``z`` (``z`` itself inside)."""
    if _distance_outside(vertices, z) == 0.0:
        return z
    candidates = [_project_segment(a, b, z) for a, b in _edges(vertices)]
    return min(candidates, key=lambda c: float(np.linalg.norm(z - c)))


def _interval(vertices: np.ndarray, axis: int, value: float) -> tuple[float, float] | None:
    """The polygon's extent along the other axis where coordinate ``axis`` equals ``value``
    (None: the line misses it)."""
    other = 1 - axis
    hits = [float(v[other]) for v in vertices if v[axis] == value]
    for a, b in _edges(vertices):
        if min(a[axis], b[axis]) < value < max(a[axis], b[axis]):
            t = (value - a[axis]) / (b[axis] - a[axis])
            hits.append(float(a[other] + t * (b[other] - a[other])))
    return (min(hits), max(hits)) if hits else None


def q_range_var(region: PQRegion, p_w: float) -> tuple[float, float] | None:
    """The region's lowest and highest Q_IP at ``P_IP = p_w``, var (None: ``p_w`` outside
    its P range)."""
    return _interval(region.vertices, 0, float(p_w))


def p_range_w(region: PQRegion, q_var: float) -> tuple[float, float] | None:
    """The region's lowest and highest P_IP at ``Q_IP = q_var``, W (None: ``q_var`` outside
    its Q range)."""
    return _interval(region.vertices, 1, float(q_var))


def clip_reference(region: PQRegion, p_ref_w: float, q_ref_var: float, priority: str = "p"
                   ) -> tuple[float, float, bool]:
    """The reference ``(P_ref, Q_ref)`` moved into the region, W and var.

    A reference inside the region (to 1 mW / 1 mvar) is returned as it is. Outside, by
    ``priority``:

    - ``"p"`` (default; P is the main service, as ``reactive.priority: p`` keeps a DER's P):
      P_ref is kept if the region has it at some Q, else moved to the nearest end of the
      region's P range; then Q_ref is clipped to the region's Q range at that P;
    - ``"q"``: the same with the roles of P and Q exchanged;
    - ``"nearest"``: the region's point nearest to the reference (1 W counted as 1 var).

    Returns
    -------
    (p_w, q_var, clipped)
        ``clipped`` is whether the reference was moved.
    """
    if priority not in PRIORITIES:
        raise ValueError(f"priority: one of {', '.join(PRIORITIES)}, got {priority!r}")
    if region.contains(p_ref_w, q_ref_var):
        return float(p_ref_w), float(q_ref_var), False
    vertices = region.vertices
    if priority == "nearest":
        p, q = _nearest(vertices, np.array([p_ref_w, q_ref_var], float))
        return float(p), float(q), True
    first, second = (0, 1) if priority == "p" else (1, 0)
    wanted = (float(p_ref_w), float(q_ref_var))
    low, high = float(vertices[:, first].min()), float(vertices[:, first].max())
    kept = min(max(wanted[first], low), high)
    span = _interval(vertices, first, kept)
    other = min(max(wanted[second], span[0]), span[1])
    out = (kept, other) if priority == "p" else (other, kept)
    return out[0], out[1], True
