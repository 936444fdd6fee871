"""The dynamics a DER runs with in a time-domain run, from the config.

``runtime.der_models: reference`` gives every DER the reference model
(docs/method.md#reference-model: a PT1 behind its dead time, the model tuning and the
analyses use, :mod:`adnmesh.dermodels.pt1`);
``detailed`` gives it its type's detailed model (docs/method.md#detailed-der-models,
:mod:`adnmesh.dermodels`: WT Type
4B-like, CHP, PV) with the defaults that reproduce the config's ``t_delay_s`` and ``t_rise_s``,
the DER's own overrides (its ``model:`` mapping) and its available power as the upper limit.

The detailed WT and CHP models are calibrated by a root finder (scipy's ``brentq``); ``adnmesh
up`` calibrates them once and hands each DER process its parameters (:func:`params_json`,
:func:`params_from_json`), so that a DER process loads no scipy.
"""

from __future__ import annotations

import dataclasses
import json

from adnmesh import dermodels
from adnmesh.dermodels.pt1 import PT1DelayParams
from adnmesh.config import DER, Config
from adnmesh.errors import ConfigError

__all__ = ["check_der_models", "der_params", "params_from_json", "params_json",
           "usable_available_w"]

_PARAM_TYPES = {t.__name__: t for t in (dermodels.WTParams, dermodels.CHPParams,
                                        dermodels.PVParams, PT1DelayParams)}


def usable_available_w(der: DER, p_avail_w: float | None) -> float:
    """The available power a DER runs with, W: ``p_avail_w`` up to its installed power (the
    installed power if None)."""
    return der.p_inst_w if p_avail_w is None else min(p_avail_w, der.p_inst_w)


def params_json(params) -> str:
    """Model parameters as one line of JSON (their type's name and every field; floats exact,
    ``math.inf`` as ``Infinity``)."""
    fields = {f.name: getattr(params, f.name) for f in dataclasses.fields(params) if f.init}
    return json.dumps({"model": type(params).__name__, **fields})


def params_from_json(text: str):
    """The parameters :func:`params_json` wrote.

    Raises
    ------
    ValueError
        Not such a text.
    """
    try:
        found = json.loads(text)
        return _PARAM_TYPES[found.pop("model")](**found)
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise ValueError(f"not model parameters: {exc}") from None


def der_params(der: DER, config: Config, p_avail_w: float):
    """The model parameters of ``der`` (see the module docstring).

    Raises
    ------
    ConfigError
        An override names a parameter the DER's model does not have, or has a bad value.
    """
    if config.runtime.der_models == "reference":
        return dermodels.reference_pt1(der.p_inst_w, der.t_delay_s, config.t_lag_s(der))
    params = dermodels.default_params(der.type, der.p_inst_w, der.t_delay_s, der.t_rise_s,
                                      p_max_w=p_avail_w)
    if not der.model:
        return params
    try:
        return dermodels.params_with(params, **der.model)
    except (ValueError, TypeError) as exc:
        index = config.der_ids().index(der.id)
        raise ConfigError(f"{config.path}: ders[{index}].model: {exc}") from None


def check_der_models(config: Config, available: dict[str, float]) -> None:
    """Build every DER's parameters once, so that a bad override is a one-line error before a
    run starts."""
    for der in config.ders:
        if der.p_sched_w > available[der.id]:
            index = config.der_ids().index(der.id)
            raise ConfigError(f"{config.path}: ders[{index}].p_sched_w: more than the DER can "
                              f"deliver ({available[der.id]:g} W at the study case), got "
                              f"{der.p_sched_w:g}")
        der_params(der, config, available[der.id])
