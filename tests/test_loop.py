"""evaluate(): invariance, unstable loops, vectorisation."""
import numpy as np
import pytest

from adnmesh.loopmodel.evaluation import evaluate

from loops import gains

#: the peak frequency sits on a flat maximum: located to ~sqrt(machine epsilon)
RTOL = {"disk_omega": 1e-6}
#: in a batch the step may be coarsened at other instants than alone (see stepresp): the
#: time-domain figures then agree within the simulation's error, not to the last digit
BATCH_RTOL = dict(RTOL, **{k: 1e-5 for k in ("overshoot_pct", "rise_time_s", "settling_time_s",
                                              "settling_time_2pct_s", "peak", "peak_time_s")})

FIGURES = ("disk_margin", "disk_omega", "disk_phase_margin_deg", "gain_margin",
           "phase_margin_deg", "delay_margin_s", "overshoot_pct", "rise_time_s",
           "settling_time_s", "settling_time_2pct_s", "peak", "peak_time_s")


@pytest.mark.parametrize("name", ["wt", "pv_chp", "all"])
def test_scaling_power_and_gains_changes_no_figure(name):
    plant, kp, ki = gains(name)
    a = evaluate(plant, kp, ki)
    for c in (1e-3, 7.0):
        b = evaluate(plant.scaled(c), kp / c, ki / c)
        assert b.stable[0]
        for key in FIGURES:
            np.testing.assert_allclose(getattr(b, key), getattr(a, key), rtol=RTOL.get(key, 1e-9), err_msg=key)


def test_unstable_loop_is_reported_unstable_without_margins():
    plant, kp, ki = gains("wt")
    f = evaluate(plant, 30 * kp, 30 * ki)
    assert not f.stable[0] and f.certified[0] and f.unstable_poles[0] >= 2
    assert f.disk_margin[0] == 0.0
    for key in ("gain_margin", "phase_margin_deg", "delay_margin_s", "rise_time_s",
                "overshoot_pct", "settling_time_s"):
        assert np.isnan(getattr(f, key)[0]), key
    row = f.row(0)
    assert row["stable"] is False and row["rise_time_s"] is None


def test_vectorised_equals_one_by_one():
    plant, kp, ki = gains("wt_chp")
    scale = np.array([0.5, 1.0, 1.5, 8.0])
    many = evaluate(plant, kp * scale, ki * scale[::-1])
    for i, s in enumerate(scale):
        one = evaluate(plant, kp * s, ki * scale[::-1][i])
        for key in ("stable",) + FIGURES:
            np.testing.assert_allclose(getattr(many, key)[i], getattr(one, key)[0],
                                       rtol=BATCH_RTOL.get(key, 1e-9),
                                       err_msg=key)


def test_per_candidate_plants_in_one_batch():
    """Gains of shape (M, G): several subsets evaluated in lock-step."""
    from adnmesh.loopmodel.plant import Plant
    plant, kp, ki = gains("all")
    rows = np.array([plant.gains_w, plant.gains_w * [1, 0, 1], plant.gains_w * [0, 1, 0]])
    batch = Plant(plant.actuators, rows, plant.t_com_s, plant.t_meas_s)
    kps, kis = kp * rows.sum(1) / rows[0].sum(), ki * rows.sum(1) / rows[0].sum()
    f = evaluate(batch, 1 / rows.sum(1) * kp * rows[0].sum(), 1 / rows.sum(1) * ki * rows[0].sum())
    for i in range(3):
        single = Plant(plant.actuators, rows[i], plant.t_com_s, plant.t_meas_s)
        g = evaluate(single, kp * rows[0].sum() / rows[i].sum(), ki * rows[0].sum() / rows[i].sum())
        for key in ("stable",) + FIGURES:
            np.testing.assert_allclose(getattr(f, key)[i], getattr(g, key)[0],
                                       rtol=BATCH_RTOL.get(key, 1e-9),
                                       err_msg=key)
    del kps, kis
