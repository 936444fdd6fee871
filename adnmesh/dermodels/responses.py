"""Step responses of the detailed DER models beside the reference PT1, and their rise times.

:func:`der_model_report` takes what the config says of one DER (id, type, P_inst, T_delay,
T_rise; optionally ``t_lag_s``, the reference model's time constant) and returns the default
detailed model's step responses — up and down, two step sizes, from 50 % of P_inst — with their
exact 10-90 % rise times and reaction times, and the same for the reference PT1. Pure: the
figure is :func:`adnmesh.dermodels.response_plot.plot_der_models`, the files are written by
``adnmesh analyze CONFIG --der-models``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from adnmesh.dermodels import default_params, functions, reference_pt1
from adnmesh.dermodels.risetime import crossing_time, first_crossing, normalised

__all__ = ["BASE_FRACTION", "STEP_FRACTIONS", "StepResponse", "DerModelReport",
           "step_response", "der_model_report", "MODEL_NAMES"]

#: Operating point the steps start from, fraction of P_inst.
BASE_FRACTION = 0.5
#: Step sizes, fractions of P_inst: the calibration step and a large one.
STEP_FRACTIONS = (0.1, 0.4)
#: What each detailed model is called in figures and tables.
MODEL_NAMES = {"WT": "WT Type 4B-like", "CHP": "CHP 2nd order + rate limit",
               "PV": "PV lag + processing delay", "HYDRO": "hydro 2nd order + rate limit",
               "GEN": "generic lag + processing delay"}
_MOVED = 1e-9          # the infeed has reacted once it moved by this fraction of the step


@dataclass(frozen=True)
class StepResponse:
    """One setpoint step and the infeed's answer.

    Attributes
    ----------
    direction : str
        ``"up"`` or ``"down"``.
    step_fraction : float
        Size of the step, fraction of P_inst.
    t_s : ndarray
        Times after the setpoint step, s.
    normalised : ndarray
        ``(P(t) - P_0) / (P_1 - P_0)``: 0 before, 1 at the new setpoint.
    rise_time_s : float
        10-90 % rise time, s (exact to 1 ns).
    reaction_s : float
        First instant the infeed has moved (by 1e-9 of the step), s.
    """

    direction: str
    step_fraction: float
    t_s: np.ndarray
    normalised: np.ndarray
    rise_time_s: float
    reaction_s: float

    @property
    def label(self) -> str:
        return f"{self.direction} {100 * self.step_fraction:g} %"


@dataclass(frozen=True)
class DerModelReport:
    """A DER's detailed model and the reference PT1, step by step.

    Attributes
    ----------
    der_id, der_type : str
    p_inst_w, t_delay_s, t_rise_s : float
        From the config.
    params : dataclass
        The detailed model's default parameters.
    responses, reference : tuple of StepResponse
        Detailed model and reference PT1 (same steps, in the same order).
    """

    der_id: str
    der_type: str
    p_inst_w: float
    t_delay_s: float
    t_rise_s: float
    params: object
    responses: tuple
    reference: tuple

    @property
    def model_name(self) -> str:
        return MODEL_NAMES[self.der_type]

    def to_json(self) -> dict:
        """Plain data: the config values, the parameters and every step's figures."""
        def step(r: StepResponse) -> dict:
            return {"direction": r.direction, "step_pct": 100 * r.step_fraction,
                    "rise_time_s": r.rise_time_s, "reaction_s": r.reaction_s}
        params = {k: (None if isinstance(v, float) and math.isinf(v) else v)
                  for k, v in dataclasses.asdict(self.params).items()}
        return {"id": self.der_id, "type": self.der_type, "p_inst_w": self.p_inst_w,
                "t_delay_s": self.t_delay_s, "t_rise_s": self.t_rise_s,
                "model": self.model_name, "params": params,
                "steps": [step(r) for r in self.responses],
                "reference_pt1": [step(r) for r in self.reference]}


def step_response(params, p_inst_w: float, direction: str, step_fraction: float,
                  t_end_s: float, n: int = 600) -> StepResponse:
    """The response of the model of ``params`` to a setpoint step from
    ``BASE_FRACTION · p_inst_w`` by ``step_fraction · p_inst_w`` up or down, sampled at
    ``n + 1`` instants over ``[0, t_end_s]`` (which must include the 90 % crossing)."""
    g = normalised(functions(params), params, *_levels(p_inst_w, direction, step_fraction))
    t = np.linspace(0.0, t_end_s, n + 1)
    y = np.array([g(x) for x in t])
    t10, t90 = first_crossing(g, t, y, 0.1), first_crossing(g, t, y, 0.9)
    if t90 is None:
        raise ValueError(f"{direction} step of {step_fraction:g} P_inst: no 90 % crossing "
                         f"within {t_end_s:g} s")
    moved = first_crossing(g, t, y, _MOVED)
    return StepResponse(direction, step_fraction, t, y, t90 - t10, moved)


def der_model_report(der, steps=STEP_FRACTIONS) -> DerModelReport:
    """Default detailed model of ``der`` (``id, type, p_inst_w, t_delay_s, t_rise_s``, optional
    ``t_lag_s``) and the reference PT1, each stepped up and down by every size in ``steps``.

    Every limit of the models scales with P_inst, so the normalised responses depend on
    (type, T_delay, T_rise, T_lag) only: they are computed once per such set (at 1 W).
    """
    t_lag = getattr(der, "t_lag_s", der.t_rise_s / math.log(9.0))
    responses, reference = _normalised_runs(der.type, der.t_delay_s, der.t_rise_s, t_lag,
                                            tuple(steps))
    params = default_params(der.type, der.p_inst_w, der.t_delay_s, der.t_rise_s)
    return DerModelReport(der.id, der.type, der.p_inst_w, der.t_delay_s, der.t_rise_s, params,
                          responses, reference)


@lru_cache(maxsize=32)
def _normalised_runs(der_type: str, t_delay_s: float, t_rise_s: float, t_lag_s: float,
                     steps: tuple) -> tuple[tuple, tuple]:
    """Responses of the default model and of the PT1 at P_inst = 1 W, on one time span: until
    1.25 times the latest 90 % crossing of them all, at least ``t_delay_s + 3.5 t_rise_s``."""
    models = (default_params(der_type, 1.0, t_delay_s, t_rise_s),
              reference_pt1(1.0, t_delay_s, t_lag_s))
    runs = [(d, s) for s in steps for d in ("up", "down")]
    t_end = t_delay_s + 3.5 * t_rise_s
    for params in models:
        for d, s in runs:
            g = normalised(functions(params), params, *_levels(1.0, d, s))
            t90 = None
            while t90 is None:
                t90 = crossing_time(g, 0.9, t_end, n=200)
                t_end = t_end if t90 is not None else 2.0 * t_end
            t_end = max(t_end, 1.25 * t90)
    return tuple(tuple(step_response(p, 1.0, d, s, t_end) for d, s in runs) for p in models)


def _levels(p_inst_w: float, direction: str, step_fraction: float) -> tuple[float, float]:
    p0 = BASE_FRACTION * p_inst_w
    return p0, p0 + (1 if direction == "up" else -1) * step_fraction * p_inst_w
