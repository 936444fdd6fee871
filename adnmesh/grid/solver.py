"""Fast, warm-started AC power flow of one grid with a few actuator generators.

:class:`GridSolver` takes a :class:`~adnmesh.grid.data.GridData` and the names of the actuator
static generators, and solves the power flow for one vector of their active powers at a time
(:meth:`GridSolver.solve`): lightsim2grid's Newton-Raphson (single slack, KLU sparse LU where
the build has it) on its own copy of the grid model, starting from the previous solution. The
model keeps its factorisation structure between solves; only the actuators' injections change.
Everything else in the grid is a constant injection (constant-impedance loads are shunts); the
actuators' reactive power stays at its study-case value unless :meth:`GridSolver.solve` is given
theirs.

Results (:class:`GridSample`) follow pandapower's definitions: ``P_IP``/``Q_IP`` are the external
grid's injection with the sign turned, so that power flowing from the MV grid into the 110 kV
grid is positive; voltage extremes over the net's buses (``res_bus.vm_pu``) except the external
grid's (the slack's voltage is set by the upper grid, a constant: it is no voltage of the ADN,
and at the reference case it would be the lowest, a flat line); loadings as
``res_line.loading_percent`` (the larger end current over ``max_i_ka · df · parallel``) and
``res_trafo.loading_percent`` (pandapower's default ``trafo_loading="current"``: the larger of
``i_hv · vn_hv_kv`` and ``i_lv · vn_lv_kv``, times √3, over ``sn_mva · parallel · df``).

Each extreme says where it is: the name of the bus, line or transformer (:class:`GridSample`,
names from :class:`~adnmesh.grid.data.GridData`).

**Taps.** :meth:`GridSolver.set_tap` moves a transformer's ratio tap changer as ``runpp`` moves
it for ``net.trafo.tap_pos = pos`` (pandapower's ratio model): the ratio by
``1 + (pos - tap_neutral) · tap_step_percent / 100`` on the tap's side and, for a tap on the
lv side, the transformer's series impedance by that factor squared and its magnetising
admittance by its inverse square (pandapower refers them to the tapped lv voltage). Where the
net names no ``tap_changer_type`` (SimBench's nets under pandapower 3) ``runpp`` ignores
``tap_pos``; the model starts at neutral and :meth:`GridSolver.set_tap` moves it as ``runpp``
does with ``tap_changer_type = "Ratio"`` (the kind SimBench's data describe: a step in %, none
in degrees). Exact to the power flow's tolerance (tests against ``runpp``).

Accuracy: Newton-Raphson to a power mismatch below ``tol_pu`` (default 1e-8 p.u. of the model's
1 MVA base, i.e. 0.01 W / 0.01 var), the tolerance pandapower's ``runpp`` uses by default.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from adnmesh.grid.data import GridData
from adnmesh.errors import GridError

__all__ = ["Branches", "GridSample", "GridSolver", "available_power_w"]

_SQRT3 = math.sqrt(3.0)


@dataclass(frozen=True)
class GridSample:
    """One power-flow solution, as the measurement at the interconnection point sees it.

    Attributes
    ----------
    p_ip_w, q_ip_var : float
        Active and reactive power at the interconnection point (the slack, 110 kV side),
        positive from the MV grid to the HV grid, W and var.
    vm_min_pu, vm_max_pu : float
        Lowest and highest bus voltage, p.u., over the net's buses but the slack's.
    line_loading_max_pct, trafo_loading_max_pct : float
        Highest line and transformer loading, % (pandapower's definitions; NaN if none).
    converged : bool
        Whether Newton-Raphson converged; if not, every number is NaN.
    iterations : int
        Newton-Raphson iterations of the (last) attempt.
    vm_min_at, vm_max_at : str
        Name of the bus with the lowest and the highest voltage ("" if not converged).
    line_max_at, trafo_max_at : str
        Name of the most loaded line and transformer ("" if none or not converged).
    """

    p_ip_w: float
    q_ip_var: float
    vm_min_pu: float
    vm_max_pu: float
    line_loading_max_pct: float
    trafo_loading_max_pct: float
    converged: bool
    iterations: int
    vm_min_at: str = ""
    vm_max_at: str = ""
    line_max_at: str = ""
    trafo_max_at: str = ""


@dataclass(frozen=True, eq=False)
class Branches:
    """The lines or the transformers of the solver's model as π models (its taps applied).

    Side 1 is a line's from bus and a transformer's hv bus. The currents into the branch are
    ``I₁ = y11·V₁ + y12·V₂`` and ``I₂ = y21·V₁ + y22·V₂`` (p.u. of the model's base).

    Attributes
    ----------
    bus1, bus2 : ndarray of int
        Model bus of each side.
    y11, y12, y21, y22 : ndarray of complex
        Admittances, p.u. (zero where the branch is out of service).
    connected : ndarray of bool
        Whether the branch is in service.
    """

    bus1: np.ndarray
    bus2: np.ndarray
    y11: np.ndarray
    y12: np.ndarray
    y21: np.ndarray
    y22: np.ndarray
    connected: np.ndarray

    @classmethod
    def of(cls, container) -> "Branches":
        """The branches of a lightsim2grid line or transformer container."""
        items = list(container)
        ints = {k: np.array([getattr(b, k) for b in items], dtype=np.int64)
                for k in ("bus1_id", "bus2_id")}
        ys = {k: np.array([getattr(b, f"yac_eff_{k[1:]}") for b in items], dtype=complex)
              for k in ("y11", "y12", "y21", "y22")}
        connected = np.array([bool(b.connected_global) for b in items], dtype=bool)
        return cls(ints["bus1_id"], ints["bus2_id"], **ys, connected=connected)


def available_power_w(data: GridData, sgen_names) -> np.ndarray:
    """Available active power of the named static generators at the study case, W.

    It is their SimBench ``p_mw`` times the study case's scaling for their type (``Wind_p`` for
    wind, ``PV_p`` for PV, ``RES_p`` for the rest) times their ``scaling``, as
    :func:`adnmesh.grid.simbench_net.apply_study_case` set it.
    """
    return data.sgen_p_mw[data.sgen_index(sgen_names)] * 1e6


def _single_slack_nr(grid) -> None:
    """Switch ``grid`` to lightsim2grid's single-slack Newton-Raphson (KLU if available)."""
    from lightsim2grid.algorithm import AlgorithmType
    names = set(grid.available_algorithm_names())
    for algo in ("NRSing_KLU", "NRSing_SparseLU"):
        if algo in names:
            grid.change_algorithm(getattr(AlgorithmType, algo))
            return


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
        Convergence tolerance on the power mismatch, p.u. of the model's base (1 MVA).
    """

    def __init__(self, data: GridData, actuator_sgens, max_iter: int = 20,
                 tol_pu: float = 1e-8) -> None:
        self.data = data
        self.actuator_sgens = tuple(actuator_sgens)
        self._act = [int(i) for i in data.sgen_index(self.actuator_sgens)]
        self._grid = data.lsgrid.copy()
        _single_slack_nr(self._grid)
        grid = self._grid
        self._setters = {"sgen_p": grid.change_p_sgen, "load_p": grid.change_p_load,
                         "load_q": grid.change_q_load, "shunt_p": grid.change_p_shunt,
                         "shunt_q": grid.change_q_shunt, "storage_p": grid.change_p_storage,
                         "gen_p": grid.change_p_gen}     # set_injections' kinds
        self._max_iter, self._tol = int(max_iter), float(tol_pu)
        self._v = data.v_init.astype(complex).copy()
        reported = _without_slack(data.report_bus, self._grid, data.slack_gen)
        self._report_bus = data.report_bus[reported]
        self._bus_names = tuple(data.bus_names[i] for i in np.flatnonzero(reported))
        self._tap = data.tap_pos.copy()
        trafos = list(self._grid.get_trafos())
        self._ratio0 = np.array([t.ratio for t in trafos], dtype=float)
        self._r0 = np.array([t.r_pu for t in trafos], dtype=float)
        self._x0 = np.array([t.x_pu for t in trafos], dtype=float)
        self._b0 = np.array([t.h1_pu + t.h2_pu for t in trafos], dtype=complex)
        self._impedance_scale = np.ones(len(trafos))     # of r, x (1/it of b) since the case
        self._branches: tuple[Branches, Branches] | None = None
        self._line_factor = 100.0 / data.line_i_max_ka
        self._hv_factor = _SQRT3 * 100.0 * data.trafo_vn_hv_kv / data.trafo_rating_mva
        self._lv_factor = _SQRT3 * 100.0 * data.trafo_vn_lv_kv / data.trafo_rating_mva

    @property
    def n_actuators(self) -> int:
        """Number of actuator generators."""
        return len(self.actuator_sgens)

    @property
    def model(self):
        """The solver's own lightsim2grid model, holding the results of the last solve (read
        them, change nothing)."""
        return self._grid

    @property
    def voltages_pu(self) -> np.ndarray:
        """Complex bus voltages of the last converged solution (model bus order), p.u."""
        return self._v.copy()

    def bus_vm_pu(self) -> np.ndarray:
        """Voltage magnitude of every reported bus (``data.report_bus`` but the slack's, in
        that order) at the last converged solution, p.u."""
        return np.abs(self._v[self._report_bus])

    @property
    def reported_buses(self) -> np.ndarray:
        """The model buses :meth:`bus_vm_pu` reports, in its order."""
        return self._report_bus.copy()

    @property
    def bus_names(self) -> tuple[str, ...]:
        """Names of the buses :meth:`bus_vm_pu` reports, in its order."""
        return self._bus_names

    @property
    def line_names(self) -> tuple[str, ...]:
        """Names of the lines, in :meth:`line_loading_pct`'s order."""
        return self.data.line_names

    @property
    def trafo_names(self) -> tuple[str, ...]:
        """Names of the transformers, in :meth:`trafo_loading_pct`'s order."""
        return self.data.trafo_names

    def branches(self) -> tuple[Branches, Branches]:
        """The lines and the transformers as π models, taps as set (:class:`Branches`)."""
        if self._branches is None:
            self._branches = (Branches.of(self._grid.get_lines()),
                              Branches.of(self._grid.get_trafos()))
        return self._branches

    def loading_pct_per_ka(self) -> tuple[tuple[np.ndarray, np.ndarray],
                                          tuple[np.ndarray, np.ndarray]]:
        """What turns side 1's and side 2's current (kA) into loading (%): ``((line side 1,
        line side 2), (trafo hv, trafo lv))``, % per kA; the loading is the larger side's."""
        return ((self._line_factor, self._line_factor), (self._hv_factor, self._lv_factor))

    def tap_pos(self, trafo: int) -> int:
        """The tap position transformer ``trafo`` (model order) is at; :class:`GridError` if it
        has no tap changer."""
        self._tap_changer(trafo)
        return int(round(float(self._tap[trafo])))

    def set_tap(self, trafo: int, pos: int) -> None:
        """Put transformer ``trafo``'s tap at ``pos`` (see the module docstring); the next
        :meth:`solve` solves with it (the last solution's results are not changed). Parallel
        transformers (SimBench's HV/MV substations have two) move one by one: a tap on one
        alone drives a circulating current between them.

        Raises
        ------
        GridError
            The transformer has no tap changer, or ``pos`` is no integer in
            ``[tap_min, tap_max]``.
        """
        data = self.data
        name = self._tap_changer(trafo)
        low, high = data.tap_min[trafo], data.tap_max[trafo]
        try:
            whole = float(pos).is_integer()
        except (TypeError, ValueError):
            whole = False
        if not whole or not low <= float(pos) <= high:
            raise GridError(f"grid solver: tap position {pos!r} of transformer {trafo} "
                            f"({name}) is not an integer in its range [{low:g}, {high:g}]")
        factor = self._tap_factor(trafo, float(pos)) / self._tap_factor(trafo,
                                                                         data.tap_pos[trafo])
        self._grid.change_ratio_trafo(trafo, float(self._ratio0[trafo] * factor))
        if data.tap_side[trafo] == "lv":             # impedances referred to the tapped side
            self._impedance_scale[trafo] = factor ** 2
            scale = self._impedance_scale
            self._grid.update_trafos_parameters(self._r0 * scale, self._x0 * scale,
                                                self._b0 / scale)
        self._tap[trafo] = float(pos)
        self._branches = None

    def _tap_changer(self, trafo: int) -> str:
        """The name of transformer ``trafo``; :class:`GridError` unless it has a tap changer."""
        names = self.data.trafo_names
        if not isinstance(trafo, (int, np.integer)) or not 0 <= trafo < len(names):
            raise GridError(f"grid solver: no transformer {trafo!r} (the grid has "
                            f"{len(names)})")
        if self.data.tap_side[trafo] == "none":
            raise GridError(f"grid solver: transformer {trafo} ({names[trafo]}) has no ratio "
                            f"tap changer in the net")
        return names[trafo]

    def _tap_factor(self, trafo: int, pos: float) -> float:
        """pandapower's voltage factor of the tap's side at ``pos``, 1 at neutral."""
        data = self.data
        return 1.0 + (pos - data.tap_neutral[trafo]) * data.tap_step_percent[trafo] / 100.0

    def line_loading_pct(self) -> np.ndarray:
        """Every line's loading at the last solve (pandapower's definition), %; NaN after a
        solve that did not converge."""
        with np.errstate(invalid="ignore", over="ignore"):
            return self._line_loading()

    def trafo_loading_pct(self) -> np.ndarray:
        """Every transformer's loading at the last solve (pandapower's definition), %; NaN
        after a solve that did not converge."""
        with np.errstate(invalid="ignore", over="ignore"):
            return self._trafo_loading()

    def _line_loading(self) -> np.ndarray:   # (the caller silences NaN's warnings)
        grid = self._grid
        return np.maximum(grid.get_line_res1()[3], grid.get_line_res2()[3]) * self._line_factor

    def _trafo_loading(self) -> np.ndarray:
        grid = self._grid
        return np.maximum(grid.get_trafo_res1()[3] * self._hv_factor,
                          grid.get_trafo_res2()[3] * self._lv_factor)

    def solve(self, p_actuator_w, q_actuator_var=None) -> GridSample:
        """Solve the power flow with the actuators at ``p_actuator_w`` (W, construction order)
        and, if given, ``q_actuator_var`` (var, same order; None: each keeps the reactive
        power it was last given, at first its study-case value).

        Starts from the last converged solution (the study case's at first); if Newton-Raphson
        fails from there it tries once more from the study case's solution.
        """
        p = self._powers(p_actuator_w, "active powers in W")
        grid = self._grid
        for sgen, p_w in zip(self._act, p.tolist()):
            grid.change_p_sgen(sgen, p_w * 1e-6)
        if q_actuator_var is not None:
            q = self._powers(q_actuator_var, "reactive powers in var")
            for sgen, q_var in zip(self._act, q.tolist()):
                grid.change_q_sgen(sgen, q_var * 1e-6)
        v = grid.ac_pf(self._v, self._max_iter, self._tol)
        if v.size == 0:
            v = grid.ac_pf(self.data.v_init, self._max_iter, self._tol)
        iterations = int(grid.get_algo().get_nb_iter())
        if v.size == 0:
            return _not_converged(iterations)
        self._v = np.array(v, dtype=complex)
        return self._sample(iterations)

    def set_injections(self, injections: dict) -> None:
        """Move the rest of the grid to another operating point: ``injections`` maps a kind
        (``sgen_p``, ``load_p``, ``load_q``, ``shunt_p``, ``shunt_q``, ``storage_p``,
        ``gen_p``; :meth:`adnmesh.grid.profiles.YearProfiles.injections`) to one value per
        element of that kind in the model's order, MW or Mvar. The actuators' own sgens take
        the value too, until :meth:`solve` gives them theirs. The next :meth:`solve` solves
        with them, from the last solution."""
        setters = self._setters
        for kind, values in injections.items():
            change = setters.get(kind)
            if change is None:
                raise GridError(f"grid solver: no injection kind {kind!r} (one of "
                                f"{', '.join(setters)})")
            numbers = np.asarray(values, dtype=float).tolist()
            deque(map(change, range(len(numbers)), numbers), maxlen=0)   # no Python loop

    def _powers(self, values, what: str) -> np.ndarray:
        out = np.asarray(values, dtype=float)
        if out.shape != (self.n_actuators,) or not np.isfinite(out).all():
            raise GridError(f"grid solver: expected {self.n_actuators} finite actuator {what}, "
                            f"got {values!r}")
        return out

    def _sample(self, iterations: int) -> GridSample:
        """The last solve as a :class:`GridSample`: each extreme by one ``argmin``/``argmax``
        (the measurement takes one at every sample: a NaN is the maximum, as ``max()``)."""
        grid, d = self._grid, self.data
        p_gen, q_gen, _ = grid.get_gen_res()
        vm = self.bus_vm_pu()
        with np.errstate(invalid="ignore", over="ignore"):
            line, trafo = self._line_loading(), self._trafo_loading()
        low, high = int(vm.argmin()), int(vm.argmax())
        line_max, line_at = _extreme(line, d.line_names)
        trafo_max, trafo_at = _extreme(trafo, d.trafo_names)
        return GridSample(p_ip_w=float(-p_gen[d.slack_gen] * 1e6),
                          q_ip_var=float(-q_gen[d.slack_gen] * 1e6),
                          vm_min_pu=float(vm[low]), vm_max_pu=float(vm[high]),
                          line_loading_max_pct=line_max, trafo_loading_max_pct=trafo_max,
                          converged=True, iterations=iterations,
                          vm_min_at=self._bus_names[low], vm_max_at=self._bus_names[high],
                          line_max_at=line_at, trafo_max_at=trafo_at)


def _without_slack(report_bus: np.ndarray, grid, slack_gen: int) -> np.ndarray:
    """Which entries of ``report_bus`` are reported: all but the slack's (all of them if the
    slack's is the only one); a boolean mask."""
    slack_bus = grid.get_generators()[slack_gen].bus_id
    keep = report_bus != slack_bus
    return keep if keep.any() else np.ones(report_bus.shape, dtype=bool)


def _extreme(values: np.ndarray, names) -> tuple[float, str]:
    """The largest of ``values`` (NaN if one is NaN, as ``max()``) and its name; NaN and ""
    if there are none."""
    if not values.size:
        return math.nan, ""
    at = int(values.argmax())
    return float(values[at]), names[at]


def _not_converged(iterations: int) -> GridSample:
    nan = math.nan
    return GridSample(nan, nan, nan, nan, nan, nan, converged=False, iterations=int(iterations))
