"""Independent reference for the loop numerics: python-control with Padé delay models
(built by :mod:`adnmesh.loopmodel.control_models`, the models users take into python-control).

Each forward path's delay ``T_com + T_delay,g`` and the measurement delay ``T_meas`` are
replaced by Padé approximants of order ``order`` (>= 10 in the tests). Two delays of one path
are merged into one approximant because an order-10 Padé of a 10 ms delay alone is numerically
useless (coefficients ~1e-20). The state-space models are diagonally balanced before time
simulation: without it, the companion realisation of a 1.1 s order-10 Padé overflows in expm.
"""
from __future__ import annotations

import control as ct
import numpy as np

from adnmesh.loopmodel.control_models import loop_models
from adnmesh.loopmodel.plant import Plant


def reference_models(plant: Plant, kp: float, ki: float, order: int = 10):
    """(L, G_CL) of the loop as python-control state-space models with Padé delays."""
    return loop_models(plant, kp, ki, order)


def reference_figures(plant: Plant, kp: float, ki: float, t_end_s: float | None = None,
                      dt: float = 1e-3, order: int = 10) -> dict:
    """Figures of merit computed the python-control way (dense grids, no refinement)."""
    loop, closed = reference_models(plant, kp, ki, order)
    poles = closed.poles()
    omega = np.geomspace(1e-4, 1e2, 30001)
    dm, _, _ = ct.disk_margins(loop, omega)
    gm, pm, _, wpc, wgc, _ = ct.stability_margins(ct.frd(loop, omega))
    out = {
        "stable": bool(np.max(poles.real) < 0), "max_pole_real": float(np.max(poles.real)),
        "disk_margin": float(dm), "gain_margin": float(gm), "phase_margin_deg": float(pm),
        "gain_margin_omega": float(wpc), "phase_margin_omega": float(wgc),
        "delay_margin_s": float(np.radians(pm) / wgc),
    }
    if t_end_s is None:
        return out
    t = np.arange(0.0, t_end_s + dt / 2, dt)
    resp = ct.step_response(closed, t)
    y = np.squeeze(resp.outputs)
    info5 = ct.step_info(y, t, yfinal=1.0, SettlingTimeThreshold=0.05)
    info2 = ct.step_info(y, t, yfinal=1.0, SettlingTimeThreshold=0.02)
    return out | {
        "overshoot_pct": float(info5["Overshoot"]), "rise_time_s": float(info5["RiseTime"]),
        "settling_time_s": float(info5["SettlingTime"]),
        "settling_time_2pct_s": float(info2["SettlingTime"]), "peak": float(info5["Peak"]),
        "peak_time_s": float(info5["PeakTime"]), "t": t, "y": y,
    }
