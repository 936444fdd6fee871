"""What the fast power-flow solver needs of a grid: a lightsim2grid model and a few arrays.

:class:`GridData` is the grid at one study case: a lightsim2grid ``LSGrid`` (the template every
:class:`~adnmesh.grid.solver.GridSolver` copies), the study case's solved bus voltages (the first
start of Newton-Raphson), every static generator's name and power, the ratings that turn
the model's branch currents into pandapower's loading percentages, the names of the reported
buses, lines and transformers, and each transformer's ratio tap changer (positions, % per
step). It is built from a pandapower net by :func:`adnmesh.grid.from_net.build_grid_data`, and
stored by :mod:`adnmesh.grid.cache` as the model's own binary file (``LSGrid.save_binary``)
plus a ``.npz`` of the arrays (:func:`to_arrays`, :func:`from_arrays`; names and tap sides in
its JSON ``meta``): no pickle, and neither pandapower nor simbench is needed to read it back.

Units: MW and Mvar (the model's), kA, kV, MVA; bus voltages in p.u.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields

import numpy as np

__all__ = ["GridData", "TAP_SIDES", "to_arrays", "from_arrays"]

_META = ("code", "case", "load_model", "converter", "sgen_names", "sgen_types", "slack_gen",
         "bus_names", "line_names", "trafo_names", "tap_side")
TAP_SIDES = ("hv", "lv", "none")
_MODEL = ("lsgrid",)


@dataclass(frozen=True, eq=False)
class GridData:
    """One grid at one study case, ready for :class:`adnmesh.grid.solver.GridSolver`.

    Attributes
    ----------
    code, case, load_model : str
        SimBench code (or another name of the grid), study case, load model (``"impedance"``:
        loads are constant impedances, ``"power"``: constant power).
    converter : str
        The ``pp_orig_file`` formula of lightsim2grid's pandapower converter that reproduced
        pandapower's ``runpp`` (see :mod:`adnmesh.grid.from_net`).
    lsgrid : lightsim2grid.network.LSGrid
        The model at the study case; a solver works on its own copy.
    v_init : ndarray of complex
        Bus voltages of the study case's solution, in the model's bus order, p.u.
    sgen_names : tuple of str
        Names of the static generators, in pandapower's (and the model's) order.
    sgen_types : tuple of str
        Their ``type`` in the net (SimBench's ``Wind_MV``, ``Biomass_MV``, ...; "" if none).
    sgen_rating_mw : ndarray of float
        Their rating, the net's ``sn_mva`` (SimBench: the installed power), MW; NaN where the
        net gives none.
    sgen_p_mw, sgen_q_mvar : ndarray of float
        Each static generator's power at the study case (scaling applied), MW and Mvar.
    slack_gen : int
        The model's generator that stands for the external grid (the slack).
    report_bus : ndarray of int
        Model bus of each in-service bus of the pandapower net (auxiliary buses of open
        switches excluded; buses coupled by closed switches, or carrying an external grid, map
        to the bus they were joined into): voltage extremes are taken over these but the
        slack's, as in pandapower's ``res_bus``.
    line_i_max_ka : ndarray of float
        ``max_i_ka · df · parallel`` of every line, kA.
    trafo_vn_hv_kv, trafo_vn_lv_kv, trafo_rating_mva : ndarray of float
        Rated voltages and ``sn_mva · parallel · df`` of every transformer, kV and MVA. A side
        the model moved onto another external grid's bus (:mod:`adnmesh.grid.from_net`) has
        its rated voltage times the new bus's nominal voltage over the old's: the model's
        current there is in the new bus's base, and the product stays pandapower's loading.
    bus_names : tuple of str
        Name of each entry of ``report_bus``: the pandapower bus's ``name``, else
        ``"bus <index>"`` (its index in the net).
    line_names, trafo_names : tuple of str
        Name of every line and transformer, in the model's (the net's table) order: its
        ``name``, else ``"line <index>"`` / ``"trafo <index>"``.
    tap_side : tuple of str
        Side of each transformer's ratio tap changer: ``"hv"``, ``"lv"``, or ``"none"`` where
        the net gives none the solver can move (no side, step, range or neutral, or a step in
        degrees: a phase shifter).
    tap_neutral, tap_min, tap_max : ndarray of float
        Neutral, lowest and highest tap position (NaN where ``tap_side`` is ``"none"``).
    tap_step_percent : ndarray of float
        Voltage change per tap step, % of the rated voltage of the tap's side (NaN where none).
    tap_pos : ndarray of float
        The tap position the model is at: the net's ``tap_pos`` where ``runpp`` applies it,
        the neutral where it does not (no ``tap_changer_type``, :mod:`adnmesh.grid.model_net`);
        NaN where none.
    """

    code: str
    case: str
    load_model: str
    converter: str
    lsgrid: object
    v_init: np.ndarray
    sgen_names: tuple[str, ...]
    sgen_types: tuple[str, ...]
    sgen_rating_mw: np.ndarray
    sgen_p_mw: np.ndarray
    sgen_q_mvar: np.ndarray
    slack_gen: int
    report_bus: np.ndarray
    line_i_max_ka: np.ndarray
    trafo_vn_hv_kv: np.ndarray
    trafo_vn_lv_kv: np.ndarray
    trafo_rating_mva: np.ndarray
    bus_names: tuple[str, ...]
    line_names: tuple[str, ...]
    trafo_names: tuple[str, ...]
    tap_side: tuple[str, ...]
    tap_neutral: np.ndarray
    tap_min: np.ndarray
    tap_max: np.ndarray
    tap_step_percent: np.ndarray
    tap_pos: np.ndarray

    def sgen_index(self, names) -> np.ndarray:
        """Positions of the named static generators; :class:`GridError` for an unknown or
        repeated name."""
        from adnmesh.errors import GridError
        position = {n: i for i, n in enumerate(self.sgen_names)}
        names = list(names)
        for name in names:
            if name not in position:
                import difflib
                close = difflib.get_close_matches(name, list(position), n=3, cutoff=0.5)
                hint = (f"closest: {', '.join(repr(c) for c in close)}" if close else
                        f"e.g. {self.sgen_names[0]!r}")
                raise GridError(f"grid {self.code}: no static generator named {name!r} "
                                f"({len(self.sgen_names)} sgens; {hint})")
        if len(set(names)) != len(names):
            raise GridError(f"grid {self.code}: a static generator is named twice in {names}")
        return np.array([position[n] for n in names], dtype=np.int64)


def to_arrays(data: GridData) -> dict[str, np.ndarray]:
    """The arrays of ``data`` (everything but the model) as a flat dict for ``np.savez``."""
    out: dict[str, np.ndarray] = {}
    meta = {}
    for f in fields(GridData):
        value = getattr(data, f.name)
        if f.name in _META:
            meta[f.name] = list(value) if isinstance(value, tuple) else value
        elif f.name not in _MODEL:
            out[f.name] = np.asarray(value)
    out["meta"] = np.array(json.dumps(meta, sort_keys=True))
    return out


def from_arrays(arrays, lsgrid) -> GridData:
    """Inverse of :func:`to_arrays`, with the model ``lsgrid`` (read separately).

    Raises ``KeyError`` or ``ValueError`` if something is missing or does not fit the model.
    """
    meta = json.loads(str(arrays["meta"]))
    kwargs = {"lsgrid": lsgrid}
    for f in fields(GridData):
        if f.name in _META:
            value = meta[f.name]
            kwargs[f.name] = tuple(value) if isinstance(value, list) else value
        elif f.name not in _MODEL:
            kwargs[f.name] = np.array(arrays[f.name])
    kwargs["slack_gen"] = int(kwargs["slack_gen"])
    data = GridData(**kwargs)
    _check_shapes(data)
    return data


def _check_shapes(data: GridData) -> None:
    """``ValueError`` unless the arrays fit the model (a damaged cache file, say)."""
    grid = data.lsgrid
    n_bus = grid.total_bus()
    n_line, n_trafo = len(grid.get_line_res1()[0]), len(grid.get_trafo_res1()[0])
    taps = (data.tap_neutral, data.tap_min, data.tap_max, data.tap_step_percent, data.tap_pos)
    ok = (data.v_init.shape == (n_bus,)
          and len(data.sgen_names) == len(data.sgen_p_mw) == len(data.sgen_q_mvar)
          == len(data.sgen_types) == len(data.sgen_rating_mw)
          == len(grid.get_sgens_res()[0])
          and data.line_i_max_ka.shape == (n_line,)
          and data.trafo_vn_hv_kv.shape == data.trafo_vn_lv_kv.shape
          == data.trafo_rating_mva.shape == (n_trafo,)
          and data.report_bus.ndim == 1 and len(data.bus_names) == data.report_bus.shape[0]
          and len(data.line_names) == n_line and len(data.trafo_names) == n_trafo
          and len(data.tap_side) == n_trafo and set(data.tap_side) <= set(TAP_SIDES)
          and all(a.shape == (n_trafo,) and a.dtype == float for a in taps)
          and _taps_consistent(data)
          and 0 <= data.slack_gen < len(grid.get_gen_res()[0])
          and bool(np.all((data.report_bus >= 0) & (data.report_bus < n_bus))))
    if not ok:
        raise ValueError("grid data arrays do not fit the grid model")


def _taps_consistent(data: GridData) -> bool:
    """Every tap changer complete (finite, ``tap_min <= tap_max``), every "none" all NaN."""
    has = np.array([side != "none" for side in data.tap_side], dtype=bool)
    values = np.vstack([data.tap_neutral, data.tap_min, data.tap_max, data.tap_step_percent,
                        data.tap_pos]) if has.size else np.zeros((5, 0))
    finite = np.isfinite(values)
    return bool(np.all(finite[:, has]) and not np.any(finite[:, ~has])
                and np.all(data.tap_min[has] <= data.tap_max[has]))
