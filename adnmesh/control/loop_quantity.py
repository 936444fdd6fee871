"""Which quantity a CPFC loop controls: the names it reads and writes on the bus.

The CPFC state machine (:class:`adnmesh.control.cpfc_controller.CPFC`) is the same for active
and reactive power (docs/method.md#reactive-power); a :class:`LoopQuantity` tells it the keys
of its output and reference, the fields of its measurement, limit states and acknowledgements.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["LOOPS", "LoopQuantity", "P_LOOP", "Q_LOOP"]


@dataclass(frozen=True)
class LoopQuantity:
    """The bus names of one controlled quantity.

    Attributes
    ----------
    name : str
        ``P`` or ``Q``.
    output_kind, reference_kind : str
        Message kinds (:mod:`adnmesh.wire.protocol`) of the output (P_Y, Q_Y) and reference.
    output_field, reference_field : str
        Their body fields; a DER's heartbeat acknowledges the last output it applied in a
        field of the output's name.
    measured_field : str
        The field of ``p_ip`` that carries the measured quantity.
    held_field : str
        The field of ``p_ip`` that says every DER following the output is held back.
    stats_prefix : str
        Before the names of the loop's stats and events (``""`` for P, ``"q_"`` for Q).
    """

    name: str
    output_kind: str
    reference_kind: str
    output_field: str
    reference_field: str
    measured_field: str
    held_field: str
    stats_prefix: str


P_LOOP = LoopQuantity("P", "p_y", "p_ref", "p_y", "p_ref_w", "p_ip_w", "held", "")
Q_LOOP = LoopQuantity("Q", "q_y", "q_ref", "q_y", "q_ref_var", "q_ip_var", "q_held", "q_")
LOOPS = {"P": P_LOOP, "Q": Q_LOOP}
