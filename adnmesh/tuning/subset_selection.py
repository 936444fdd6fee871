"""Which subsets ``adnmesh tune`` tunes: all of them where that is sensible, else a selection.

``all`` enumerates the 2^m - 1 subsets only up to :data:`MAX_ALL_DERS` DERs (65,535 subsets);
beyond that a table of every subset is neither computable nor storable and is refused with a
one-line error. ``scenario`` takes the sets of available DERs the config's scenario meets,
``random:N`` N distinct random subsets (seeded, reproducible) plus the set of all DERs, and a
FILE one subset per line (DER ids separated by spaces or commas, ``#`` starts a comment).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from adnmesh.errors import UsageError
from adnmesh.tuning.problem import all_subsets

__all__ = ["MAX_ALL_DERS", "select_subsets", "scenario_subsets", "random_subsets",
           "spread_random_subsets"]

#: ``--subsets all`` is refused beyond this many DERs (2^16 - 1 = 65,535 subsets)
MAX_ALL_DERS = 16
#: a random subset is drawn with each DER in it with probability 1/2
SEED = 0


def scenario_subsets(config) -> list[tuple[str, ...]]:
    """The sets of available DERs the scenario passes through (all DERs at t = 0)."""
    ids = list(config.der_ids())
    available = set(ids)
    out = [tuple(ids)]
    for change in config.scenario.availability:
        if change.available:
            available |= set(change.ders)
        else:
            available -= set(change.ders)
        s = tuple(d for d in ids if d in available)
        if s and s not in out:
            out.append(s)
    return out


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
        lines = Path(path).read_text().splitlines()
    except OSError as exc:
        raise UsageError(f"--subsets {path}: cannot read ({exc.strerror})") from None
    known = set(ids)
    out = []
    for n, line in enumerate(lines, 1):
        names = line.split("#", 1)[0].replace(",", " ").split()
        if not names:
            continue
        unknown = [d for d in names if d not in known]
        if unknown:
            raise UsageError(f"--subsets {path}:{n}: unknown DER id {unknown[0]!r}")
        s = tuple(d for d in ids if d in set(names))
        if s not in out:
            out.append(s)
    if not out:
        raise UsageError(f"--subsets {path}: no subset in the file")
    return out


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
        if n < 1:
            raise UsageError(f"--subsets {spec}: N must be a positive integer")
        return random_subsets(ids, n)
    return _from_file(Path(spec), ids)
