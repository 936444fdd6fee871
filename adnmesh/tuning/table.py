"""The gain-scheduling table CP: one PI pair and weight vector per DER subset
(docs/method.md#tuning-the-gain-table).

A table is written by ``adnmesh tune`` as JSON::

    {"format": 1, "config_sha256": ..., "constraints": {...}, "method": "paper" | "global",
     "der_ids": [...],
     "entries": [{"ders": [ids], "kp": 1/W, "ki": 1/(W s), "w": {id: w}, "feasible": bool,
                  "reason": str | null, "rise_time_s": ..., ...}, ...],
     "static": {"kp": ..., "ki": ..., ...}}

Gains are in 1/W (``kp``) and 1/(W s) (``ki``), ~1e-9 for MW-scale plants. The figures stored
with an entry are those of the as-deployed loop (weights applied).

A table is bound to what its gains depend on, not to the config file
(:mod:`adnmesh.tuning.design_key`): it holds the config's ``design`` document and its
``design_sha256``, and :func:`load_table` refuses it for a config whose design differs, naming
the first difference. The scenario, the grid model, the runtime and comments may change. A
table without a design (written before it was kept) is bound to the config file's sha256 as
before. By default the table of ``DIR/NAME.yaml`` is ``DIR/tables/NAME.<first 12 hex of the
design sha256>.json``, next to the config whatever the working directory
(:func:`default_table_path`).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

from adnmesh.errors import ConfigError
from adnmesh.files import read_regular, write_atomic
from adnmesh.loopmodel.gains import gain_problem
from adnmesh.tuning.design_key import (design_document, design_sha256, document_sha256,
                                       first_difference)

__all__ = ["TableEntry", "SchedulingTable", "new_table", "default_table_path", "load_table",
           "save_table", "check_table", "FIGURE_KEYS", "MAX_TABLE_BYTES"]

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
    """CP for one config: entries keyed by subset, plus the static controller.

    ``config_sha256``: the file it was tuned from (provenance); ``design``: the design
    document it is bound to (:mod:`adnmesh.tuning.design_key`; None in older tables, bound to
    ``config_sha256``).
    """

    config_sha256: str
    constraints: dict
    method: str
    der_ids: tuple[str, ...]
    entries: dict = field(default_factory=dict)      # frozenset(ids) -> TableEntry
    static: TableEntry | None = None
    complete: bool = False
    design: dict | None = None

    @property
    def design_sha256(self) -> str | None:
        """SHA-256 of :attr:`design` (None without one)."""
        return None if self.design is None else document_sha256(self.design)

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
                **({} if self.design is None else {"design_sha256": self.design_sha256,
                                                    "design": self.design}),
                "der_ids": list(self.der_ids), "complete": self.complete,
                "entries": [e.to_json() for e in rows],
                "static": None if self.static is None else self.static.to_json()}

    @classmethod
    def from_json(cls, obj: dict) -> "SchedulingTable":
        table = cls(obj["config_sha256"], dict(obj["constraints"]), obj["method"],
                    tuple(obj["der_ids"]), complete=bool(obj.get("complete", False)),
                    design=obj.get("design"))
        for row in obj["entries"]:
            table.add(TableEntry.from_json(row))
        if obj.get("static"):
            table.static = TableEntry.from_json(obj["static"])
        return table


def new_table(config, constraints: dict, method: str) -> SchedulingTable:
    """An empty table for ``config``, bound to its design."""
    return SchedulingTable(config.sha256, constraints, method, config.der_ids(),
                           design=design_document(config))


def default_table_path(config) -> Path:
    """``<config's folder>/tables/<config stem>.<first 12 hex of its design sha256>.json``."""
    path = Path(config.path)
    return path.parent / "tables" / f"{path.stem}.{design_sha256(config)[:12]}.json"


def save_table(table: SchedulingTable, path: str | Path) -> None:
    """Write atomically (:func:`adnmesh.files.write_atomic`): an interrupted write never leaves
    a broken table."""
    write_atomic(path, json.dumps(table.to_json(), indent=1, allow_nan=False))


#: the largest table file read, bytes (every subset of 16 DERs, 65,535 entries, is ~70 MB)
MAX_TABLE_BYTES = 256 * 2**20


