"""What a gain table depends on, and its hash: the key a table is bound to
(docs/tuning.md#what-a-table-is-bound-to).

A table's gains and weights are a function of the loop the tuning solves, not of the config
file: the DERs (id, type, installed power, delay and rise time, in file order), the loop's
delays (``t_com_s``, ``t_meas_s`` and the ``T_com`` the tuning uses, which holds half a PI
period when ``constraints.sampled_pi``), what ``t_rise_s`` means (``t_rise_is``) and the
constraints. :func:`design_document` is that content as plain data, every number a float (so
that ``2000000`` and ``2.0e6`` are the same design); :func:`design_sha256` its SHA-256 over
canonical JSON. Everything else in a config — the scenario, the grid model and its limits, the
runtime, the links' jitter and faults, comments and formatting — may change without
invalidating the table. (A table tuned for the scenario's subsets only lacks the subsets a new
scenario adds: the CPFC tunes those on demand.)

:func:`first_difference` names the first field in which two design documents differ, for a
one-line refusal (``ders[3].t_delay_s: 2 in the table, 1.5 in the config``).
"""

from __future__ import annotations

import hashlib
import json

__all__ = ["DESIGN_FORMAT", "design_document", "design_sha256", "document_sha256",
           "first_difference"]

#: bumped when the design document's content changes meaning
DESIGN_FORMAT = 1

_DER_FIELDS = ("id", "type", "p_inst_w", "t_delay_s", "t_rise_s")


def _plain(value):
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return str(value)


def design_document(config) -> dict:
    """The design-relevant content of ``config`` (:class:`adnmesh.config.Config`), plain data;
    a reactive view's (:func:`adnmesh.reactive.reactive_view`) says ``quantity: Q`` (a P
    document says nothing, as before there was a Q)."""
    quantity = {"quantity": "Q"} if getattr(config, "quantity", "P") == "Q" else {}
    return _plain({
        **quantity,
        "format": DESIGN_FORMAT,
        "ders": [{f: getattr(der, f) for f in _DER_FIELDS} for der in config.ders],
        "t_com_s": config.t_com_s,
        "t_meas_s": config.t_meas_s,
        "design_t_com_s": config.design_t_com_s,
        "t_rise_is": config.t_rise_is,
        # an uncertainty set is part of the design; none leaves the document as before
        "constraints": config.constraints.model_dump(exclude_none=True),
    })


def document_sha256(document: dict) -> str:
    """SHA-256 (hex) of a design document over canonical JSON (sorted keys, no spaces)."""
    text = json.dumps(document, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


def design_sha256(config) -> str:
    """SHA-256 (hex) of :func:`design_document` of ``config``."""
    return document_sha256(design_document(config))


def first_difference(table: object, config: object, at: str = "") -> str | None:
    """Where two design documents first differ, as ``path: A in the table, B in the config``
    (None if they are equal)."""
    if isinstance(table, dict) and isinstance(config, dict):
        for key in [*config, *(k for k in table if k not in config)]:
            if key not in table:
                return f"{at}{key}: missing in the table"
            if key not in config:
                return f"{at}{key}: only in the table"
            found = first_difference(table[key], config[key], f"{at}{key}.")
            if found:
                return found
        return None
    if isinstance(table, list) and isinstance(config, list):
        for i, (a, b) in enumerate(zip(table, config)):
            found = first_difference(a, b, f"{at.rstrip('.')}[{i}].")
            if found:
                return found
        if len(table) != len(config):
            return f"{at.rstrip('.')}: {len(table)} in the table, {len(config)} in the config"
        return None
    if table == config:
        return None
    return f"{at.rstrip('.')}: {_show(table)} in the table, {_show(config)} in the config"


def _show(value) -> str:
    if isinstance(value, float):
        return f"{value:.12g}"                  # 2000000, 0.105 (not 0.10500000000000001)
    text = repr(value) if isinstance(value, str) else str(value)
    return text if len(text) <= 40 else text[:37] + "..."
