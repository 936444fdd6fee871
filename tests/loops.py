"""Loops used across the numerics tests: SimBench subsets with reasonable PI gains.

Gains are given normalised (``k_n = K * sum P_inst``, dimensionless and 1/s) and converted to
1/W and 1/(W s) by :func:`gains`.
"""
from __future__ import annotations

from pathlib import Path

from adnmesh.config import load_config
from adnmesh.loopmodel.plant import plant_from_ders

CONFIG = load_config(Path(__file__).resolve().parent.parent / "configs" / "simbench.yaml")

#: name -> (DER ids, kp_n, ki_n 1/s): WT-only, CHP-only, PV+CHP, WT+CHP and all eleven
LOOPS = {
    "wt": (["SGen1", "SGen2"], 0.108, 0.595),
    "chp": (["SGen5", "SGen6", "SGen11"], 0.914, 0.101),
    "pv_chp": (["SGen9", "SGen11"], 0.353, 0.0707),
    "wt_chp": (["SGen3", "SGen5"], 0.353, 0.292),
    "all": (list(CONFIG.der_ids()), 0.220, 0.848),
}


def plant(ids, **kw):
    return plant_from_ders(CONFIG.ders_by_id(ids), CONFIG.design_t_com_s, CONFIG.t_meas_s, **kw)


def gains(name):
    """(plant, kp 1/W, ki 1/(W s)) of a named loop."""
    ids, kpn, kin = LOOPS[name]
    p = plant(ids)
    total = float(p.total_gain_w)
    return p, kpn / total, kin / total