def load_table(path: str | Path, config=None) -> SchedulingTable:
    """Read a table; with ``config`` check that it was tuned for exactly that config.

    Every value a runtime uses is checked (:func:`check_table`): a table is data that may
    have been edited or damaged, and the CPFC must not meet a gain it cannot run.

    Raises
    ------
    ConfigError
        Missing, unreadable or malformed file (not a regular file, more than
        :data:`MAX_TABLE_BYTES`, JSON nested too deep), a value out of its range, or a table
        made for another config.
    """
    path = Path(path)
    try:
        obj = json.loads(read_regular(path, MAX_TABLE_BYTES))
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such table (run 'adnmesh tune CONFIG' first)") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, not a table file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the table: {exc.strerror or exc}") from None
    except RecursionError:
        raise ConfigError(f"{path}: not a valid adnmesh table (JSON nested too deep)") from None
    except ValueError as exc:       # JSON (UnicodeDecodeError is one)
        raise ConfigError(f"{path}: not a valid adnmesh table ({exc.__class__.__name__}: "
                          f"{' '.join(str(exc).split())[:200]})") from None
    try:
        check_table(obj)
    except ValueError as exc:
        raise ConfigError(f"{path}: not a valid adnmesh table: {exc}") from None
    table = SchedulingTable.from_json(obj)
    if config is not None and table.design is not None:
        wanted = design_document(config)
        option = " --quantity q" if wanted.get("quantity") == "Q" else ""
        if table.design.get("quantity") != wanted.get("quantity"):
            raise ConfigError(f"{path}: a table of the {'Q' if option == '' else 'P'} loop, "
                              f"not of the {'P' if option == '' else 'Q'} loop; tune that with "
                              f"'adnmesh tune {config.path}{option}'")
        difference = first_difference(table.design, wanted)
        if difference is not None:
            raise ConfigError(f"{path}: table was tuned for another design ({difference}); "
                              f"retune with 'adnmesh tune {config.path}{option}'")
    elif config is not None and table.config_sha256 != config.sha256:
        raise ConfigError(f"{path}: table was tuned for another config "
                          f"(sha256 {table.config_sha256[:12]}, config has {config.sha256[:12]}; "
                          "a table without a design is bound to the file)")
    if config is not None and table.der_ids != config.der_ids():
        raise ConfigError(f"{path}: not a valid adnmesh table: der_ids: not the config's DERs "
                          f"({_show(list(table.der_ids))}, the config has "
                          f"{_show(list(config.der_ids()))})")
    if config is not None:
        power = {d.id: d.p_inst_w for d in config.ders}
        rows = [(f"entries[{i}]", e) for i, e in enumerate(obj["entries"])]
        for at, row in rows + ([("static", obj["static"])] if obj.get("static") else []):
            if row["kp"] is not None:
                problem = gain_problem(row["kp"], row["ki"],
                                       sum(power[d] for d in row["ders"]))
                if problem is not None:
                    raise ConfigError(f"{path}: not a valid adnmesh table: {at}: {problem}")
    return table


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _check_entry(row, at: str, known: set[str]) -> None:
    if not isinstance(row, dict):
        raise ValueError(f"{at}: must be a mapping, got {_show(row)}")
    for key in ("ders", "kp", "ki", "w", "feasible"):
        if key not in row:
            raise ValueError(f"{at}: the key {key!r} is missing")
    ders = row["ders"]
    if not (isinstance(ders, list) and ders and all(isinstance(d, str) for d in ders)):
        raise ValueError(f"{at}.ders: must be a non-empty list of DER ids, got {_show(ders)}")
    if len(set(ders)) != len(ders):
        raise ValueError(f"{at}.ders: a DER id appears twice")
    unknown = [d for d in ders if d not in known]
    if unknown:
        raise ValueError(f"{at}.ders: unknown DER id {unknown[0]!r}")
    if not isinstance(row["feasible"], bool):
        raise ValueError(f"{at}.feasible: must be true or false, got {_show(row['feasible'])}")
    if row["feasible"] or row["kp"] is not None or row["ki"] is not None:
        problem = gain_problem(row["kp"], row["ki"])
        if problem is not None:
            raise ValueError(f"{at}: {problem}"
                             + ("" if row["feasible"] else " (null: an infeasible entry's)"))
    weights = row["w"]
    if not isinstance(weights, dict):
        raise ValueError(f"{at}.w: must be a mapping of DER id to weight, got {_show(weights)}")
    for der_id, w in weights.items():
        if der_id not in ders:
            raise ValueError(f"{at}.w: {der_id!r} is not a DER of the entry")
        if not (_number(w) and 0 <= w <= 1):
            raise ValueError(f"{at}.w.{der_id}: must be a weight in [0, 1], got {_show(w)}")
    missing = [d for d in ders if d not in weights]
    if missing:
        raise ValueError(f"{at}.w: no weight for {missing[0]!r} (one per DER of the entry)")
    if row["feasible"] and not any(weights.values()):
        raise ValueError(f"{at}.w: every weight is 0 in a feasible entry")
    if row.get("reason") is not None and not isinstance(row["reason"], str):
        raise ValueError(f"{at}.reason: must be a text or null, got {_show(row['reason'])}")


