"""The on-load tap changer of the HV/MV transformer, as a bus-free state machine
(docs/models.md#tap-changer).

It is part of the grid the measurement agent solves: every sample it is given the voltage of
the transformer's MV busbar, and it moves the tap one step when that voltage has been outside
``v_set_pu ± dead_band_pu`` for ``delay_s`` without a break, then waits ``delay_s`` again before
the next step (the time-delayed voltage regulator of real OLTCs; no line-drop compensation).
The step goes the way that brings the voltage back: with the tap on the HV side a higher
position means a higher ratio and a lower MV voltage, on the LV side the reverse. At the end of
its range it stays and says so once.
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
            self._outside_since = None
            self._at_end_said = False
            return 0, ""
        if self._outside_since is None:
            self._outside_since = t_ns
            return 0, ""
        if t_ns - self._outside_since < self.delay_ns:
            return 0, ""
        step = -self.raises_voltage if error > 0 else self.raises_voltage
        target = self.position + step
        self._outside_since = t_ns            # the next step needs another delay
        if not self.tap_min <= target <= self.tap_max:
            if self._at_end_said:
                return 0, ""
            self._at_end_said = True
            return 0, (f"tap changer at the end of its range (position {self.position}): "
                       f"MV busbar at {v_pu:.4f} p.u. stays outside "
                       f"{self.v_set_pu:g} ± {self.dead_band_pu:g} p.u.")
        self.position = target
        self.moves += 1
        return step, ""
