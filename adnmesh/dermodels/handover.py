"""The re-entry transient of the detailed DER models, open loop
(docs/method.md#returning-ders-handover).

When a DER returns, the CPFC's switch moves power from the DERs that carried it to the one
that returns. :func:`handover_response` shows what that move does to the DERs' total infeed
without the controller: DER A (returning) takes ``share_w`` more, DER B gives as much back,
either at once or ramped over ``handover_s`` (the setpoints change every ``period_s``, as P_Y
does); the sum of their infeeds should not move. What it does move is what the loop has to
correct: with the WT's ramp limit acting upward only and a PV moving at once, a handover at
once is a dip of most of the share; over the handover the DERs follow their ramps with their
response times and the dip shrinks with ``1 / handover_s``. Pure; ``adnmesh analyze
--der-models`` draws it (:func:`adnmesh.dermodels.response_plot.plot_handover`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from adnmesh.dermodels import default_params, infeed_at, set_point, steady_state
from adnmesh.dermodels.responses import BASE_FRACTION

__all__ = ["HandoverResponse", "handover_panels", "handover_pair", "handover_response"]


@dataclass(frozen=True)
class HandoverResponse:
    """The total infeed of two DERs while ``share_w`` moves from ``giver`` to ``taker``.

    Attributes
    ----------
    taker, giver : str
        What each DER is (labels).
    share_w : float
        Power moved, W.
    handover_s : float
        Over how long (0: at once), s.
    t_s : ndarray
        Times after the switch, s.
    deviation : ndarray
        Change of the two infeeds' sum, fraction of ``share_w`` (0: a perfect handover).
    """

    taker: str
    giver: str
    share_w: float
    handover_s: float
    t_s: np.ndarray
    deviation: np.ndarray

    @property
    def largest(self) -> float:
        """The largest ``|deviation|``, fraction of the share."""
        return float(np.max(np.abs(self.deviation)))


def handover_response(taker_params, giver_params, taker_p0_w: float, giver_p0_w: float,
                      share_w: float, handover_s: float, t_end_s: float,
                      period_s: float = 0.01, labels=("taker", "giver")) -> HandoverResponse:
    """Move ``share_w`` (W) from the DER of ``giver_params`` (at ``giver_p0_w``) to that of
    ``taker_params`` (at ``taker_p0_w``): the setpoints change every ``period_s`` on a linear
    ramp over ``handover_s`` (0: at once, at t = 0); return the sum of the two infeeds'
    changes, sampled every ``period_s`` to ``t_end_s``."""
    taker = steady_state(taker_params, taker_p0_w)
    giver = steady_state(giver_params, giver_p0_w)
    steps = int(round(t_end_s / period_s))
    t_ns = [int(round(k * period_s * 1e9)) for k in range(steps + 1)]
    out = np.empty(steps + 1)
    moved = 0.0
    for k, t in enumerate(t_ns):
        done = 1.0 if handover_s <= 0 else min(1.0, t * 1e-9 / handover_s)
        if done != moved:
            moved = done
            set_point(taker_params, taker, t, taker_p0_w + done * share_w)
            set_point(giver_params, giver, t, giver_p0_w - done * share_w)
        total = infeed_at(taker_params, taker, t) + infeed_at(giver_params, giver, t)
        out[k] = (total - taker_p0_w - giver_p0_w) / share_w
    return HandoverResponse(labels[0], labels[1], share_w, handover_s,
                            np.asarray(t_ns) * 1e-9, out)


def handover_pair(taker, giver, share_fraction: float, handover_s: float,
                  t_end_s: float) -> HandoverResponse:
    """:func:`handover_response` for two DERs of a config (``type, p_inst_w, t_delay_s,
    t_rise_s``, ``id``) with their default detailed models, both from
    :data:`~adnmesh.dermodels.responses.BASE_FRACTION` of their installed power, moving
    ``share_fraction`` of the smaller installed power."""
    share = share_fraction * min(taker.p_inst_w, giver.p_inst_w)
    return handover_response(
        default_params(taker.type, taker.p_inst_w, taker.t_delay_s, taker.t_rise_s),
        default_params(giver.type, giver.p_inst_w, giver.t_delay_s, giver.t_rise_s),
        BASE_FRACTION * taker.p_inst_w, BASE_FRACTION * giver.p_inst_w, share, handover_s,
        t_end_s, labels=(f"{taker.type} {taker.id}", f"{giver.type} {giver.id}"))


def handover_panels(ders, response_s, handover_times: float, share_fraction: float = 0.1):
    """For the figure: one panel per kind of DER (the first of each distinct type, T_delay,
    T_rise of ``ders``) taking ``share_fraction`` from one DER of every kind, at once and over
    ``handover_times`` times the slower one's response time (``response_s(der)``, s: the
    shortest handover the CPFC gives them, docs/method.md#returning-ders-handover)."""
    first: dict[tuple, object] = {}
    for d in ders:
        first.setdefault((d.type, d.t_delay_s, d.t_rise_s), d)
    kinds = list(first.values())
    panels = []
    for taker in kinds:
        responses = []
        for giver in kinds:
            handover = handover_times * max(response_s(taker), response_s(giver))
            t_end = handover + 4 * max(response_s(taker), response_s(giver))
            for seconds in (0.0, handover):
                responses.append(handover_pair(taker, giver, share_fraction, seconds, t_end))
        panels.append((f"{taker.type} {taker.id} returns", responses))
    return panels
