"""Reactive power: each DER's P-Q capability, its reactive dynamics, the Q services at the
interface, and the config's **reactive view** (docs/method.md#reactive-power).

The Q controller is the P controller with the quantity as a parameter. Tuning, analyses, the
static controller and the CPFC read a DER through four fields: its capacity ``C_d``
(``p_inst_w``), its reaction and rise time, and its schedule. :func:`reactive_view` is the config
whose DERs carry their reactive side in those fields, so every command that works for P works
for Q on it (``--quantity q``):

- capacity ``C_d^Q`` = the width of the DER's reactive range, ``Q_max,d - Q_min,d`` (var), as
  ``C_d = P_inst,d`` is the width of ``[0, P_inst,d]``, so that Eq. 1 reads
  ``Q_ref,d = Q_Y w_d C_d^Q + Q_sched,d``;
- reaction and rise time: ``t_delay_q_s`` and ``t_rise_q_s`` (defaults by type,
  :data:`Q_DYNAMICS`);
- schedule and range: Q is counted from the DER's lowest reactive power ``Q_min,d`` (≤ 0), so
  that its range is ``[0, C_d^Q]`` like a P range ``[0, P_inst,d]``; the shift is the same on
  both sides of Eq. 1 and leaves ``Q_Y`` unchanged;
- the scenario's Q_ref steps in place of its P_ref steps.

A DER without reactive range (preset ``unity``) is left out of the view. The view's design
document says ``quantity: Q``, so a Q table is bound to the reactive data and never mistaken for
a P table. Signs: generator convention, ``Q > 0`` injects (over-excited), as pandapower's
``sgen.q_mvar``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pydantic_core import PydanticCustomError

from adnmesh.config import (CAPABILITY_PRESETS, DER, AvailabilityChange, Config, ConfigFile, PRefStep, QU,
                            Reactive, Scenario)
from adnmesh.errors import ConfigError

__all__ = ["Capability", "Q_DYNAMICS", "capability_of", "limit_pq", "q_dynamics",
           "q_of_cos_phi", "q_of_u", "q_reference", "reactive_settings", "reactive_view"]

Q_DYNAMICS: dict[str, tuple[float, float]] = {
    "WT": (0.01, 0.05), "PV": (0.01, 0.05),
    "CHP": (0.05, 0.5), "HYDRO": (0.05, 0.5), "GEN": (0.05, 0.5)}
"""Type -> default (reaction time, 10-90 % rise time) of the reactive power, s: converter-
coupled plants (WT Type 4, PV) set Q by their current control within a few grid periods plus
their control cycle (much faster than P, which a WT's pitch and a CHP's engine limit);
synchronous generators (CHP, hydro, other) through their excitation and voltage regulator, a
few hundred ms. They are assumptions for a generic plant (docs/models.md#reactive-power);
set a DER's own (``t_delay_q_s``, ``t_rise_q_s``)."""


@dataclass(frozen=True)
class Capability:
    """The P-Q capability of one DER: ``P^2 + Q^2 <= S^2`` and ``Q_min <= Q <= Q_max``.

    Attributes
    ----------
    s_va : float
        Apparent power rating, VA.
    q_min_var : float
        Lowest reactive power (absorbing, under-excited), var, ≤ 0.
    q_max_var : float
        Highest reactive power (injecting, over-excited), var, ≥ 0.
    """

    s_va: float
    q_min_var: float
    q_max_var: float

    @property
    def capacity_var(self) -> float:
        """``C_d^Q``: the width of the reactive range, ``Q_max - Q_min``, var (as ``C_d =
        P_inst,d`` is the width of ``[0, P_inst,d]``)."""
        return self.q_max_var - self.q_min_var


def _q_at(p_inst_w: float, cos_phi: float) -> float:
    return p_inst_w * math.tan(math.acos(cos_phi))


def capability_of(der: DER, reactive: Reactive | None) -> Capability:
    """The capability of ``der`` (its preset or the section's, its cos phi overrides)."""
    preset = der.q_capability or (reactive or Reactive()).capability
    under, over = CAPABILITY_PRESETS[preset]
    under = under if der.cos_phi_under is None else der.cos_phi_under
    over = over if der.cos_phi_over is None else der.cos_phi_over
    return Capability(der.apparent_va, -_q_at(der.p_inst_w, under), _q_at(der.p_inst_w, over))


def limit_pq(cap: Capability, p_w: float, q_var: float, p_max_w: float, priority: str
             ) -> tuple[float, float, int, int]:
    """Limit a DER's wanted ``(p_w, q_var)`` to its capability.

    P is first limited to ``[0, p_max_w]`` (W), Q to ``[Q_min, Q_max]``; then, if
    ``P^2 + Q^2 > S^2``, the one without priority gives way (``priority`` ``"p"``: Q to
    ``±sqrt(S^2 - P^2)``; ``"q"``: P to ``sqrt(S^2 - Q^2)``).

    Returns
    -------
    (p_w, q_var, p_held, q_held)
        The limited values and, for each, +1 if it was limited from above, -1 from below, 0
        if free.
    """
    p = min(max(p_w, 0.0), p_max_w)
    q = min(max(q_var, cap.q_min_var), cap.q_max_var)
    s2 = cap.s_va * cap.s_va
    if p * p + q * q > s2:
        if priority == "p":
            room = math.sqrt(max(s2 - p * p, 0.0))
            q = min(max(q, -room), room)
        else:
            p = min(p, math.sqrt(max(s2 - q * q, 0.0)))
    return p, q, (p_w > p) - (p_w < p), (q_var > q) - (q_var < q)


def q_dynamics(der: DER) -> tuple[float, float]:
    """``(t_delay_q_s, t_rise_q_s)`` of ``der``: its own, else its type's default."""
    delay, rise = Q_DYNAMICS[der.type]
    return (delay if der.t_delay_q_s is None else der.t_delay_q_s,
            rise if der.t_rise_q_s is None else der.t_rise_q_s)


def q_of_u(u_pu: float, q_u: QU) -> float:
    """The Q(U) characteristic's change of Q_ref at voltage ``u_pu`` (p.u.), var: 0 inside
    ``u_ref ± dead_band``, beyond it ``-slope`` per p.u. of the distance to the band's edge
    (over-voltage: less injection), limited to ``±q_max_var``."""
    above = u_pu - (q_u.u_ref_pu + q_u.dead_band_pu)
    below = (q_u.u_ref_pu - q_u.dead_band_pu) - u_pu
    dq = -q_u.slope_var_per_pu * above if above > 0 else \
        q_u.slope_var_per_pu * below if below > 0 else 0.0
    return min(max(dq, -q_u.q_max_var), q_u.q_max_var)


def q_of_cos_phi(p_w: float, cos_phi: float, q_with_p: bool) -> float:
    """The reactive power at active power ``p_w`` (W) and power factor ``cos_phi``, var: the
    sign of P when ``q_with_p``, the opposite else."""
    q = abs(p_w) * math.tan(math.acos(cos_phi))
    return math.copysign(q, p_w if q_with_p else -p_w) if p_w != 0 else 0.0


def reactive_settings(config: Config) -> Reactive:
    """The config's reactive section, or its defaults when it has none."""
    return config.reactive if config.reactive is not None else Reactive()


def reactive_view(config: Config) -> Config:
    """The config for the Q loop (see the module docstring).

    Raises
    ------
    ConfigError
        No DER has reactive range, a reactive schedule outside its DER's range, or reactive
        dynamics out of what the loop numerics hold (the same rules as for P, said with the
        reactive keys).
    """
    if config.quantity == "Q":
        return config
    reactive = reactive_settings(config)
    ders = []
    for i, der in enumerate(config.ders):
        cap = capability_of(der, reactive)
        if not cap.q_min_var <= der.q_sched_var <= cap.q_max_var:
            raise ConfigError(f"{config.path}: ders[{i}].q_sched_var: outside its reactive "
                              f"range [{cap.q_min_var:.6g}, {cap.q_max_var:.6g}] var, got "
                              f"{der.q_sched_var:g}")
        if cap.capacity_var <= 0:
            continue
        delay, rise = q_dynamics(der)
        ders.append(DER.model_construct(
            id=der.id, type=der.type, p_inst_w=cap.capacity_var, t_delay_s=delay,
            t_rise_s=rise, sgen=der.sgen, p_sched_w=der.q_sched_var - cap.q_min_var))
    if not ders:
        raise ConfigError(f"{config.path}: no DER has a reactive power range (every one is "
                          "'unity'): there is no Q loop to tune or run")
    scenario = config.scenario
    steps = tuple(PRefStep.model_construct(t_s=s.t_s, delta_w=s.delta_var)
                  for s in scenario.q_ref_steps)
    kept = {d.id for d in ders}
    availability = tuple(
        AvailabilityChange.model_construct(t_s=c.t_s, available=c.available,
                                           ders=tuple(d for d in c.ders if d in kept))
        for c in scenario.availability if set(c.ders) & kept)
    view = config.model_copy(update={
        "ders": tuple(ders), "quantity": "Q",
        "scenario": Scenario.model_construct(duration_s=scenario.duration_s,
                                             p_ref_steps=steps, availability=availability)})
    try:
        ConfigFile._numerics(view)
    except PydanticCustomError as exc:
        raise ConfigError(f"{config.path}: reactive dynamics (t_delay_q_s, t_rise_q_s): "
                          f"{exc.context['message'] if exc.context else exc}") from None
    return view


def q_reference(config: Config, p_ref_w: float, q_ip_var: float
                ) -> tuple[float, list[tuple[float, float]]]:
    """Q_ref over the run by ``reactive.mode``: ``(start, [(t_s, change), ...])``, var.

    ``p_ref_w`` and ``q_ip_var`` are the operating point (P_ref before the first step, Q_IP
    with every DER at its schedule):

    - ``q``: from Q_IP, the scenario's Q_ref steps;
    - ``q_u``: from Q_IP plus :func:`q_of_u` of the upper side's voltage (``u_ref_pu`` before
      the first of ``scenario.u_hv_steps``), a step wherever the characteristic moves;
    - ``cos_phi``: :func:`q_of_cos_phi` of P_ref, from the first sample (a step at 0 from
      Q_IP) and with every P_ref step.
    """
    reactive, scenario = reactive_settings(config), config.scenario
    if reactive.mode == "q":
        return q_ip_var, [(s.t_s, s.delta_var) for s in scenario.q_ref_steps]
    steps: list[tuple[float, float]] = []
    if reactive.mode == "q_u":
        before = q_of_u(reactive.q_u.u_ref_pu, reactive.q_u)
        for step in scenario.u_hv_steps:
            now = q_of_u(step.u_pu, reactive.q_u)
            if now != before:
                steps.append((step.t_s, now - before))
            before = now
        return q_ip_var + q_of_u(reactive.q_u.u_ref_pu, reactive.q_u), steps
    p, before = p_ref_w, q_ip_var
    for t_s, delta in [(0.0, 0.0), *((s.t_s, s.delta_w) for s in scenario.p_ref_steps)]:
        p += delta
        now = q_of_cos_phi(p, reactive.cos_phi, reactive.cos_phi_q_with_p)
        if now != before:
            steps.append((t_s, now - before))
        before = now
    return q_ip_var, steps
