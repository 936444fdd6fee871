"""A user's time series of a net's injections, as CSV or Parquet (``adnmesh study --profiles``).

One row per interval, one column per series (docs/study.md#your-own-time-series):

- ``time``: the interval's start, ``2024-03-01T00:15`` or ``2024-03-01 00:15`` (ISO; seconds
  allowed and dropped), or a Parquet timestamp; increasing, equally spaced;
- ``sgen.p_mw:<name>``, ``load.p_mw:<name>``, ``load.q_mvar:<name>``,
  ``storage.p_mw:<name>``, ``gen.p_mw:<name>``: that element's ``p_mw`` / ``q_mvar`` (before
  its ``scaling``, as in the net's tables), the element named by its ``name`` in the net
  (everything after the first colon).

Elements without a column keep the value they have at the config's operating point. Read with
pyarrow (its CSV reader and Parquet reader), at most :data:`MAX_PROFILE_BYTES`; every problem
is a one-line :class:`~adnmesh.errors.GridError` naming the file and the column or row.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from adnmesh.errors import GridError
from adnmesh.files import read_regular, unreadable

__all__ = ["MAX_PROFILE_BYTES", "MAX_SERIES_MW", "SERIES", "read_profile_table"]

#: the largest profile file read, bytes
MAX_PROFILE_BYTES = 1024 * 2**20
#: the largest power a series may give, MW or Mvar (the config's bound on a DER, 10 GW)
MAX_SERIES_MW = 1e4
#: column prefixes: (element table, column of it)
SERIES = {"sgen.p_mw": ("sgen", "p_mw"), "load.p_mw": ("load", "p_mw"),
          "load.q_mvar": ("load", "q_mvar"), "storage.p_mw": ("storage", "p_mw"),
          "gen.p_mw": ("gen", "p_mw")}


def _table(path: Path):
    import pyarrow as pa

    try:
        data = read_regular(path, MAX_PROFILE_BYTES)
    except OSError as exc:
        raise GridError(f"profiles: {unreadable(path, exc, 'profile file')}") from None
    try:
        if path.suffix.lower() in (".parquet", ".pq"):
            import pyarrow.parquet as pq
            return pq.read_table(pa.BufferReader(data))
        import pyarrow.csv as pcsv
        block = min(max(len(data) + 1, 1 << 20), (1 << 31) - 1)   # the header fits one block
        return pcsv.read_csv(pa.BufferReader(data),
                             read_options=pcsv.ReadOptions(block_size=block),
                             convert_options=pcsv.ConvertOptions(
                                 column_types={"time": pa.string()}))
    except (pa.ArrowException, ValueError, OSError, KeyError) as exc:
        text = _printable(" ".join(str(exc).split())[:160])
        raise GridError(f"profiles: {path} cannot be read as "
                        f"{'Parquet' if path.suffix.lower() in ('.parquet', '.pq') else 'CSV'}"
                        f": {text}") from None


def _printable(text: str) -> str:
    """``text`` with every character a terminal would act on shown as ``?``."""
    return "".join(c if c.isprintable() else "?" for c in text)


def _times(path: Path, column) -> np.ndarray:
    import pyarrow as pa

    if pa.types.is_timestamp(column.type):
        if column.type.tz is not None:
            raise GridError(f"profiles: {path}: the times carry a time zone "
                            f"({_printable(column.type.tz)}); give local times without one, "
                            "as the profiles' own")
        return column.to_numpy(zero_copy_only=False).astype("datetime64[m]")
    out = np.empty(len(column), dtype="datetime64[m]")
    for i, text in enumerate(column.to_pylist()):
        m = (re.fullmatch(r"(\d{4}-\d{2}-\d{2})[T ](\d{2}:\d{2})(:\d{2}(\.\d+)?)?",
                          str(text).strip()) if text is not None else None)
        try:
            out[i] = np.datetime64(f"{m.group(1)}T{m.group(2)}") if m else None
        except ValueError:
            m = None
        if m is None:
            raise GridError(f"profiles: {path}: row {i + 2}: time {text!r} is not "
                            "'YYYY-MM-DDTHH:MM'")
    return out


def read_profile_table(path: str | Path) -> tuple[np.ndarray, dict[tuple[str, str], dict]]:
    """``(times, series)`` of a profile file: times as datetime64[m]; ``series[(table,
    column)]`` maps element names to their values per interval (float arrays). One-line
    :class:`GridError` for a file that cannot be read, a missing or bad time column, a
    column of no known kind, a repeated column, or a value that is no number within
    ±:data:`MAX_SERIES_MW`."""
    import pyarrow as pa

    path = Path(path)
    table = _table(path)
    try:
        names = table.column_names
    except UnicodeDecodeError:
        raise GridError(f"profiles: {path}: the column names are not UTF-8 text") from None
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise GridError(f"profiles: {path}: column {_printable(repeated[0])!r} is given "
                        f"{names.count(repeated[0])} times")
    if "time" not in names:
        raise GridError(f"profiles: {path}: no 'time' column (columns: "
                        f"{', '.join(names[:5])}{', ...' if len(names) > 5 else ''})")
    if table.num_rows < 2:
        raise GridError(f"profiles: {path}: at least two intervals needed, got "
                        f"{table.num_rows}")
    times = _times(path, table.column("time"))
    steps = np.diff(times)
    if not (steps > np.timedelta64(0, "m")).all() or (steps != steps[0]).any():
        bad = int(np.flatnonzero((steps <= np.timedelta64(0, "m")) | (steps != steps[0]))[0])
        raise GridError(f"profiles: {path}: row {bad + 3}: times must increase in equal steps "
                        f"of whole minutes ({times[bad]} then {times[bad + 1]}; times are read "
                        "to the minute)")
    series: dict[tuple[str, str], dict] = {}
    for name in names:
        if name == "time":
            continue
        prefix, colon, element = name.partition(":")
        if not colon or prefix not in SERIES or not element:
            raise GridError(f"profiles: {path}: column {_printable(name)!r} is none of "
                            f"{', '.join(k + ':<name>' for k in SERIES)}")
        column = table.column(name)
        if not (pa.types.is_floating(column.type) or pa.types.is_integer(column.type)):
            raise GridError(f"profiles: {path}: column {_printable(name)!r} holds "
                            f"{column.type}, not numbers")
        values = column.to_numpy(zero_copy_only=False).astype(float)
        bad = np.flatnonzero(~(np.abs(values) <= MAX_SERIES_MW))
        if bad.size:
            raise GridError(f"profiles: {path}: column {_printable(name)!r}, row "
                            f"{int(bad[0]) + 2}: not a number within ±{MAX_SERIES_MW:g} MW or "
                            f"Mvar, got {float(values[bad[0]])!r}")
        target = series.setdefault(SERIES[prefix], {})
        if element in target:
            raise GridError(f"profiles: {path}: column {_printable(name)!r} is given twice")
        target[element] = values
    return times, series
