"""Default dynamics per DER type and the DER type of a grid's generator types.

:data:`DEFAULT_DYNAMICS` gives ``(t_delay_s, t_rise_s, source)`` per DER type of the config
(``t_rise_s`` the 10-90 % rise time of the reference model, docs/method.md#reference-model):

- **WT, CHP, PV**: the paper's values (docs/method.md#reference-case): wind turbine 0.01 s /
  0.515 s, CHP (SimBench's biomass plants) 1.0 s / 24.57 s, PV 0.01 s / 0.1 s.
- **HYDRO**: 0.5 s / 10 s, assumed for a small run-of-river plant whose governor follows a
  setpoint: the usual HYGOV parameters (water starting time T_w 1 s, gate servo T_g 0.5 s,
  governor T_r 5 s) give a setpoint response of some seconds with the non-minimum-phase dip of
  the penstock, and ENTSO-E's frequency containment reserve asks for full activation within
  30 s, an upper bound. Not a measured plant: override it with the plant's own figure.
- **GEN**: 1.0 s / 10 s, assumed for a generator of unknown kind (a conservative lag).

Every value can be overridden per type and per DER (``adnmesh init --dynamics``,
``--der-dynamics``) or edited in the written config.
"""

from __future__ import annotations

__all__ = ["DEFAULT_DYNAMICS", "der_type_of"]

DEFAULT_DYNAMICS: dict[str, tuple[float, float, str]] = {
    "WT": (0.01, 0.515, "the paper"),
    "CHP": (1.0, 24.57, "the paper"),
    "PV": (0.01, 0.1, "the paper"),
    "HYDRO": (0.5, 10.0, "assumed: HYGOV-type governor, see docs/models.md"),
    "GEN": (1.0, 10.0, "assumed: generator of unknown kind"),
}


def der_type_of(kind: str, profile: str = "") -> str:
    """The DER type of a generator of SimBench/pandapower type ``kind`` (e.g. ``Wind_MV``,
    ``Biomass_MV``, ``PV_MV``, ``Hydro_MV``, ``lv_RES``, ``wye``): by the words in it, else by
    its ``profile`` (SimBench's ``WP4``, ``PV3``, ``BM1``, ``Hydro2``); ``lv_RES`` (aggregated
    low-voltage generation, mostly rooftop PV) is PV; anything else GEN."""
    for text in (kind, profile):
        lowered = text.lower()
        if "wind" in lowered or lowered.startswith("wp"):
            return "WT"
        if "biomass" in lowered or "chp" in lowered or lowered.startswith("bm"):
            return "CHP"
        if "pv" in lowered or "solar" in lowered:
            return "PV"
        if "hydro" in lowered or "water" in lowered:
            return "HYDRO"
    if kind.lower().startswith("lv_res"):
        return "PV"
    return "GEN"
