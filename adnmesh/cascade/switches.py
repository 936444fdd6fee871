"""What a lower ADN's gain switch does to the upper loop, and the rule that keeps it certified.

An ADN switches its own entry when its DERs' availability changes (bumplessly: its ``P_Y``
stays continuous, so the switch itself puts no step into the upper loop). What changes for
the level above is the ADN's closed loop ``T_i`` (its gain ``K_i = w_i C_i`` stays: see
:func:`switched`). The upper entry was certified with every ADN at its entry for all its DERs.

**The rule** (docs/hierarchy.md#lower-switches): after ADN i switches, the upper controller
evaluates the cascade with i's new closed loop. If it still meets both
constraints, the upper gains stay; otherwise they are scaled by the back-off factor of
:func:`~adnmesh.cascade.certificate.back_off` for the new cascade (bumplessly, like the upper
controller's own gain switch), which certifies it again. :func:`switch_sweep` applies the
rule to every entry of one ADN's table, so the factors and figures are known before a run.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from adnmesh.cascade.certificate import CascadeFigures, back_off
from adnmesh.cascade.lower_adn import LowerAdn, announced
from adnmesh.cascade.structure import Cascade

__all__ = ["LowerSwitchRule", "SwitchRow", "switched", "switch_sweep"]


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


def switched(cascade: Cascade, position: int, lower: LowerAdn) -> Cascade:
    """``cascade`` with its ADN at ``position`` under another entry, ``lower``. Its ``K_i``
    stays: the upper controller asks ``P_Y w_i C_i`` of the ADN with the ``C_i`` it was
    designed with, and the ADN's new loop still follows its reference offset at unit gain;
    what the lost plants take away is its dynamics and its reach (its limit state)."""
    adns = list(cascade.adns)
    adns[position] = lower
    return replace(cascade, adns=tuple(adns))


def switch_sweep(cascade: Cascade, position: int, kp: float, ki: float,
                 entries: list[tuple[tuple[str, ...], LowerAdn]], constraints,
                 on_entry=None) -> list[SwitchRow]:
    """The rule applied to each of ``entries`` (an ADN's entries: its DERs and itself under
    that entry) in turn, the other ADNs at theirs; ``on_entry(done, total)`` after each."""
    rows = []
    for done, (ders, lower) in enumerate(entries, 1):
        factor, fig = back_off(switched(cascade, position, lower), kp, ki,
                               constraints.disk_margin_min, constraints.overshoot_max_pct,
                               constraints.settling_band_pct)
        rows.append(SwitchRow(lower.name, ders, factor, fig))
        if on_entry:
            on_entry(done, len(entries))
    return rows


@dataclass
class LowerSwitchRule:
    """The rule at run time, in the upper CPFC of a hierarchy's run: the ADNs' loops as they
    last announced them, and the back-off an upper entry needs over them.

    Attributes
    ----------
    lowers : dict
        ADN id -> its :class:`LowerAdn` now (at the start: under its entry for all its DERs,
        as the upper table was certified).
    gain_w : dict
        ADN id -> ``C_i g_i``: its capacity in the upper config times the HV grid's gain at
        its bus (:attr:`~adnmesh.cascade.upper_table.Site.grid_gain`), W (``K_i = w_i C_i
        g_i``).
    t_com_s : dict
        ADN id -> its inter-site delay, s.
    t_meas_s : float
        The upper measurement's delay, s.
    constraints : object
        ``disk_margin_min``, ``overshoot_max_pct``, ``settling_band_pct``.
    """

    lowers: dict[str, LowerAdn]
    gain_w: dict[str, float]
    t_com_s: dict[str, float]
    t_meas_s: float
    constraints: object

    def take(self, message) -> str | None:
        """Take an ADN's ``adn_actuator`` announcement (its ``grid`` names the ADN); the
        ADN's id if its loop changed, else None (an unknown or repeated one)."""
        adn = getattr(message, "grid", None)
        if adn not in self.lowers:
            return None
        lower = announced(adn, message)
        if _same_loop(lower, self.lowers[adn]):
            return None
        self.lowers[adn] = lower
        return adn

    def back_off(self, ders, w: dict[str, float], kp: float, ki: float
                 ) -> tuple[float | None, CascadeFigures]:
        """The factor on ``(kp, ki)`` for the cascade of the ADNs ``ders`` with weights ``w``
        at their loops now (:func:`~adnmesh.cascade.certificate.back_off`)."""
        cascade = Cascade(tuple(self.lowers[a] for a in ders),
                          tuple(w[a] * self.gain_w[a] for a in ders),
                          tuple(self.t_com_s[a] for a in ders), self.t_meas_s)
        c = self.constraints
        return back_off(cascade, kp, ki, c.disk_margin_min, c.overshoot_max_pct,
                        c.settling_band_pct)


def _same_loop(a: LowerAdn, b: LowerAdn) -> bool:
    """The same closed loop: gains, groups and delays."""
    return (a.kp, a.ki, a.plant.actuators, a.plant.t_com_s, a.plant.t_meas_s) == \
        (b.kp, b.ki, b.plant.actuators, b.plant.t_com_s, b.plant.t_meas_s) and \
        np.array_equal(a.plant.gains_w, b.plant.gains_w)
