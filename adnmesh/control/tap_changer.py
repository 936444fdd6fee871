"""The on-load tap changer of the HV/MV transformer, as a bus-free state machine
(docs/models.md#tap-changer).

It is part of the grid the measurement agent solves. It regulates one of two things:

- ``busbar`` (:meth:`TapChangerControl.observe`): the voltage of the transformer's MV busbar,
  kept within ``v_set_pu ± dead_band_pu`` (the time-delayed voltage regulator of real OLTCs;
  no line-drop compensation);
- ``extremes`` (:meth:`TapChangerControl.observe_extremes`): the grid's highest and lowest bus
  voltage, kept within a band inside the voltage limits (the wide-area control some DSOs run
  their OLTCs with, from measurements out in the feeders): the highest above the band's top
  lowers the voltage, else the lowest below its bottom raises it.

It moves the tap one step when its voltage has been outside its band for ``delay_s`` without a
break, then waits ``delay_s`` again before the next step. The step goes the way that brings the
voltage back: with the tap on the HV side a higher position means a higher ratio and a lower MV
voltage, on the LV side the reverse. At the end of its range it stays and says so once.
"""

from __future__ import annotations

__all__ = ["TapChangerControl"]


class TapChangerControl:
    """The regulator's logic (see the module docstring).

    Parameters
    ----------
    v_set_pu, dead_band_pu : float
        The busbar voltage it keeps and the half width of its band, p.u.
    delay_s : float
        How long the voltage must be outside before a step, s.
    position, tap_min, tap_max : int
        The tap's position and range.
    raises_voltage : int
        +1 if a higher position raises the MV voltage (tap on the LV side), -1 if it lowers
        it (tap on the HV side).
    """

    def __init__(self, v_set_pu: float, dead_band_pu: float, delay_s: float, position: int,
                 tap_min: int, tap_max: int, raises_voltage: int) -> None:
        if not tap_min <= position <= tap_max:
            raise ValueError(f"tap position {position} outside its range "
                             f"[{tap_min}, {tap_max}]")
        self.v_set_pu, self.dead_band_pu = float(v_set_pu), float(dead_band_pu)
        self.delay_ns = int(round(delay_s * 1e9))
        self.position, self.tap_min, self.tap_max = int(position), int(tap_min), int(tap_max)
        self.raises_voltage = 1 if raises_voltage > 0 else -1
        self._outside_since: int | None = None
        self._at_end_said = False
        self.moves = 0

    def observe(self, t_ns: int, v_pu: float) -> tuple[int, str]:
        """Fold in the busbar voltage at ``t_ns``; returns ``(step, note)``: the change of
        position to make now (-1, 0, +1) and, when it wants to move but is at the end of its
        range (said once per stay there), a note saying so."""
        error = v_pu - self.v_set_pu
        if abs(error) <= self.dead_band_pu or v_pu != v_pu:       # inside, or no value
            return self._inside()
        return self._outside(t_ns, 1 if error > 0 else -1,
                             f"MV busbar at {v_pu:.4f} p.u. stays outside "
                             f"{self.v_set_pu:g} ± {self.dead_band_pu:g} p.u.")

    def observe_extremes(self, t_ns: int, v_min_pu: float, v_max_pu: float, low_pu: float,
                         high_pu: float) -> tuple[int, str]:
        """Mode ``extremes``: fold in the grid's lowest and highest bus voltage at ``t_ns``
        against the band ``[low_pu, high_pu]``; returns what :meth:`observe` returns. The
        highest above the band lowers the voltage (it wins when both are out: the limits are
        not kept either way then, and over-voltage is what DERs cause)."""
        if v_max_pu > high_pu:
            return self._outside(t_ns, 1, f"highest bus voltage {v_max_pu:.4f} p.u. stays "
                                          f"above {high_pu:g} p.u.")
        if v_min_pu < low_pu:
            return self._outside(t_ns, -1, f"lowest bus voltage {v_min_pu:.4f} p.u. stays "
                                           f"below {low_pu:g} p.u.")
        return self._inside()

    def _inside(self) -> tuple[int, str]:
        self._outside_since = None
        self._at_end_said = False
        return 0, ""

    def _outside(self, t_ns: int, too: int, words: str) -> tuple[int, str]:
        """The voltage is too high (``too`` +1) or too low (-1) at ``t_ns``."""
        if self._outside_since is None:
            self._outside_since = t_ns
            return 0, ""
        if t_ns - self._outside_since < self.delay_ns:
            return 0, ""
        step = -self.raises_voltage if too > 0 else self.raises_voltage
        target = self.position + step
        self._outside_since = t_ns            # the next step needs another delay
        if not self.tap_min <= target <= self.tap_max:
            if self._at_end_said:
                return 0, ""
            self._at_end_said = True
            return 0, (f"tap changer at the end of its range (position {self.position}): "
                       f"{words}")
        self.position = target
        self.moves += 1
        return step, ""
