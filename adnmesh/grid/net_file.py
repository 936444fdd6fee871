"""A pandapower net file as a grid model's net (imports pandapower, and simbench for a net
with study cases).

:func:`read_net` reads at most :data:`MAX_NET_BYTES` of a regular file, as
``pandapower.to_json`` writes it (``pandapower.from_json_string``) or, named ``.sqlite``,
``.sqlite3`` or ``.db``, as ``pandapower.to_sqlite`` writes it (``pandapower.from_sqlite`` on a
private copy of the bytes read). It returns the net with the SHA-256 of the file's bytes, which
keys the grid cache. :func:`net_at_case` puts it at its operating point: a
net with a ``loadcases`` table (a SimBench net saved to a file keeps it) at one of its study
cases, as :func:`adnmesh.grid.simbench_net.apply_study_case` does; a net without one as saved.
Loads as constant impedances or as constant power, as for SimBench.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from adnmesh.errors import GridError
from adnmesh.files import read_regular, unreadable

__all__ = ["MAX_NET_BYTES", "SQLITE_SUFFIXES", "AS_SAVED", "read_net", "net_sha256", "net_at_case"]

#: the largest net file read, bytes
MAX_NET_BYTES = 256 * 2**20
#: file name suffixes read as ``pandapower.to_sqlite`` writes them (any other: JSON)
SQLITE_SUFFIXES = (".sqlite", ".sqlite3", ".db")
#: the study case of a net used as saved (it has no loadcases table)
AS_SAVED = "as saved"


def _read(path: Path) -> bytes:
    try:
        return read_regular(path, MAX_NET_BYTES)
    except OSError as exc:
        raise GridError(f"grid: {unreadable(path, exc, 'pandapower net file')}") from None


def net_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of the net file's bytes (:class:`GridError` if it cannot be read)."""
    return hashlib.sha256(_read(Path(path))).hexdigest()


def _from_sqlite(path: Path, data: bytes):
    """``pandapower.from_sqlite`` of the bytes read (a private copy: the file the hash was
    taken of, and sqlite3 never creates or changes the user's file)."""
    import tempfile

    import pandapower as pp

    if not data.startswith(b"SQLite format 3\x00"):
        raise ValueError("not an SQLite database")
    with tempfile.TemporaryDirectory(prefix="adnmesh-net-") as folder:
        copy = Path(folder) / "net.sqlite"
        copy.write_bytes(data)
        return pp.from_sqlite(str(copy))


def read_net(path: str | Path):
    """``(net, sha256)`` of a pandapower net file (:class:`GridError`, one line, for a file
    that cannot be read or is not a pandapower net)."""
    import pandapower as pp

    path = Path(path)
    data = _read(path)
    sqlite = path.suffix.lower() in SQLITE_SUFFIXES
    try:
        net = _from_sqlite(path, data) if sqlite else pp.from_json_string(data.decode())
    except Exception as exc:                # whatever pandapower's readers raise
        text = " ".join(str(exc).split())[:120]
        raise GridError(f"grid: {path} is not a pandapower net file ({type(exc).__name__}: "
                        f"{text})") from None
    if not isinstance(net, pp.pandapowerNet) or "bus" not in net or "ext_grid" not in net:
        raise GridError(f"grid: {path} is not a pandapower net file (no bus or ext_grid table)")
    if not len(net.ext_grid) or not bool(net.ext_grid.in_service.astype(bool).any()):
        raise GridError(f"grid: {path}: the net has no external grid in service (the "
                        "interconnection point to the upper voltage level)")
    return net, hashlib.sha256(data).hexdigest()


def net_at_case(net, case: str | None, load_model: str) -> str:
    """Put ``net`` (in place) at study ``case`` of its loadcases table (or the time step of its
    profiles that ``case`` names: :func:`adnmesh.grid.simbench_net.time_step_case`), or leave
    it as saved if ``case`` is None and it has none; loads as ``load_model``. Returns the case
    used (:data:`AS_SAVED` for none).

    Raises
    ------
    GridError
        A case for a net without study cases, or one it does not have; a time step for a net
        without profiles, or one they do not have.
    """
    from adnmesh.grid.simbench_net import (apply_study_case, apply_time_step,
                                           loads_as_impedances, study_cases, time_step_of)

    cases = study_cases(net)
    used = AS_SAVED
    step = time_step_of(case)
    if step is not None:
        apply_time_step(net, step)
        used = case
    elif cases:
        used = case or "lW"
        apply_study_case(net, used)
    elif case is not None:
        raise GridError(f"grid: study case {case!r} asked for, but the net has no study cases "
                        "(no loadcases table): leave grid_model.study_case out to use it as "
                        "saved")
    if load_model == "impedance":
        loads_as_impedances(net)
    return used
