"""Which static generators become actuators (pure): the rules of ``adnmesh init``.

A generator is an actuator if it passes every rule given:

- **level** ``"mv"`` (default): on a bus of at least 1 kV and not SimBench's aggregated
  low-voltage generation (type ``lv_*``: whole LV feeders, not plants); ``"all"``: any;
- **types**: its DER type (:func:`adnmesh.adn.dynamics.der_type_of`) is one of them;
- **min_size_w**: its installed power is at least this, W;
- **names**: an explicit list of sgen names replaces the level rule (every name must exist).

A generator that passes but produces nothing at the study case can move neither way: it is left
out and said (:class:`Selection`). Generators that are not actuators stay constant injections.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass

from adnmesh.adn.dynamics import der_type_of
from adnmesh.adn.survey import Generator
from adnmesh.errors import UsageError

__all__ = ["LEVELS", "Actuator", "Selection", "select_actuators"]

LEVELS = ("mv", "all")
_MV_KV = 1.0


@dataclass(frozen=True)
class Actuator:
    """A generator made an actuator, with its DER type."""

    generator: Generator
    der_type: str


@dataclass(frozen=True)
class Selection:
    """The actuators (in the net's order) and the generators the rules left out for producing
    nothing at the study case."""

    actuators: tuple[Actuator, ...]
    idle: tuple[Generator, ...]


def _is_aggregated_lv(generator: Generator) -> bool:
    return generator.kind.lower().startswith("lv_")


def select_actuators(generators, level: str = "mv", types=None, min_size_w: float = 0.0,
                     names=None) -> Selection:
    """The actuators among ``generators`` by the rules of the module docstring.

    Raises
    ------
    UsageError
        A name not among the generators (with the closest names), or no generator left.
    """
    if level not in LEVELS:
        raise UsageError(f"--actuators: unknown level {level!r} (one of {', '.join(LEVELS)})")
    generators = list(generators)
    if names is not None:
        known = {g.name: g for g in generators}
        for name in names:
            if name not in known:
                close = difflib.get_close_matches(name, list(known), n=3, cutoff=0.6)
                hint = f"; closest: {', '.join(repr(c) for c in close)}" if close else ""
                raise UsageError(f"--sgens: no static generator named {name!r} in the net{hint}")
        chosen = [g for g in generators if g.name in set(names)]
    elif level == "mv":
        chosen = [g for g in generators if g.vn_kv >= _MV_KV and not _is_aggregated_lv(g)]
    else:
        chosen = list(generators)
    actuators, idle = [], []
    for g in chosen:
        der_type = der_type_of(g.kind, g.profile)
        if types is not None and der_type not in types:
            continue
        if g.p_inst_w < min_size_w or g.p_inst_w <= 0:
            continue
        if g.p_case_w <= 0:
            idle.append(g)
            continue
        actuators.append(Actuator(g, der_type))
    if not actuators:
        rules = [f"level {level}" if names is None else f"{len(names)} named sgen(s)"]
        if types is not None:
            rules.append(f"types {','.join(types)}")
        if min_size_w:
            rules.append(f"at least {min_size_w:g} W")
        idle_note = f" ({len(idle)} match but produce nothing at the study case)" if idle else ""
        raise UsageError(f"no static generator matches the rules ({', '.join(rules)}) of "
                         f"{len(generators)} in the net{idle_note}")
    return Selection(tuple(actuators), tuple(idle))
