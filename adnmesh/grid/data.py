"""What the fast power-flow solver needs of a grid, as plain arrays.

:class:`GridData` is the grid at one study case in pandapower's own internal (per-unit, "ppci")
form: the bus admittance matrix ``Ybus`` and the branch matrices ``Yf``, ``Yt`` exactly as
pandapower builds them (open line switches as auxiliary buses, transformer model, phase shift,
shunts), the injections that do not change, every static generator's bus and power, and the
factors that turn branch currents into pandapower's loading percentages. It holds numbers only,
so it is written to and read from a ``.npz`` file without pickle (:func:`to_arrays`,
:func:`from_arrays`) and building a solver from it needs neither pandapower nor simbench.

Units: per unit on ``base_mva`` for admittances and injections (``s_fixed_pu``), MW and Mvar
for the generators' powers, % for loadings.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields

import numpy as np
import scipy.sparse as sp

__all__ = ["GridData", "to_arrays", "from_arrays"]

_SPARSE = ("ybus", "yf", "yt")
_META = ("code", "case", "load_model", "base_mva", "line_rows", "trafo_rows", "sgen_names")


@dataclass(frozen=True, eq=False)
class GridData:
    """One grid at one study case, ready for :class:`adnmesh.grid.solver.GridSolver`.

    Attributes
    ----------
    code, case, load_model : str
        SimBench code (or another name of the grid), study case, load model (``"impedance"``:
        loads are constant impedances, ``"power"``: constant power).
    base_mva : float
        Per-unit base power, MVA.
    ybus, yf, yt : scipy.sparse.csr_matrix
        Bus admittance matrix (n_bus × n_bus) and branch from/to-end admittance matrices
        (n_branch × n_bus), p.u.; constant-impedance loads are shunts in ``ybus``.
    v_init : ndarray of complex
        Bus voltages of the study case's solution, p.u. (the solver's first start).
    ref, pv, pq : ndarray of int
        Slack bus (one), PV buses (none in a SimBench MV grid), PQ buses.
    s_fixed_pu : ndarray of complex
        Injection at every bus from everything but the static generators (constant-power loads,
        negative), p.u.
    sgen_names : tuple of str
        Names of the static generators, in pandapower's order.
    sgen_bus : ndarray of int
        Bus (internal index) of each static generator.
    sgen_p_mw, sgen_q_mvar : ndarray of float
        Each static generator's power at the study case (scaling applied), MW and Mvar.
    report_bus : ndarray of int
        Internal index of each bus of the pandapower net (auxiliary buses excluded): the buses
        over which voltage extremes are taken, as in pandapower's ``res_bus``.
    branch_from, branch_to : ndarray of int
        From (HV) and to (LV) bus of every branch (row of ``yf`` and ``yt``).
    line_rows, trafo_rows : tuple of (int, int)
        Branch rows ``[start, stop)`` of the lines and of the transformers.
    loading_f, loading_t : ndarray of float
        Loading in % per p.u. of current at the from (HV) and to (LV) end of every branch:
        pandapower's ``loading_percent`` is ``max(|I_f| loading_f, |I_t| loading_t)``.
    """

    code: str
    case: str
    load_model: str
    base_mva: float
    ybus: sp.csr_matrix
    yf: sp.csr_matrix
    yt: sp.csr_matrix
    v_init: np.ndarray
    ref: np.ndarray
    pv: np.ndarray
    pq: np.ndarray
    s_fixed_pu: np.ndarray
    sgen_names: tuple[str, ...]
    sgen_bus: np.ndarray
    sgen_p_mw: np.ndarray
    sgen_q_mvar: np.ndarray
    report_bus: np.ndarray
    branch_from: np.ndarray
    branch_to: np.ndarray
    line_rows: tuple[int, int]
    trafo_rows: tuple[int, int]
    loading_f: np.ndarray
    loading_t: np.ndarray

    @property
    def n_bus(self) -> int:
        """Number of internal buses (auxiliary buses included)."""
        return self.ybus.shape[0]

    def sgen_index(self, names) -> np.ndarray:
        """Positions of the named static generators; :class:`GridError` for an unknown or
        repeated name."""
        from adnmesh.grid.errors import GridError
        position = {n: i for i, n in enumerate(self.sgen_names)}
        names = list(names)
        for name in names:
            if name not in position:
                raise GridError(f"grid {self.code}: no static generator named {name!r} "
                                f"({len(self.sgen_names)} sgens, e.g. {self.sgen_names[0]!r})")
        if len(set(names)) != len(names):
            raise GridError(f"grid {self.code}: a static generator is named twice in {names}")
        return np.array([position[n] for n in names], dtype=np.int64)


def to_arrays(data: GridData) -> dict[str, np.ndarray]:
    """``data`` as a flat dict of numpy arrays (no object arrays: safe for ``np.savez``)."""
    out: dict[str, np.ndarray] = {}
    meta = {}
    for f in fields(GridData):
        value = getattr(data, f.name)
        if f.name in _SPARSE:
            m = sp.csr_matrix(value)
            out[f"{f.name}.data"] = m.data
            out[f"{f.name}.indices"] = m.indices
            out[f"{f.name}.indptr"] = m.indptr
            out[f"{f.name}.shape"] = np.asarray(m.shape, dtype=np.int64)
        elif f.name in _META:
            meta[f.name] = list(value) if isinstance(value, tuple) else value
        else:
            out[f.name] = np.asarray(value)
    out["meta"] = np.array(json.dumps(meta, sort_keys=True))
    return out


def from_arrays(arrays) -> GridData:
    """Inverse of :func:`to_arrays` (``arrays``: a mapping such as an opened ``.npz``).

    Raises ``KeyError`` or ``ValueError`` if something is missing or malformed.
    """
    meta = json.loads(str(arrays["meta"]))
    kwargs = {}
    for f in fields(GridData):
        if f.name in _SPARSE:
            shape = tuple(int(x) for x in arrays[f"{f.name}.shape"])
            kwargs[f.name] = sp.csr_matrix((arrays[f"{f.name}.data"],
                                            arrays[f"{f.name}.indices"],
                                            arrays[f"{f.name}.indptr"]), shape=shape)
        elif f.name in _META:
            value = meta[f.name]
            kwargs[f.name] = tuple(value) if isinstance(value, list) else value
        else:
            kwargs[f.name] = np.array(arrays[f.name])
    kwargs["line_rows"] = tuple(int(x) for x in kwargs["line_rows"])
    kwargs["trafo_rows"] = tuple(int(x) for x in kwargs["trafo_rows"])
    kwargs["base_mva"] = float(kwargs["base_mva"])
    data = GridData(**kwargs)
    _check_shapes(data)
    return data


def _check_shapes(data: GridData) -> None:
    """``ValueError`` unless the arrays fit together (a damaged cache file, say)."""
    n, m = data.n_bus, data.yf.shape[0]
    ok = (data.ybus.shape == (n, n) and data.yf.shape == data.yt.shape == (m, n)
          and data.v_init.shape == data.s_fixed_pu.shape == (n,)
          and len(data.sgen_names) == len(data.sgen_bus) == len(data.sgen_p_mw)
          == len(data.sgen_q_mvar)
          and data.loading_f.shape == data.loading_t.shape == (m,)
          and data.branch_from.shape == data.branch_to.shape == (m,)
          and data.ref.size == 1 and 0 <= data.line_rows[0] <= data.line_rows[1] <= m
          and 0 <= data.trafo_rows[0] <= data.trafo_rows[1] <= m)
    for idx in (data.ref, data.pv, data.pq, data.sgen_bus, data.report_bus, data.branch_from,
                data.branch_to):
        ok = ok and bool(np.all((idx >= 0) & (idx < n)))
    if not ok:
        raise ValueError("grid data arrays do not fit together")
