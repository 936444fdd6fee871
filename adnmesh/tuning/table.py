"""The gain-scheduling table CP: one PI pair and weight vector per DER subset
(docs/method.md#tuning-the-gain-table).

A table is written by ``adnmesh tune`` as JSON::

    {"format": 1, "config_sha256": ..., "constraints": {...}, "method": "paper" | "global",
     "der_ids": [...],
     "entries": [{"ders": [ids], "kp": 1/W, "ki": 1/(W s), "w": {id: w}, "feasible": bool,
                  "reason": str | null, "rise_time_s": ..., ...}, ...],
     "static": {"kp": ..., "ki": ..., ...}}

Gains are in 1/W (``kp``) and 1/(W s) (``ki``), ~1e-9 for MW-scale plants. The figures stored
with an entry are those of the as-deployed loop (weights applied). By default a table for
``configs/NAME.yaml`` lives at ``tables/NAME.<first 12 hex of the config's sha256>.json``
relative to the working directory (:func:`default_table_path`), so a runtime finds the table that matches its config exactly and
never a stale one.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

from adnmesh.errors import ConfigError
from adnmesh.files import write_atomic

__all__ = ["TableEntry", "SchedulingTable", "default_table_path", "load_table", "save_table",
           "FIGURE_KEYS"]

FORMAT = 1

#: figures of merit stored with every entry (and the static controller)
FIGURE_KEYS = ("rise_time_s", "settling_time_s", "overshoot_pct", "disk_margin", "gain_margin",
               "phase_margin_deg", "delay_margin_s")


@dataclass(frozen=True)
class TableEntry:
    """One row of CP.

    Attributes
    ----------
    ders : tuple of str
        The subset A_n (DER ids in config order).
    kp : float
        Proportional gain, 1/W.
    ki : float
        Integral gain, 1/(W s).
    w : dict
        Weight per DER id, dimensionless in (0, 1].
    feasible : bool
        The as-deployed loop meets both constraints.
    reason : str or None
        Why no feasible pair exists (infeasible entries only).
    figures : dict
        ``FIGURE_KEYS`` of the as-deployed loop (weights applied), plus ``design_rise_time_s``
        (the tuning method's rise time on the unweighted plant), ``global_rise_time_s`` (the
        global optimum's on that plant) and ``gain_back_off`` (factor applied to both gains so
        that the weighted loop meets the constraints; 1 if none was needed) and ``tuned_by``
        (``paper``, ``global``, or the global search standing in where the paper's path found
        no feasible point).
    """

    ders: tuple[str, ...]
    kp: float
    ki: float
    w: dict
    feasible: bool = True
    reason: str | None = None
    figures: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        finite = lambda v: v if v == v and abs(v) != float("inf") else None  # noqa: E731
        out = {"ders": list(self.ders), "kp": finite(self.kp), "ki": finite(self.ki),
               "w": dict(self.w),
               "feasible": self.feasible, "reason": self.reason}
        out.update(self.figures)
        return out

    @classmethod
    def from_json(cls, obj: dict) -> "TableEntry":
        figures = {k: v for k, v in obj.items()
                   if k not in ("ders", "kp", "ki", "w", "feasible", "reason")}
        gain = lambda v: float("nan") if v is None else float(v)  # noqa: E731
        return cls(tuple(obj["ders"]), gain(obj["kp"]), gain(obj["ki"]),
                   {k: float(v) for k, v in obj["w"].items()}, bool(obj["feasible"]),
                   obj.get("reason"), figures)


@dataclass
class SchedulingTable:
    """CP for one config: entries keyed by subset, plus the static controller."""

    config_sha256: str
    constraints: dict
    method: str
    der_ids: tuple[str, ...]
    entries: dict = field(default_factory=dict)      # frozenset(ids) -> TableEntry
    static: TableEntry | None = None
    complete: bool = False

    def lookup(self, ders: Iterable[str]) -> TableEntry | None:
        """Entry for the subset ``ders`` (any order), or None if the table lacks it."""
        return self.entries.get(frozenset(ders))

    def add(self, entry: TableEntry) -> None:
        self.entries[frozenset(entry.ders)] = entry

    def to_json(self) -> dict:
        order = {d: i for i, d in enumerate(self.der_ids)}
        rows = sorted(self.entries.values(),
                      key=lambda e: (len(e.ders), [order.get(d, 0) for d in e.ders]))
        return {"format": FORMAT, "config_sha256": self.config_sha256,
                "constraints": self.constraints, "method": self.method,
                "der_ids": list(self.der_ids), "complete": self.complete,
                "entries": [e.to_json() for e in rows],
                "static": None if self.static is None else self.static.to_json()}

    @classmethod
    def from_json(cls, obj: dict) -> "SchedulingTable":
        table = cls(obj["config_sha256"], dict(obj["constraints"]), obj["method"],
                    tuple(obj["der_ids"]), complete=bool(obj.get("complete", False)))
        for row in obj["entries"]:
            table.add(TableEntry.from_json(row))
        if obj.get("static"):
            table.static = TableEntry.from_json(obj["static"])
        return table


def default_table_path(config) -> Path:
    """``tables/<config stem>.<first 12 hex of its sha256>.json``, relative to the working dir."""
    return Path("tables") / f"{Path(config.path).stem}.{config.sha256[:12]}.json"


def save_table(table: SchedulingTable, path: str | Path) -> None:
    """Write atomically (:func:`adnmesh.files.write_atomic`): an interrupted write never leaves
    a broken table."""
    write_atomic(path, json.dumps(table.to_json(), indent=1, allow_nan=False))


def load_table(path: str | Path, config=None) -> SchedulingTable:
    """Read a table; with ``config`` check that it was tuned for exactly that config.

    Raises
    ------
    ConfigError
        Missing or malformed file, or a table made for another config.
    """
    path = Path(path)
    try:
        table = SchedulingTable.from_json(json.loads(path.read_text()))
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such table (run 'adnmesh tune CONFIG' first)") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"{path}: not a valid adnmesh table ({exc.__class__.__name__}: {exc})") \
            from None
    if config is not None and table.config_sha256 != config.sha256:
        raise ConfigError(f"{path}: table was tuned for another config "
                          f"(sha256 {table.config_sha256[:12]}, config has {config.sha256[:12]})")
    return table


def entry_figures(figures, i: int) -> dict:
    """``FIGURE_KEYS`` of candidate ``i`` of a :class:`adnmesh.loopmodel.evaluation.LoopFigures`."""
    row = figures.row(i)
    return {k: row[k] for k in FIGURE_KEYS}

