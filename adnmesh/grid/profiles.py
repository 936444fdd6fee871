"""A year of a grid's operating points: every injection of the solver's model per interval.

:class:`YearProfiles` holds, for each interval of a net's profiles (SimBench: 35,136 quarter
hours of 2016), the active power of every static generator and the active and reactive power
of every load, in the solver's model order (:class:`~adnmesh.grid.data.GridData`), ready for
:meth:`adnmesh.grid.solver.GridSolver.set_injections`. With the ``impedance`` load model the
loads are the model's shunts (:func:`adnmesh.grid.simbench_net.loads_as_impedances`: the net's
own shunts first, constant, then one per in-service load); with ``power`` they are its loads.
Values are simbench's ``get_absolute_values(net, profiles_instead_of_study_cases=True)`` times
each element's ``scaling`` (0 for an element out of service), what
:func:`adnmesh.grid.simbench_net.apply_time_step` puts into the net; static generators keep
their saved reactive power (the profiles have none), storages and generators with profiles
take their active power per interval.

:func:`load_profiles` builds them with simbench (seconds: the net's download and parse) and
keeps them in the grid cache folder (:mod:`adnmesh.grid.cache`) as one ``.npz`` whose arrays
carry a digest (no pickle); a damaged file is rebuilt with a one-line warning.

Units: MW and Mvar (the model's); times as ``numpy.datetime64`` minutes.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from adnmesh.errors import GridError
from adnmesh.files import write_atomic
from adnmesh.grid.cache import arrays_digest, cache_key, default_cache_dir, read_or_build

__all__ = ["YearProfiles", "load_profiles", "profiles_of_net", "profiles_of_table",
           "PROFILE_FORMAT"]

PROFILE_FORMAT = 3
_KINDS = ("sgen_p", "load_p", "load_q", "shunt_p", "shunt_q", "storage_p", "gen_p")


@dataclass(frozen=True, eq=False)
class YearProfiles:
    """Every injection of a grid's model per interval (see the module docstring).

    Attributes
    ----------
    times : ndarray of datetime64[m], shape (T,)
        Start of each interval.
    step_s : float
        Length of an interval, s (900 for SimBench's quarter hours).
    sgen_p : ndarray, shape (T, n_sgen)
        Static generators' active power, MW, model order (``GridData.sgen_names``).
    load_p, load_q : ndarray, shape (T, n_load), or None
        The model's loads (constant power), MW and Mvar; None with the impedance model.
    shunt_p, shunt_q : ndarray, shape (T, n_shunt), or None
        The model's shunts at 1 p.u. (the loads as constant impedances), MW and Mvar; None
        with the power model.
    storage_p, gen_p : ndarray, shape (T, n), or None
        Storages' and (non-slack) generators' active power where the profiles give them, MW.
    """

    times: np.ndarray
    step_s: float
    sgen_p: np.ndarray
    load_p: np.ndarray | None = None
    load_q: np.ndarray | None = None
    shunt_p: np.ndarray | None = None
    shunt_q: np.ndarray | None = None
    storage_p: np.ndarray | None = None
    gen_p: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.times.shape[0])

    def injections(self, k: int) -> dict[str, np.ndarray]:
        """The injections of interval ``k``: ``{"sgen_p": ..., "shunt_p": ..., ...}`` (the
        kinds this grid has), for :meth:`~adnmesh.grid.solver.GridSolver.set_injections`."""
        return {kind: getattr(self, kind)[k] for kind in _KINDS
                if getattr(self, kind) is not None}

    def window(self, start: int, stop: int) -> "YearProfiles":
        """Intervals ``start`` to ``stop - 1``."""
        cut = {kind: (None if getattr(self, kind) is None else getattr(self, kind)[start:stop])
               for kind in _KINDS}
        return YearProfiles(self.times[start:stop], self.step_s, **cut)


def _times(text) -> np.ndarray:
    """SimBench's ``"dd.mm.yyyy HH:MM"`` as datetime64[m]."""
    out = np.empty(len(text), dtype="datetime64[m]")
    for i, t in enumerate(text):
        m = re.fullmatch(r"(\d{2})\.(\d{2})\.(\d{4}) (\d{2}):(\d{2})", str(t).strip())
        if m is None:
            raise GridError(f"grid profiles: time {t!r} is not 'dd.mm.yyyy HH:MM'")
        day, month, year, hour, minute = m.groups()
        out[i] = np.datetime64(f"{year}-{month}-{day}T{hour}:{minute}")
    return out


def profiles_of_net(net, load_model: str) -> YearProfiles:
    """The :class:`YearProfiles` of a SimBench-style ``net`` (with ``net.profiles``) for the
    model :func:`adnmesh.grid.simbench_net.grid_net` makes of it with ``load_model``."""
    import simbench

    from adnmesh.grid.simbench_net import time_steps

    count = time_steps(net)
    if not count:
        raise GridError("grid: the net has no profiles (SimBench nets have a year of quarter "
                        "hours)")
    values = simbench.get_absolute_values(net, profiles_instead_of_study_cases=True)
    series = {}
    for (element, column), frame in values.items():
        if frame.shape[1] and len(net[element]):
            series[(element, column)] = frame.reindex(columns=net[element].index).to_numpy(
                dtype=float)
    times = _times(net.profiles["load"]["time"].to_numpy())
    return _assemble(net, times, series, load_model)


def profiles_of_table(net, times: np.ndarray, named: dict, load_model: str) -> YearProfiles:
    """The :class:`YearProfiles` of a user's time series (:func:`adnmesh.grid.profile_file.
    read_profile_table`: ``named[(table, column)][element name]``) for ``net`` at its
    operating point, loads not yet made impedances; an element without a series keeps its
    value there. :class:`GridError` for a name the net's table does not have or has twice."""
    series = {}
    for (element, column), by_name in named.items():
        table = net[element]
        names = table.name.astype(str).tolist() if "name" in table else []
        position = {}
        for i, name in enumerate(names):
            position.setdefault(name, []).append(i)
        matrix = np.broadcast_to(table[column].to_numpy(dtype=float),
                                 (times.size, len(table))).copy()
        for name, values in by_name.items():
            rows = position.get(name, [])
            if len(rows) != 1:
                what = "no" if not rows else "more than one"
                raise GridError(f"profiles: {element}.{column}:{name}: the net has {what} "
                                f"{element} named {name!r}")
            matrix[:, rows[0]] = values
        series[(element, column)] = matrix
    return _assemble(net, times, series, load_model)


def _assemble(net, times: np.ndarray, series: dict, load_model: str) -> YearProfiles:
    """Every injection of the model per interval from ``series[(table, column)]`` (one column
    per row of the net's table, values before scaling; tables without a series keep their
    values at the net's operating point)."""
    count = times.size

    def scaled(element: str, column: str) -> np.ndarray | None:
        table = net[element] if element in net else None
        if table is None or len(table) == 0 or column not in table:
            return None
        matrix = series.get((element, column))
        if matrix is None:
            matrix = np.broadcast_to(table[column].to_numpy(dtype=float), (count, len(table)))
        scaling = (table.scaling.fillna(1.0).to_numpy(dtype=float) if "scaling" in table
                   else np.ones(len(table)))
        if "in_service" in table:               # out of service: nothing (the model's off)
            scaling = scaling * table.in_service.fillna(False).to_numpy(dtype=bool)
        return np.ascontiguousarray(np.nan_to_num(matrix * scaling))

    sgen = scaled("sgen", "p_mw")
    out = {"sgen_p": np.zeros((count, 0)) if sgen is None else sgen,
           "storage_p": scaled("storage", "p_mw") if ("storage", "p_mw") in series else None,
           "gen_p": scaled("gen", "p_mw") if ("gen", "p_mw") in series else None}
    n_load = len(net.load)
    load_p = scaled("load", "p_mw")
    load_q = scaled("load", "q_mvar")
    load_p = np.zeros((count, n_load)) if load_p is None else load_p
    load_q = np.zeros((count, n_load)) if load_q is None else load_q
    if load_model == "impedance":
        on = net.load.in_service.to_numpy(dtype=bool)
        shunts = net.shunt
        fixed_p = np.broadcast_to(shunts.p_mw.to_numpy(dtype=float), (count, len(shunts)))
        fixed_q = np.broadcast_to(shunts.q_mvar.to_numpy(dtype=float), (count, len(shunts)))
        out["shunt_p"] = np.ascontiguousarray(np.hstack([fixed_p, load_p[:, on]]))
        out["shunt_q"] = np.ascontiguousarray(np.hstack([fixed_q, load_q[:, on]]))
    else:
        out["load_p"], out["load_q"] = load_p, load_q
    step = float((times[1] - times[0]) / np.timedelta64(1, "s")) if count > 1 else 900.0
    return YearProfiles(times=times, step_s=step, **out)


def _path(key: dict, directory: Path) -> Path:
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", f"{key['code']}-{key['load_model']}")
    return directory / f"profiles-{stem}-{digest}.npz"


def _key(code: str, load_model: str) -> dict:
    key = cache_key(code, "profiles", load_model)
    key["profiles_format"] = PROFILE_FORMAT
    return key


def load_profiles(code: str, load_model: str = "impedance", cache_dir=None) -> YearProfiles:
    """The year of SimBench grid ``code`` for the model of ``load_model`` (cached; see the
    module docstring). :class:`GridError` for a code that is no SimBench grid or has no
    profiles."""
    key = _key(code, load_model)
    path = _path(key, Path(cache_dir) if cache_dir is not None else default_cache_dir())

    def build() -> YearProfiles:
        from adnmesh.grid.simbench_net import load_simbench_net
        return profiles_of_net(load_simbench_net(code), load_model)
    return read_or_build(path, lambda: _read(path, key), build,
                         lambda profiles: _write(path, key, profiles), "profile cache")


def _write(path: Path, key: dict, profiles: YearProfiles) -> None:
    arrays = {kind: getattr(profiles, kind) for kind in _KINDS
              if getattr(profiles, kind) is not None}
    arrays["times"] = profiles.times.astype("datetime64[m]").astype(np.int64)
    arrays["step_s"] = np.array(profiles.step_s)
    arrays["cache_key"] = np.array(json.dumps(key, sort_keys=True))
    arrays["digest"] = np.array(arrays_digest(arrays))
    write_atomic(path, lambda fh: np.savez(fh, **arrays), mode=0o600)


def _read(path: Path, key: dict) -> YearProfiles:
    with np.load(path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    digest = str(arrays.pop("digest"))
    if arrays_digest(arrays) != digest:
        raise ValueError("the arrays do not match their digest (modified or damaged)")
    if json.loads(str(arrays["cache_key"])) != key:
        raise ValueError("another key")
    times = arrays["times"].astype("datetime64[m]")
    kinds = {kind: arrays[kind] for kind in _KINDS if kind in arrays}
    if any(a.ndim != 2 or a.shape[0] != times.shape[0] for a in kinds.values()):
        raise ValueError("arrays of another length than the times")
    return YearProfiles(times=times, step_s=float(arrays["step_s"]), **kinds)
