"""Which subsets ``adnmesh tune`` tunes: all of them where that is sensible, else a selection.

``all`` enumerates the 2^m - 1 subsets only up to :data:`MAX_ALL_DERS` DERs (65,535 subsets);
beyond that a table of every subset is neither computable nor storable and is refused with a
one-line error. ``scenario`` takes the sets of available DERs the config's scenario meets,
``random:N`` N distinct random subsets (seeded, reproducible) plus the set of all DERs, and a
FILE one subset per line (DER ids separated by spaces or commas, ``#`` starts a comment).
"""
from __future__ import annotations

from itertools import combinations
from pathlib import Path
from typing import Sequence

import numpy as np

from adnmesh.errors import UsageError
from adnmesh.files import read_regular

__all__ = ["DIRECTION_HEADROOM", "MAX_ALL_DERS", "MAX_SUBSETS", "able_to_move", "all_subsets", "select_subsets",
           "scenario_subsets", "random_subsets", "spread_random_subsets"]

#: ``--subsets all`` is refused beyond this many DERs (2^16 - 1 = 65,535 subsets)
MAX_ALL_DERS = 16
#: the most subsets a selection (``random:N``, FILE) may have: as many as ``all`` of
#: :data:`MAX_ALL_DERS` DERs
MAX_SUBSETS = 2 ** MAX_ALL_DERS - 1
#: the largest subset FILE read, bytes
MAX_FILE_BYTES = 64 * 2**20
#: a random subset is drawn with each DER in it with probability 1/2
SEED = 0


#: a DER can move up (down) from its schedule if its headroom there, up to its available
#: power (down to 0), is at least this fraction of its installed power
#: (docs/method.md#directional-availability)
DIRECTION_HEADROOM = 0.01


def all_subsets(ids: Sequence[str]) -> list[tuple[str, ...]]:
    """Every non-empty subset of ``ids`` (2^m - 1), by size then config order."""
    return [c for k in range(1, len(ids) + 1) for c in combinations(ids, k)]


def able_to_move(config, available_w=None) -> dict[int, frozenset[str]]:
    """The DERs that can move up (key 1) and down (key -1) from their schedules
    (docs/method.md#directional-availability): up if their available power (``available_w``,
    DER id -> W; default their installed power) exceeds their schedule by at least
    :data:`DIRECTION_HEADROOM` of their installed power, down if their schedule is at least
    that much above 0. A DER at ``p_sched_w: 0`` can only move up."""
    power = available_w or {d.id: d.p_inst_w for d in config.ders}
    margin = {d.id: DIRECTION_HEADROOM * d.p_inst_w for d in config.ders}
    return {1: frozenset(d.id for d in config.ders
                         if power[d.id] - d.p_sched_w >= margin[d.id]),
            -1: frozenset(d.id for d in config.ders if d.p_sched_w >= margin[d.id])}


def scenario_subsets(config, available_w=None) -> list[tuple[str, ...]]:
    """The sets of available DERs the scenario passes through (all DERs at t = 0), each
    followed by those of its DERs that can move up and those that can move down from their
    schedules where they are other non-empty sets (:func:`able_to_move`; ``available_w``:
    the DERs' available power, W, default their installed power): the sets the CPFC's gain
    schedule uses."""
    ids = list(config.der_ids())
    able = able_to_move(config, available_w)
    available = set(ids)
    out: dict[tuple[str, ...], None] = {}
    for change in (None, *config.scenario.availability):
        if change is not None and change.available:
            available |= set(change.ders)
        elif change is not None:
            available -= set(change.ders)
        for part in (available, available & able[1], available & able[-1]):
            s = tuple(d for d in ids if d in part)
            if s:
                out.setdefault(s, None)
    return list(out)


