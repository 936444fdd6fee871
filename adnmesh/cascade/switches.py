"""What a lower ADN's gain switch does to the upper loop, and the rule that keeps it certified.

An ADN switches its own entry when its DERs' availability changes (bumplessly: its ``P_Y``
stays continuous, so the switch itself puts no step into the upper loop). What changes for
the level above is the ADN's closed loop ``T_i`` and its capacity ``C_i`` (so ``K_i = w_i
C_i``). The upper entry was certified with every ADN at its entry for all its DERs.

**The rule** (docs/hierarchy.md#lower-switches): after ADN i switches, the upper controller
evaluates the cascade with i's new closed loop and capacity. If it still meets both
constraints, the upper gains stay; otherwise they are scaled by the back-off factor of
:func:`~adnmesh.cascade.certificate.back_off` for the new cascade (bumplessly, like the upper
controller's own gain switch), which certifies it again. :func:`switch_sweep` applies the
rule to every entry of one ADN's table, so the factors and figures are known before a run.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

from adnmesh.cascade.certificate import CascadeFigures, back_off
from adnmesh.cascade.lower_adn import LowerAdn
from adnmesh.cascade.structure import Cascade

__all__ = ["SwitchRow", "switched", "switch_sweep"]


@dataclass(frozen=True)
class SwitchRow:
    """The upper entry with one ADN at another of its entries.

    Attributes
    ----------
    adn : str
        The ADN that switched.
    ders : tuple of str
        Its available DERs (the entry it switched to).
    back_off : float or None
        The factor the rule applies to the upper gains (1: none needed; None: no factor of
        the back-off meets the constraints).
    figures : CascadeFigures
        The cascade's figures with that factor applied.
    """

    adn: str
    ders: tuple[str, ...]
    back_off: float | None
    figures: CascadeFigures


def switched(cascade: Cascade, position: int, lower: LowerAdn, weight: float) -> Cascade:
    """``cascade`` with its ADN at ``position`` under another entry: ``lower``, and ``K_i =
    weight * lower.capacity_w``."""
    adns = list(cascade.adns)
    gains = list(cascade.gains_w)
    adns[position] = lower
    gains[position] = weight * lower.capacity_w
    return replace(cascade, adns=tuple(adns), gains_w=tuple(gains))


def switch_sweep(cascade: Cascade, position: int, weight: float, kp: float, ki: float,
                 entries: list[tuple[tuple[str, ...], LowerAdn]], constraints,
                 on_entry=None) -> list[SwitchRow]:
    """The rule applied to each of ``entries`` (an ADN's entries: its DERs and itself under
    that entry) in turn, the other ADNs at theirs; ``on_entry(done, total)`` after each."""
    rows = []
    for done, (ders, lower) in enumerate(entries, 1):
        factor, fig = back_off(switched(cascade, position, lower, weight), kp, ki,
                               constraints.disk_margin_min, constraints.overshoot_max_pct,
                               constraints.settling_band_pct)
        rows.append(SwitchRow(lower.name, ders, factor, fig))
        if on_entry:
            on_entry(done, len(entries))
    return rows
