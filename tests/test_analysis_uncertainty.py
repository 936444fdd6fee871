"""Model-uncertainty analysis: scan logic, limits against direct computations, RHPZ, outputs."""
import json
import math

import numpy as np
import pytest
from scipy.optimize import brentq

from adnmesh.analysis import plots, report
from adnmesh.analysis.subset_loops import deployed_batch
from adnmesh.analysis.uncertainty import (B_RANGE, Limit, _scan, analyze_uncertainty,
                                          round_sig)
from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.loopmodel.step_response import simulate_step

from coarse_table import example

# SGen5 alone (CHP, 0.31 MW, T = 24.57 s / ln 9, reaction time 1 s) with an aggressive K_P:
# fine with the slow nominal lag, unstable once the lag is much faster (K K_P = 1.25 > 1)
KP_CHP, KI_CHP = 4.024e-6, 3.165e-7


class _Threshold:
    """Fake evaluator: row i fails where ``b`` is beyond ``lo[i]`` / ``hi[i]``."""

    def __init__(self, lo, hi):
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        self.calls = []

    def fails(self, quantity, model, b, rows):
        self.calls.append((b, rows.size))
        bad = (b <= self.lo[rows]) | (b >= self.hi[rows])
        return bad, bad


def _scan_fake(lo, hi, direction, edge=None):
    ev = _Threshold(lo, hi)
    names = [(f"s{i}",) for i in range(len(lo))]
    edge = edge or (B_RANGE[0] if direction == "down" else B_RANGE[1])
    return _scan(ev, "pt1", "stability", direction, np.arange(len(lo)), edge, names, []), ev


def test_scan_brackets_then_bisects_to_three_digits():
    lim, ev = _scan_fake([0.0123, 0.5, 0.02], [3.14159, 7.0, 50.0], "up")
    assert lim.status == "found" and lim.b == 3.14 and lim.subsets == ("s0",)
    assert lim.b_pass < 3.14159 <= lim.b_fail and round_sig(lim.b_pass) == 3.14
    assert [b for b, _ in ev.calls[:3]] == [1.0, 2.0, 4.0]          # bracket by factors of 2
    assert all(n == 1 for _, n in ev.calls[3:])                     # bisection: witnesses only
    lim, _ = _scan_fake([0.0123, 0.5, 0.02], [3.14159, 7.0, 50.0], "down")
    assert lim.b == 0.5 and lim.subsets == ("s1",)
    lim, _ = _scan_fake([0.0123, 0.0456, 0.02], [3.14159, 7.0, 50.0], "down")
    assert lim.b == 0.0456 and lim.text() == "0.0456"


def test_scan_reports_beyond_the_range_and_failure_at_nominal():
    lim, ev = _scan_fake([0.001], [1000.0], "up")
    assert lim.status == "beyond" and lim.b is None and lim.text() == "> 100"
    assert ev.calls[-1][0] == B_RANGE[1]
    lim, ev = _scan_fake([0.001], [1000.0], "down")
    assert lim.text() == "< 0.01" and ev.calls[-1][0] == B_RANGE[0]
    lim, _ = _scan_fake([0.001, 1.5], [1000.0, 2.0], "up")          # row 1 fails at b = 1
    assert lim.status == "at nominal" and lim.b == 1.0 and lim.subsets == ("s1",)
    lim, ev = _scan_fake([0.001], [1000.0], "up", edge=5.0)        # bounded by a known limit
    assert lim.status == "beyond" and ev.calls[-1][0] == 5.0


def _direct_pt1_limit(k_w, kp, ki, t_lag_s, delay_s):
    """b at which the single-DER PT1 loop's Nyquist curve passes through -1 (b < 1 side).

    ``L = K (kp + ki / (j w)) exp(-j w delay) / (1 + j w b T)``: ``|L| = 1`` gives
    ``b(w) = sqrt(K^2 (kp^2 + ki^2 / w^2) - 1) / (w T)``; the phase condition
    ``arg L = -(2k + 1) pi`` then is one equation in w.
    """
    def b_of(w):
        return math.sqrt(k_w ** 2 * (kp ** 2 + ki ** 2 / w ** 2) - 1.0) / (w * t_lag_s)

    def phase(w):
        return -math.atan2(ki / w, kp) - w * delay_s - math.atan(w * b_of(w) * t_lag_s)

    ws = np.geomspace(1e-3, 1e3, 20001)
    ws = ws[k_w ** 2 * (kp ** 2 + ki ** 2 / ws ** 2) > 1.0 + 1e-12]
    found = []
    for k in range(0, 20):
        target = -(2 * k + 1) * math.pi
        f = np.array([phase(w) - target for w in ws])
        for i in np.nonzero(np.sign(f[:-1]) != np.sign(f[1:]))[0]:
            w = brentq(lambda x: phase(x) - target, ws[i], ws[i + 1], xtol=1e-14)
            found.append(b_of(w))
    below = [b for b in found if b < 1.0]
    return max(below)