def random_subsets(ids, n: int, seed: int = SEED) -> list[tuple[str, ...]]:
    """``n`` distinct random non-empty subsets of ``ids`` plus ``ids`` itself (first)."""
    ids = list(ids)
    total = 2 ** len(ids) - 1 if len(ids) < 63 else float("inf")
    n = int(min(n, total - 1))
    rng = np.random.default_rng(seed)
    seen = {tuple(ids)}
    out = [tuple(ids)]
    while len(out) < n + 1:
        mask = rng.random(len(ids)) < 0.5
        s = tuple(d for d, m in zip(ids, mask) if m)
        if s and s not in seen:
            seen.add(s)
            out.append(s)
    return out


def spread_random_subsets(ids, n: int, seed: int = SEED) -> list[tuple[str, ...]]:
    """``n`` distinct random non-empty subsets of ``ids`` (every subset if there are no more),
    each of a size drawn uniformly from 1 to all, then its DERs uniformly: a sample that
    holds small subsets as well (with each DER in it with probability 1/2, a subset of 100
    DERs has 50 +- 15 of them, and no small subset is ever drawn)."""
    ids = list(ids)
    if len(ids) < 63 and n >= 2 ** len(ids) - 1:
        return all_subsets(ids)
    rng = np.random.default_rng(seed)
    seen: dict[tuple[str, ...], None] = {}
    while len(seen) < n:
        size = int(rng.integers(1, len(ids) + 1))
        pick = np.sort(rng.choice(len(ids), size, replace=False))
        seen.setdefault(tuple(ids[i] for i in pick), None)
    return list(seen)


def _from_file(path: Path, ids) -> list[tuple[str, ...]]:
    try:
        data = read_regular(path, MAX_FILE_BYTES)
    except IsADirectoryError:
        raise UsageError(f"--subsets {path}: is a directory, not a file of subsets") from None
    except OSError as exc:
        raise UsageError(f"--subsets {path}: cannot read ({exc.strerror or exc})") from None
    try:
        lines = data.decode("utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise UsageError(f"--subsets {path}: not UTF-8 text (byte {exc.start}): a file of "
                         "subsets has one subset of DER ids per line") from None
    known = set(ids)
    out: dict[tuple[str, ...], None] = {}
    for n, line in enumerate(lines, 1):
        names = line.split("#", 1)[0].replace(",", " ").split()
        if not names:
            continue
        unknown = [d for d in names if d not in known]
        if unknown:
            raise UsageError(f"--subsets {path}:{n}: unknown DER id {unknown[0][:70]!r}")
        out.setdefault(tuple(d for d in ids if d in set(names)), None)
        if len(out) > MAX_SUBSETS:
            raise UsageError(f"--subsets {path}:{n}: more than {MAX_SUBSETS:,} subsets, more "
                             "than a table can hold")
    if not out:
        raise UsageError(f"--subsets {path}: no subset in the file")
    return list(out)


def select_subsets(config, spec: str) -> list[tuple[str, ...]] | None:
    """Subsets for ``--subsets spec``; None means every subset (``all``).

    Raises
    ------
    UsageError
        ``all`` beyond :data:`MAX_ALL_DERS` DERs, a bad ``random:N`` or an unreadable FILE.
    """
    ids = list(config.der_ids())
    if spec == "all":
        if len(ids) > MAX_ALL_DERS:
            raise UsageError(f"--subsets all: {len(ids)} DERs have 2^{len(ids)} - 1 subsets, "
                             f"more than a table can hold (limit {MAX_ALL_DERS} DERs); use "
                             "--subsets scenario, random:N or FILE")
        return None
    if spec == "scenario":
        return scenario_subsets(config)
    if spec.startswith("random:"):
        try:
            n = int(spec.split(":", 1)[1])
        except ValueError:
            n = 0
        if not 1 <= n <= MAX_SUBSETS:
            raise UsageError(f"--subsets {spec[:40]}: N must be a positive integer, at most "
                             f"{MAX_SUBSETS:,} (as many subsets as a table can hold)")
        return random_subsets(ids, n)
    return _from_file(Path(spec), ids)