def check_table(obj) -> None:
    """Check a table document (parsed JSON) before it is used.

    The rules: ``format`` 1; ``der_ids`` distinct ids; a ``design``, if there is one, plain
    data whose sha256 is ``design_sha256``;
    every entry (and the static controller) names a non-empty set of distinct known DERs,
    says whether it is ``feasible``, has gains ``kp`` (1/W) and ``ki`` (1/(W s)) the loop
    numerics take (:func:`adnmesh.loopmodel.gains.gain_problem`: finite, positive, ``K_P /
    K_I`` at most 1e9 s) where it is feasible (an infeasible entry may have none: null), and
    weights ``w``, one per DER of the entry, in [0, 1] and not all 0 in a feasible entry (Find
    W gives 0 to a DER that can take no share).

    Raises
    ------
    ValueError
        The first problem, as one line naming its place (``entries[3].kp: ...``).
    """
    if not isinstance(obj, dict):
        raise ValueError(f"must be a JSON object, got {_show(obj)}")
    if obj.get("format", FORMAT) != FORMAT:
        raise ValueError(f"format: must be {FORMAT}, got {_show(obj.get('format'))}")
    for key in ("config_sha256", "constraints", "method", "der_ids", "entries"):
        if key not in obj:
            raise ValueError(f"the key {key!r} is missing")
    if not isinstance(obj["config_sha256"], str):
        raise ValueError(f"config_sha256: must be a text, got {_show(obj['config_sha256'])}")
    if not isinstance(obj["constraints"], dict):
        raise ValueError(f"constraints: must be a mapping, got {_show(obj['constraints'])}")
    if not isinstance(obj["method"], str):
        raise ValueError(f"method: must be a text, got {_show(obj['method'])}")
    if "design" in obj:
        if not isinstance(obj["design"], dict):
            raise ValueError(f"design: must be a mapping, got {_show(obj['design'])}")
        try:
            digest = document_sha256(obj["design"])
        except (TypeError, ValueError):
            raise ValueError("design: not plain data (numbers, texts, lists, mappings)") from None
        if obj.get("design_sha256") != digest:
            raise ValueError(f"design_sha256: {_show(obj.get('design_sha256'))} is not the "
                             "design's (the table was edited)")
    ids = obj["der_ids"]
    if not (isinstance(ids, list) and all(isinstance(d, str) for d in ids)):
        raise ValueError(f"der_ids: must be a list of DER ids, got {_show(ids)}")
    if len(set(ids)) != len(ids):
        raise ValueError("der_ids: a DER id appears twice")
    known = set(ids)
    if not isinstance(obj["entries"], list):
        raise ValueError(f"entries: must be a list, got {_show(obj['entries'])}")
    for i, row in enumerate(obj["entries"]):
        _check_entry(row, f"entries[{i}]", known)
    if obj.get("static") is not None:
        _check_entry(obj["static"], "static", known)

def entry_figures(figures, i: int) -> dict:
    """``FIGURE_KEYS`` of candidate ``i`` of a :class:`adnmesh.loopmodel.evaluation.LoopFigures`."""
    row = figures.row(i)
    return {k: row[k] for k in FIGURE_KEYS}