def test_single_der_pt1_stability_limit_agrees_with_direct_computation():
    config = example("wt-chp")
    batch = deployed_batch(config, [("SGen5",)], KP_CHP, KI_CHP)
    res = analyze_uncertainty(batch, 5.0, models=("pt1",), quantities=("stability",))
    down, up = res.models[0].limits["stability"]
    der = config.ders_by_id(["SGen5"])[0]
    b_direct = _direct_pt1_limit(der.p_inst_w, KP_CHP, KI_CHP, config.t_lag_s(der),
                                 der.t_delay_s + config.design_t_com_s + config.t_meas_s)
    assert down.status == "found" and down.subsets == ("SGen5",)
    assert down.b_fail <= b_direct <= down.b_pass
    assert down.b == round_sig(b_direct) == 0.0327     # T_com with the PI's half-sample hold
    assert up.text() == "> 100"
    # and the loop's own stability test agrees on either side of the limit
    for b, stable in ((b_direct * 1.001, True), (b_direct * 0.999, False)):
        f = evaluate(batch.plant("pt1", b), KP_CHP, KI_CHP, time_domain=False)
        assert bool(f.stable[0]) is stable


def test_doubling_limits_are_measured_against_the_nominal_pt1_values():
    config = example("wt-chp")
    batch = deployed_batch(config, [("SGen5",)], KP_CHP, KI_CHP)
    res = analyze_uncertainty(batch, 5.0, models=("pt2",),
                              quantities=("stability", "settling_time"))
    nominal = evaluate(batch.plant(), KP_CHP, KI_CHP, classical=False)
    assert res.nominal_settling_s[0] == pytest.approx(nominal.settling_time_s[0])
    stab_up = res.models[0].limits["stability"][1]
    settle_up = res.models[0].limits["settling_time"][1]
    assert settle_up.status == "found" and not settle_up.unstable
    assert 1.0 < settle_up.b_fail < stab_up.b_fail           # doubles before it goes unstable
    ts = {b: evaluate(batch.plant("pt2", b), KP_CHP, KI_CHP, classical=False).settling_time_s[0]
          for b in (settle_up.b_pass, settle_up.b_fail)}
    assert ts[settle_up.b_pass] < 2 * nominal.settling_time_s[0] <= ts[settle_up.b_fail]


def test_rhpz_step_response_starts_in_the_wrong_direction():
    config = example("wt-chp")
    batch = deployed_batch(config, [("SGen1",)], 1.078e-7, 3.502e-7)
    delay = 0.01 + config.design_t_com_s                          # P_Y reaches the DER after this
    for model, sign in (("rhpz", -1), ("pt1", +1), ("pt2", +1)):
        t, y = simulate_step(batch.plant(model), 1.078e-7, 3.502e-7, 1.0)
        early = y[0, (t > delay) & (t < delay + 0.1)]
        assert np.all(y[0, t <= delay] == 0.0)
        assert np.sign(early[np.argmax(np.abs(early))]) == sign, model
    t, y = simulate_step(batch.plant("rhpz"), 1.078e-7, 3.502e-7, 1.0)
    assert y[0].min() < -1e-3


def test_identical_subsets_are_named_together_and_outputs_written(tmp_path):
    config = example("two-wt")
    # gains scaled by 1/P_inst (as a table tuned on normalised plants has them): one loop
    batch = deployed_batch(config, [("SGen1",), ("SGen2",), ("SGen1", "SGen2")],
                           [2e-7, 2e-7, 1e-7], [6e-7, 6e-7, 3e-7])
    res = analyze_uncertainty(batch, 5.0, "adaptive", models=("pt1", "rhpz"),
                              quantities=("stability",))
    assert res.loop_classes == 1
    down = res.models[1].limits["stability"][0]           # RHPZ: faster lag, larger s-gain
    assert down.status == "found" and set(down.subsets) == {"SGen1", "SGen2", "SGen1,SGen2"}
    md = report.uncertainty_markdown([res])
    assert "| RHPZ |" in md and f"| {down.text()} |" in md and "{SGen1} (+2 more)" in md
    doc = json.loads(json.dumps(res.to_json(), allow_nan=False))
    assert doc["models"][1]["stability"]["b_min"]["b"] == down.b
    path = plots.plot_uncertainty([res, res], tmp_path / "u.png")
    assert path.stat().st_size > 20_000


def test_limit_text():
    assert Limit("stability", "down", "found", 0.0312, 0.0313, 0.0312).text() == "0.0312"
    assert Limit("stability", "up", "beyond", None, 100.0, None).text() == "> 100"
    assert Limit("rise_time", "up", "at nominal", 1.0, 1.0, 1.0).text().startswith("1 ")
