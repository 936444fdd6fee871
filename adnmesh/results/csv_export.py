"""A run's time series as CSV files a controls engineer loads in pandas or a spreadsheet
(``adnmesh export RUN.mcap --csv DIR``).

One file per bus key, named after the key below ``adn/<grid>/`` (``measurement_p_ip.csv``;
of a recording of several grids with the grid first, ``hv.measurement_p_ip.csv``;
``cpfc_p_y.csv``, ``der_SGen1_state.csv``, ``availability_si.csv``, ``measurement_grid.csv``,
``scenario_p_ref.csv``): a column ``time_s`` (the send time, s of sim time from the run's
start) and one column per series of that key, named with its unit (``P_IP [MW]``,
``K_P [1/MW]``, ``SGen1 infeed [MW]``, ``SGen1 available``), in the units of
:data:`adnmesh.results.rules.DISPLAY_UNITS` (MW, Mvar, 1/MW, 1/(MW s); p.u., %, and 0/1 as
recorded). The series of one key are sampled together (one message), so a file is a table
without gaps; where a key's messages lack a field the cell is empty. Values are written in
full precision (Python's shortest round-trip form): ``pd.read_csv(path,
float_precision="round_trip")`` gives them bit for bit (pandas' default parser to within
1e-15).

Besides, ``series.csv`` lists every series (file, column, name, unit, role, DER, key, field)
and ``events.csv`` the run's events (time_s, kind, level, text, key): what ``inspect`` shows.
The series are those of :func:`adnmesh.results.series.read_run`, the one reader of
recordings.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np

from adnmesh.results.rules import natural_key
from adnmesh.results.series import RunData, Series

__all__ = ["EVENTS_FILE", "INDEX_FILE", "csv_name", "write_csv"]

INDEX_FILE = "series.csv"
"""The file that lists every series and where it is."""

EVENTS_FILE = "events.csv"
"""The file of the run's events."""


def csv_name(topic: str, with_grid: bool = False) -> str:
    """The file of the series of ``topic``: the key below ``adn/<grid>/`` with ``/`` as ``_``
    (``adn/g/der/SGen1/state`` -> ``der_SGen1_state.csv``); ``with_grid`` (a recording of
    several grids) puts the grid first (``g.der_SGen1_state.csv``)."""
    parts = topic.split("/")
    below = parts[2:] if len(parts) > 2 and parts[0] == "adn" else parts
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", "_".join(below) or "run") + ".csv"
    if with_grid and len(parts) > 2 and parts[0] == "adn":
        name = re.sub(r"[^A-Za-z0-9_-]", "_", parts[1]) + "." + name
    return name


def _cell(value: float) -> str:
    return "" if not np.isfinite(value) else repr(float(value))


def _table(run: RunData, series: list[Series]) -> tuple[list[str], list[list[str]]]:
    """The header and rows of the series of one key (columns joined on their send times)."""
    header = ["time_s", *(s.label for s in series)]
    first = series[0].t_ns
    if all(np.array_equal(s.t_ns, first) for s in series[1:]):
        times, columns = first, [s.shown() for s in series]
    else:                                            # a field missing in some messages
        times = np.unique(np.concatenate([s.t_ns for s in series]))
        columns = []
        for s in series:
            column = np.full(times.size, np.nan)
            column[np.searchsorted(times, s.t_ns)] = s.shown()
            columns.append(column)
    seconds = run.seconds(times)
    rows = [[repr(float(t)), *(_cell(c[i]) for c in columns)] for i, t in enumerate(seconds)]
    return header, rows


def write_csv(run: RunData, out_dir: str | Path) -> list[Path]:
    """Write ``run``'s series and events as CSV files into ``out_dir`` (made if missing; see
    the module doc); return the files written, the index and the events first."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    by_topic: dict[str, list[Series]] = {}
    for series in run.series.values():
        by_topic.setdefault(series.topic, []).append(series)
    index = [["file", "column", "series", "unit", "role", "der", "key", "field"]]
    written = []
    several = len({t.split("/")[1] for t in by_topic if t.startswith("adn/")
                   and t.count("/") >= 2}) > 1           # a hierarchy's: names would collide
    for topic in sorted(by_topic, key=natural_key):
        found = sorted(by_topic[topic], key=lambda s: (s.der is not None,
                                                       natural_key(s.der or "")))
        name = csv_name(topic, with_grid=several)
        header, rows = _table(run, found)
        _write(out_dir / name, [header, *rows])
        written.append(out_dir / name)
        index += [[name, column, s.name, s.display_unit, s.role, s.der or "", topic,
                   s.entity_path.removeprefix(f"/{topic}/")]
                  for column, s in zip(header[1:], found)]
    events = [["time_s", "kind", "level", "text", "key"]]
    events += [[repr(float(run.seconds(e.t_ns))), e.kind, e.level, e.text, e.topic]
               for e in run.events]
    _write(out_dir / INDEX_FILE, index)
    _write(out_dir / EVENTS_FILE, events)
    return [out_dir / INDEX_FILE, out_dir / EVENTS_FILE, *written]


def _write(path: Path, rows: list[list[str]]) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)
