"""Disk cache of :class:`~adnmesh.grid.data.GridData`: a second start without simbench.

Loading a SimBench grid and solving it with pandapower takes tens of seconds (importing the two
alone several); reading the model and its arrays back takes milliseconds (plus about a second
to import lightsim2grid). :func:`load_grid` returns the
data of (code, study case, load model), from the cache when a valid file is there, else built
with simbench and pandapower and then written to the cache.

- **Where**: the folder ``$ADNMESH_CACHE_DIR``, else ``$XDG_CACHE_HOME/adnmesh``, else
  ``~/.cache/adnmesh`` (:func:`default_cache_dir`); a ``cache_dir`` argument overrides it.
- **Key**: grid code, study case, load model, the installed versions of simbench, pandapower and
  lightsim2grid, and :data:`FORMAT_VERSION` (:func:`cache_key`). The file name carries a hash of
  the key and the file holds the key itself, which is compared on reading.
- **Format**: the grid model in lightsim2grid's own binary format (``LSGrid.save_binary``, which
  checks what it reads: a truncated or damaged file is an error, not garbage) and a ``.npz`` of
  plain arrays (:func:`adnmesh.grid.data.to_arrays`) read with ``allow_pickle=False``, which
  holds the key, the model file's sha256 and ``digest``: the sha256 of every other entry of the
  ``.npz`` (name, dtype, shape and bytes, :func:`arrays_digest`). So every byte the cache loads
  is covered: the model by its hash, the arrays (line ratings, voltages, names, ...) and the
  key and model hash themselves by the digest. No pickle anywhere: nothing in the cache runs
  code. The hashes detect damage and edits, not an adversary who recomputes them: the cache
  folder is the user's own (files written with mode 0600).
- **Robustness**: each file is written to a temporary file and renamed into place (readers see
  an old file or a new one, never half of one), the model first, the arrays last; a pair that
  cannot be read, whose key differs, whose arrays do not match their digest (an entry changed,
  added or removed) or whose model is not the one the arrays name is rebuilt with a one-line
  warning; a folder that cannot be written is a warning, not an error.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import warnings
from collections.abc import Callable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

from adnmesh.files import write_atomic
from adnmesh.grid.data import GridData, from_arrays, to_arrays

__all__ = ["FORMAT_VERSION", "warn_cache", "default_cache_dir", "cache_key", "net_cache_key",
           "cache_path", "is_cached", "read_or_build", "model_path", "arrays_digest", "cached", "load_grid", "load_net_grid"]

FORMAT_VERSION = 6          # 6: names of buses, lines, trafos and the trafos' tap changers;
                            # 5: switches, taps, several ext grids; 4: sgen types and ratings;
                            # 3: the arrays digest (older files are not read, nor removed)

_DIGEST = "digest"


def default_cache_dir() -> Path:
    """``$ADNMESH_CACHE_DIR``, else ``$XDG_CACHE_HOME/adnmesh``, else ``~/.cache/adnmesh``."""
    explicit = os.environ.get("ADNMESH_CACHE_DIR")
    if explicit:
        return Path(explicit)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "adnmesh"


def _version(package: str) -> str:
    try:
        return version(package)
    except PackageNotFoundError:
        return "none"


def cache_key(code: str, case: str, load_model: str) -> dict:
    """What the cached data depends on (a JSON-able dict)."""
    return {"format": FORMAT_VERSION, "code": code, "case": case, "load_model": load_model,
            "simbench": _version("simbench"), "pandapower": _version("pandapower"),
            "lightsim2grid": _version("lightsim2grid")}


def net_cache_key(path, case: str | None, load_model: str) -> dict:
    """What the cached data of a pandapower net file depends on: its content's sha256 (not its
    name), the study case asked for (None: as saved) and the load model, with the versions."""
    from adnmesh.grid.net_file import net_sha256

    key = cache_key(f"net-{Path(path).stem}", case or "as-saved", load_model)
    key["net_sha256"] = net_sha256(path)
    return key


def cache_path(key: dict, directory: Path) -> Path:
    """The cache file of ``key`` in ``directory``: readable name plus a hash of the key."""
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", f"{key['code']}-{key['case']}-{key['load_model']}")
    return Path(directory) / f"grid-{stem}-{digest}.npz"


def is_cached(code: str, case: str, load_model: str, cache_dir=None) -> bool:
    """Whether :func:`load_grid` finds a cache file for these arguments (it may still rebuild
    one it finds damaged); tells a caller whether to announce a build of tens of seconds."""
    directory = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    return cache_path(cache_key(code, case, load_model), directory).exists()


def cached(key: dict, build: Callable[[], GridData], directory=None) -> GridData:
    """The data of ``key`` from the cache in ``directory``, else ``build()`` and store it."""
    path = cache_path(key, Path(directory) if directory is not None else default_cache_dir())
    return read_or_build(path, lambda: _read(path, key), build,
                         lambda data: _write(path, key, data), "grid cache")


def read_or_build(path: Path, read: Callable[[], object], build: Callable[[], object],
                  write: Callable[[object], None], what: str):
    """``read()`` if ``path`` exists and reads; else ``build()``, then ``write()`` it. Any
    damage to the file is a one-line warning and a rebuild, a file that cannot be written a
    warning: the cache never stops the caller."""
    if path.exists():
        try:
            return read()
        except Exception as exc:          # any damage to the file: rebuild, never crash
            warn_cache(f"{what} {path} is unreadable or modified "
                       f"({type(exc).__name__}: {exc}); rebuilding it")
    data = build()
    try:
        write(data)
    except OSError as exc:
        warn_cache(f"{what} {path} could not be written ({exc}); continuing without it")
    return data


def warn_cache(message: str) -> None:
    """A ``RuntimeWarning`` that prints as one line (``adnmesh:0: RuntimeWarning: ...``): no
    source line under it, whoever called."""
    warnings.warn_explicit(message, RuntimeWarning, filename="adnmesh", lineno=0,
                           module="adnmesh.grid.cache")


def load_grid(code: str, case: str = "lW", load_model: str = "impedance",
              cache_dir=None) -> GridData:
    """The solver's data of SimBench grid ``code`` at study ``case`` (cached; module doc).

    Parameters
    ----------
    code : str
        SimBench code, e.g. ``"1-MV-rural--0-no_sw"``.
    case : str
        Study case of the grid's own ``loadcases`` table (default ``"lW"``).
    load_model : str
        ``"impedance"`` (constant impedance, docs/method.md#reference-case) or ``"power"``
        (constant power).
    cache_dir : path, optional
        Cache folder (default :func:`default_cache_dir`).
    """
    def build() -> GridData:
        from adnmesh.grid.from_net import build_grid_data
        from adnmesh.grid.simbench_net import grid_net
        return build_grid_data(grid_net(code, case, load_model), code, case, load_model)

    from adnmesh.grid.simbench_net import LOAD_MODELS
    if load_model not in LOAD_MODELS:
        from adnmesh.errors import GridError
        raise GridError(f"grid: load model must be one of {', '.join(LOAD_MODELS)}, "
                        f"got {load_model!r}")
    return cached(cache_key(code, case, load_model), build, cache_dir)


def load_net_grid(path, case: str | None = None, load_model: str = "impedance",
                  cache_dir=None) -> GridData:
    """The solver's data of a pandapower net file (:mod:`adnmesh.grid.net_file`) at study
    ``case`` (None: as saved, for a net without study cases), cached by the file's content.

    Raises
    ------
    GridError
        The file cannot be read or is no pandapower net, the case is not the net's, the net
        has elements the solver does not model, or its power flow does not converge.
    """
    from adnmesh.errors import GridError

    def build() -> GridData:
        import pandapower as pp

        from adnmesh.grid.from_net import build_grid_data
        from adnmesh.grid.net_file import net_at_case, read_net
        net, _ = read_net(path)
        used = net_at_case(net, case, load_model)
        try:
            return build_grid_data(net, f"net {Path(path).name}", used, load_model)
        except pp.LoadflowNotConverged:
            raise GridError(f"grid: {path}: the power flow of the net at its operating point "
                            f"({used}) does not converge") from None

    from adnmesh.grid.simbench_net import LOAD_MODELS
    if load_model not in LOAD_MODELS:
        raise GridError(f"grid: load model must be one of {', '.join(LOAD_MODELS)}, "
                        f"got {load_model!r}")
    return cached(net_cache_key(path, case, load_model), build, cache_dir)


def model_path(path: Path) -> Path:
    """The grid model's file beside the arrays' ``.npz``."""
    return path.with_suffix(".lsgrid")


def _read(path: Path, key: dict) -> GridData:
    from lightsim2grid.lightsim2grid_cpp import LSGrid      # not .network: it imports pandapower

    with np.load(path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    if _DIGEST not in arrays:
        raise ValueError("the arrays carry no digest")
    if arrays_digest({n: a for n, a in arrays.items() if n != _DIGEST}) != str(arrays[_DIGEST]):
        raise ValueError("the arrays do not match their digest (modified or damaged)")
    stored = json.loads(str(arrays["cache_key"]))
    if stored != key:
        raise ValueError(f"stored key {stored} is not {key}")
    model = model_path(path)
    if _sha256(model) != str(arrays["model_sha256"]):
        raise ValueError(f"{model.name} is not the model the arrays were written with")
    return from_arrays(arrays, LSGrid.load_binary(str(model)))


def arrays_digest(arrays: dict[str, np.ndarray]) -> str:
    """sha256 over every array of ``arrays``: its name, dtype, shape and bytes, by name."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        head = json.dumps([name, a.dtype.str, list(a.shape)]).encode()
        h.update(len(head).to_bytes(8, "little") + head)
        body = a.tobytes()
        h.update(len(body).to_bytes(8, "little") + body)
    return h.hexdigest()


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _write(path: Path, key: dict, data: GridData) -> None:
    """The model (lightsim2grid's own atomic binary file), then the arrays with its hash."""
    path.parent.mkdir(parents=True, exist_ok=True)
    model = model_path(path)
    data.lsgrid.save_binary(str(model), True)
    arrays = to_arrays(data)
    arrays["cache_key"] = np.array(json.dumps(key, sort_keys=True))
    arrays["model_sha256"] = np.array(_sha256(model))
    arrays = {name: np.asarray(a) for name, a in arrays.items()}
    arrays[_DIGEST] = np.array(arrays_digest(arrays))
    write_atomic(path, lambda fh: np.savez(fh, **arrays), mode=0o600)
