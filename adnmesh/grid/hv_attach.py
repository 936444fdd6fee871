"""An HV net with MV ADNs attached at their HV buses (imports pandapower, and simbench for a
SimBench code).

A hierarchy of ADNs (docs/hierarchy.md) may put an HV grid between its ADNs and the level
above: the upper controller then acts on the HV grid's exchange with the level above, and each
ADN's exchange is an injection at the HV bus its HV/MV transformer hangs from. :func:`hv_net`
builds that net once, at its operating point, for the upper level's config to solve as an
ordinary grid model (saved without study cases: the operating point is already in it;
:func:`hv_base` then :func:`attach_adns`):

- the HV net (a SimBench code, or a pandapower net file) at its study case;
- at each ADN's bus, what stood for that MV grid taken out of service: the named loads and
  static generators, or by default those whose profile (a load's) or type (a static
  generator's) begins with ``mv_`` — SimBench's aggregated MV grids;
- per ADN two static generators at that bus: ``<adn>``, the upper level's actuator, whose
  infeed the upper measurement sets to the ADN's (its schedule part: 0 up to its installed
  power ``capacity_w``), and ``<adn> operating point``, constant, its exchange at its own
  operating point beyond that schedule (``P_IP,0 - P_sched``) and its reactive exchange
  ``Q_IP,0``. Their sum is the ADN's exchange, MV -> HV positive.

Units: W and var in, MW and Mvar in the net.
"""

from __future__ import annotations

from dataclasses import dataclass

from adnmesh.errors import GridError

__all__ = ["ADN_TYPE", "Attachment", "OPERATING_POINT", "attach_adns", "hv_base", "locate",
           "replaced_at", "write_net"]

OPERATING_POINT = " operating point"
"""Suffix of the name of an ADN's constant static generator in the HV net."""
ADN_TYPE = "ADN"
"""The net ``type`` of the static generators that stand for ADNs."""


@dataclass(frozen=True)
class Attachment:
    """One ADN at its HV bus.

    Attributes
    ----------
    adn : str
        Its id (the upper level's DER id and its static generator's name).
    bus : str
        The HV bus's name in the net.
    capacity_w : float
        Its installed power, W (the actuator's rating and available power).
    p_w, q_var : float
        The constant part of its exchange: ``P_IP,0 - P_sched`` (W) and ``Q_IP,0`` (var).
    replaces : tuple of str or None
        Names of the loads and static generators at ``bus`` it takes the place of (None: the
        ``mv_`` ones).
    """

    adn: str
    bus: str
    capacity_w: float
    p_w: float
    q_var: float
    replaces: tuple[str, ...] | None = None


def _bus_index(net, name: str) -> int:
    found = net.bus.index[net.bus.name.astype(str) == name]
    if len(found) == 0:
        some = ", ".join(repr(str(n)) for n in net.bus.name[:3])
        raise GridError(f"HV grid: no bus named {name!r} (its {len(net.bus)} buses are named "
                        f"like {some})")
    if len(found) > 1:
        raise GridError(f"HV grid: {len(found)} buses are named {name!r}; name one that is "
                        "unique")
    return int(found[0])


def _mv_stand_in(frame, column: str):
    if column not in frame:
        return frame.index[:0]
    return frame.index[frame[column].astype(str).str.startswith("mv_")]


def replaced_at(net, bus: int, replaces: tuple[str, ...] | None) -> dict[str, list[int]]:
    """``{"load": [...], "sgen": [...]}``: the indices at bus ``bus`` an ADN takes the place
    of (see :class:`Attachment`).

    Raises
    ------
    GridError
        A name in ``replaces`` that is no load or static generator at the bus.
    """
    at = {kind: net[kind][net[kind].bus == bus] for kind in ("load", "sgen")}
    if replaces is None:
        return {"load": [int(i) for i in _mv_stand_in(at["load"], "profile")],
                "sgen": [int(i) for i in _mv_stand_in(at["sgen"], "type")]}
    out: dict[str, list[int]] = {"load": [], "sgen": []}
    for name in replaces:
        hits = [(kind, int(i)) for kind, frame in at.items()
                for i in frame.index[frame.name.astype(str) == name]]
        if not hits:
            raise GridError(f"HV grid: {name!r} is no load or static generator at bus "
                            f"{net.bus.name[bus]!r}")
        for kind, i in hits:
            out[kind].append(i)
    return out


def hv_base(source: str, name: str, case: str | None):
    """The HV net at its operating point, without study cases: ``source`` ``"simbench"``
    (``name`` a code) or ``"pandapower"`` (``name`` a file); ``case`` its study case (None: lW
    for a SimBench net, as saved for a file).

    Raises
    ------
    GridError
        One line: a net or study case that cannot be had.
    """
    from adnmesh.grid.simbench_net import apply_study_case, load_simbench_net, study_cases

    if source == "simbench":
        net = load_simbench_net(name)
    else:
        from adnmesh.grid.net_file import read_net
        net, _ = read_net(name)
    if case is not None or (source == "simbench" and study_cases(net)):
        apply_study_case(net, case or "lW")
    for table in ("loadcases", "profiles"):
        if table in net:
            del net[table]
    return net


def locate(net, bus: str, replaces: tuple[str, ...] | None) -> tuple[int, dict[str, list[int]]]:
    """``(bus index, replaced)`` of an ADN at bus ``bus`` (:func:`replaced_at`).

    Raises
    ------
    GridError
        One line: an unknown or ambiguous bus, one out of service or not supplied from an
        external grid, a replaced element that is not at the bus.
    """
    index = _bus_index(net, bus)
    if not bool(net.bus.in_service[index]):
        raise GridError(f"HV grid: bus {bus!r} is out of service")
    from pandapower.topology import unsupplied_buses

    if index in unsupplied_buses(net):
        raise GridError(f"HV grid: bus {bus!r} is not connected to an external grid (the "
                        "level above) through lines and transformers in service")
    return index, replaced_at(net, index, replaces)


def attach_adns(net, attachments: list[Attachment]) -> dict[str, list[str]]:
    """Attach the ADNs to ``net`` (in place; module docstring); per ADN the names of what it
    took the place of.

    Raises
    ------
    GridError
        As :func:`locate`.
    """
    import pandapower as pp

    replaced: dict[str, list[str]] = {}
    for a in attachments:
        bus, taken = locate(net, a.bus, a.replaces)
        replaced[a.adn] = []
        for kind, indices in taken.items():
            net[kind].loc[indices, "in_service"] = False
            replaced[a.adn] += [str(n) for n in net[kind].name[indices]]
        mw = a.capacity_w / 1e6
        pp.create_sgen(net, bus, p_mw=mw, q_mvar=0.0, sn_mva=mw, name=a.adn, type=ADN_TYPE,
                       controllable=False)
        pp.create_sgen(net, bus, p_mw=a.p_w / 1e6, q_mvar=a.q_var / 1e6,
                       name=a.adn + OPERATING_POINT, type=ADN_TYPE, controllable=False)
    return replaced


def write_net(net, path) -> None:
    """Write ``net`` as ``pandapower.to_json`` does, to ``path``."""
    import pandapower as pp

    pp.to_json(net, str(path))
