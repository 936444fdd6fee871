"""Reactive power control (docs/method.md#reactive-power): the DERs' P-Q capability, the Q
services, the Q table against python-control, the Q loop in a run beside the P loop, and the
coupled 2x2 loop against a python-control model of both loops with Padé delays."""

from __future__ import annotations

import math
from pathlib import Path

import control as ct
import msgspec
import numpy as np
import pytest
import yaml

from adnmesh.config import QU, load_config
from adnmesh.control.cpfc_controller import GainSchedule
from adnmesh.control.der_controller import DERController
from adnmesh.errors import ConfigError
from adnmesh.loopmodel.plant import plant_from_ders
from adnmesh.reactive import (Capability, capability_of, limit_pq, q_of_cos_phi, q_of_u,
                              q_reference, reactive_view)
from adnmesh.results.summary import RunSeries, summarize
from adnmesh.sim.local import run_local
from adnmesh.tuning import tune_subset
from adnmesh.wire.envelope import decode
from adnmesh.wire.keys import Keys
from adnmesh.wire.messages import QY, Envelope
from pade_reference import reference_figures

REPO = Path(__file__).resolve().parent.parent
SIMBENCH_PQ = REPO / "configs" / "examples" / "simbench-pq.yaml"
TAN_095 = math.tan(math.acos(0.95))          # 0.3287: Q/P_inst at cos phi 0.95


def _config(tmp_path: Path, name: str = "pq", **changes):
    """A small P-Q case (two WTs and a CHP of SimBench 1-MV-rural, its grid at lW) with
    ``changes`` merged into the document."""
    document = {
        "grid": "pq-test", "simbench_code": "1-MV-rural--0-no_sw",
        "t_com_s": 0.1, "t_meas_s": 0.1,
        "ders": [
            {"id": "SGen1", "type": "WT", "p_inst_w": 2.0e6, "t_delay_s": 0.01,
             "t_rise_s": 0.515, "sgen": "MV1.101 SGen 1", "p_sched_w": 1.0e6},
            {"id": "SGen2", "type": "WT", "p_inst_w": 2.0e6, "t_delay_s": 0.01,
             "t_rise_s": 0.515, "sgen": "MV1.101 MV SGen 2", "p_sched_w": 1.0e6},
            {"id": "SGen5", "type": "CHP", "p_inst_w": 0.31e6, "t_delay_s": 1.0,
             "t_rise_s": 24.57, "sgen": "MV1.101 MV SGen 5"}],
        "scenario": {"duration_s": 40, "p_ref_steps": [{"t_s": 5, "delta_w": 0.5e6}],
                     "q_ref_steps": [{"t_s": 20, "delta_var": 0.4e6}]},
        "grid_model": {"study_case": "lW"},
        "reactive": {},
    }
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(document.get(key), dict):
            document[key] = {**document[key], **value}
        else:
            document[key] = value
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(document))
    return load_config(path)


# --- capability ---------------------------------------------------------------------------------


def test_presets_give_the_reactive_range_at_p_inst_and_a_der_may_override_them(tmp_path):
    config = _config(tmp_path)
    cap = capability_of(config.ders[0], config.reactive)
    assert cap.q_max_var == pytest.approx(2e6 * TAN_095, rel=1e-12)
    assert cap.q_min_var == pytest.approx(-2e6 * TAN_095, rel=1e-12)
    assert cap.s_va == 2e6 and cap.capacity_var == pytest.approx(4e6 * TAN_095)
    der = config.ders[0].model_copy(update={"cos_phi_over": 0.9, "cos_phi_under": 1.0,
                                            "s_inst_va": 2.2e6})
    cap = capability_of(der, config.reactive)
    assert (cap.q_min_var, cap.s_va) == (0.0, 2.2e6)
    assert cap.q_max_var == pytest.approx(2e6 * math.tan(math.acos(0.9)))
    unity = config.ders[0].model_copy(update={"q_capability": "unity"})
    assert capability_of(unity, config.reactive).capacity_var == 0.0


@pytest.mark.parametrize("p, q, priority, want", [
    (0.5e6, 0.2e6, "p", (0.5e6, 0.2e6, 0, 0)),           # inside: untouched
    (0.5e6, 0.9e6, "p", (0.5e6, 0.6e6, 0, 1)),           # Q range
    (0.5e6, -0.9e6, "p", (0.5e6, -0.6e6, 0, -1)),
    (1.2e6, 0.3e6, "p", (1.0e6, 0.3e6, 1, 0)),           # P_avail (not S: 1.0^2 + 0.3^2 < 1.1^2)
    (-0.1e6, 0.0, "p", (0.0, 0.0, -1, 0)),               # P below 0
    (1.0e6, 0.6e6, "p", (1.0e6, math.sqrt(1.1e6**2 - 1e12), 0, 1)),   # S binds: Q gives way
    (1.0e6, 0.6e6, "q", (math.sqrt(1.1e6**2 - 0.36e12), 0.6e6, 1, 0)),  # S binds: P gives way
    (1.0e6, -0.6e6, "q", (math.sqrt(1.1e6**2 - 0.36e12), -0.6e6, 1, 0)),
])
def test_limit_pq_keeps_the_range_and_the_apparent_power_with_the_priority(p, q, priority,
                                                                             want):
    cap = Capability(s_va=1.1e6, q_min_var=-0.6e6, q_max_var=0.6e6)
    got = limit_pq(cap, p, q, 1.0e6, priority)
    assert got[:2] == pytest.approx(want[:2], rel=1e-12, abs=1e-6)
    assert got[2:] == want[2:]
    assert got[0] ** 2 + got[1] ** 2 <= cap.s_va ** 2 * (1 + 1e-12)


def test_bad_reactive_keys_are_one_line_errors(tmp_path):
    with pytest.raises(ConfigError, match=r"ders\[0\]\.s_inst_va: must be at least p_inst_w"):
        _config(tmp_path, ders=[{"id": "A", "type": "WT", "p_inst_w": 2e6, "t_delay_s": 0.01,
                                 "t_rise_s": 0.5, "sgen": "x", "s_inst_va": 1e6}])
    with pytest.raises(ConfigError, match=r"reactive\.capability: must be one of"):
        _config(tmp_path, reactive={"capability": "cos_phi_0.8"})
    with pytest.raises(ConfigError, match=r"ders\[0\]\.cos_phi_over: must be at least 0\.5"):
        _config(tmp_path, ders=[{"id": "A", "type": "WT", "p_inst_w": 2e6, "t_delay_s": 0.01,
                                 "t_rise_s": 0.5, "sgen": "x", "cos_phi_over": 0.1}])
    with pytest.raises(ConfigError, match=r"scenario\.q_ref_steps\[0\]\.delta_var: must be a "
                                          r"non-zero number"):
        _config(tmp_path, scenario={"duration_s": 10, "q_ref_steps": [{"t_s": 1,
                                                                        "delta_var": 0}]})
    far = _config(tmp_path, ders=[{"id": "A", "type": "WT", "p_inst_w": 2e6,
                                   "t_delay_s": 0.01, "t_rise_s": 0.5, "sgen": "x",
                                   "q_sched_var": 0.7e6}])
    with pytest.raises(ConfigError, match=r"ders\[0\]\.q_sched_var: outside its reactive "
                                          r"range \[-657368, 657368\] var, got 700000"):
        reactive_view(far)
    config = _config(tmp_path, reactive={"capability": "unity"})
    with pytest.raises(ConfigError, match="no DER has a reactive power range"):
        reactive_view(config)
    fast = _config(tmp_path, ders=[{"id": "A", "type": "WT", "p_inst_w": 2e6,
                                    "t_delay_s": 0.01, "t_rise_s": 0.5, "sgen": "x",
                                    "t_rise_q_s": 1e-6}])
    with pytest.raises(ConfigError, match=r"reactive dynamics \(t_delay_q_s, t_rise_q_s\): "
                                          "too fast for the loop's delays"):
        reactive_view(fast)


# --- the services ---------------------------------------------------------------------------------


def test_q_of_u_has_a_dead_band_a_slope_and_a_limit():
    qu = QU(u_ref_pu=1.0, dead_band_pu=0.01, slope_var_per_pu=1e8, q_max_var=1e6)
    assert q_of_u(1.0, qu) == q_of_u(1.0099, qu) == q_of_u(0.9901, qu) == 0.0
    assert q_of_u(1.015, qu) == pytest.approx(-0.5e6)          # over-voltage: absorb
    assert q_of_u(0.985, qu) == pytest.approx(+0.5e6)
    assert q_of_u(1.2, qu) == -1e6 and q_of_u(0.5, qu) == 1e6  # limited


def test_cos_phi_gives_q_with_or_against_p():
    assert q_of_cos_phi(10e6, 0.95, True) == pytest.approx(10e6 * TAN_095)
    assert q_of_cos_phi(10e6, 0.95, False) == pytest.approx(-10e6 * TAN_095)
    assert q_of_cos_phi(-10e6, 0.95, True) == pytest.approx(-10e6 * TAN_095)
    assert q_of_cos_phi(5e6, 1.0, True) == 0.0


def test_q_reference_by_mode(tmp_path):
    config = _config(tmp_path)
    assert q_reference(config, 16e6, 1e5) == (1e5, [(20.0, 0.4e6)])
    qu = _config(tmp_path, "qu", reactive={"mode": "q_u", "q_u": {"slope_var_per_pu": 1e8}},
                 scenario={"duration_s": 40, "u_hv_steps": [{"t_s": 10, "u_pu": 1.02},
                                                             {"t_s": 20, "u_pu": 1.005},
                                                             {"t_s": 30, "u_pu": 0.97}]})
    start, steps = q_reference(qu, 16e6, 1e5)
    assert start == 1e5 and [t for t, _ in steps] == [10.0, 20.0, 30.0]
    assert np.cumsum([d for _, d in steps]) == pytest.approx([-1e6, 0.0, 1e6])
    cos = _config(tmp_path, "cos", reactive={"mode": "cos_phi", "cos_phi": 0.95})
    start, steps = q_reference(cos, 16e6, 1e5)
    assert steps[0] == (0.0, pytest.approx(16e6 * TAN_095 - 1e5))
    assert steps[1] == (5.0, pytest.approx(0.5e6 * TAN_095))


# --- the Q table against python-control ---------------------------------------------------------


@pytest.fixture(scope="module")
def simbench_q():
    return reactive_view(load_config(SIMBENCH_PQ))


@pytest.mark.parametrize("which", ["all", "chp_pv"])
def test_the_q_table_entry_meets_the_constraints_in_python_control(simbench_q, which):
    """The Q loop of every DER and of the slower plants only: the tuned entry, as deployed,
    is stable, has the disk margin and overshoot it was certified with, by python-control with
    order-10 Padé delays (an independent evaluation)."""
    view = simbench_q
    ids = [d.id for d in view.ders if which == "all" or d.type != "WT"]
    entry = tune_subset(view, ids)
    assert entry.feasible
    plant = plant_from_ders(view.ders_by_id(ids), view.design_t_com_s, view.t_meas_s,
                            weights=entry.w)
    ref = reference_figures(plant, entry.kp, entry.ki, t_end_s=30.0, dt=1e-3)
    assert ref["stable"]
    assert ref["disk_margin"] >= view.constraints.disk_margin_min - 2e-3
    assert ref["disk_margin"] == pytest.approx(entry.figures["disk_margin"], abs=2e-3)
    assert ref["overshoot_pct"] < view.constraints.overshoot_max_pct
    assert ref["rise_time_s"] == pytest.approx(entry.figures["rise_time_s"], rel=0.01)
    # the quantity's own dynamics: inverters much faster in Q than in P
    assert all(d.t_rise_s <= 0.5 for d in view.ders)
    assert view.ders_by_id(["SGen1"])[0].p_inst_w == pytest.approx(4e6 * TAN_095)


def test_a_q_table_is_bound_to_the_reactive_data(tmp_path, capsys):
    from adnmesh.cli import main
    from adnmesh.tuning.table import load_table

    config = _config(tmp_path)
    out = tmp_path / "q.json"
    assert main(["tune", str(config.path), "--quantity", "q", "--out", str(out),
                 "--workers", "1"]) == 0
    assert "1/var" in capsys.readouterr().out
    table = load_table(out, reactive_view(config))
    assert table.to_json()["design"]["quantity"] == "Q"
    with pytest.raises(ConfigError, match="a table of the Q loop, not of the P loop; tune "
                                          "that with 'adnmesh tune .*pq.yaml'"):
        load_table(out, config)                       # not a P table
    p_out = tmp_path / "p.json"
    assert main(["tune", str(config.path), "--out", str(p_out), "--workers", "1"]) == 0
    with pytest.raises(ConfigError, match="a table of the P loop, not of the Q loop; tune "
                                          "that with 'adnmesh tune .*pq.yaml --quantity q'"):
        load_table(p_out, reactive_view(config))
    entry = table.lookup(["SGen1", "SGen2", "SGen5"])
    assert main(["margins", str(config.path), "--quantity", "q", "--kp", repr(entry.kp),
                 "--ki", repr(entry.ki)]) == 0
    text = capsys.readouterr().out
    assert "Q loop of 3 DER(s)" in text and "1/var" in text and "constraints met: yes" in text


# --- the DER's local controller -------------------------------------------------------------------


def _q_y(q_y: float, w: dict, entry: int = 0) -> Envelope:
    return QY(v=1, type="q_y", src="cpfc", seq=0, t_send_ns=0, t_deliver_ns=0, q_y=q_y,
              q_ref_var=0.0, kp=1e-8, ki=1e-8, entry=entry, w=w)


@pytest.mark.parametrize("priority", ["p", "q"])
def test_a_der_follows_q_y_within_its_capability_and_says_when_it_is_held(tmp_path, priority):
    config = _config(tmp_path, reactive={"priority": priority})
    der = config.ders[0]                              # 2 MW WT at 1 MW, S = 2 MVA
    cap = capability_of(der, config.reactive)
    agent = DERController(der, config, p_avail_w=2e6)
    agent.on_message(0, _q_y(0.1, {"SGen1": 1.0}))
    assert agent.q_setpoint_var == pytest.approx(0.1 * cap.capacity_var)
    state = next(o for o in agent.on_timer(0) if o.key.endswith("/state")).body
    assert state["q_setpoint_var"] == agent.q_setpoint_var and state["q_held"] == 0
    agent.on_message(1, _q_y(0.6, {"SGen1": 1.0}))   # beyond Q_max: held
    assert agent.q_setpoint_var == pytest.approx(cap.q_max_var)
    assert agent._q_clamped == 1
    # P to 1.95 MW: S binds (1.95^2 + 0.657^2 > 2^2)
    agent.p_y, agent.weight, agent.entry = 0.95 / 2.0, 1.0, 0
    agent._update_setpoint(2)
    if priority == "p":
        assert agent.setpoint_w == pytest.approx(1.95e6)
        assert agent.q_setpoint_var == pytest.approx(math.sqrt(4e12 - 1.95e6 ** 2))
    else:
        assert agent.q_setpoint_var == pytest.approx(cap.q_max_var)
        assert agent.setpoint_w == pytest.approx(math.sqrt(4e12 - cap.q_max_var ** 2))
        assert agent._clamped == 1
    # a Q_Y of another entry than the weights it holds is stale
    agent.on_message(3, QY(v=1, type="q_y", src="cpfc", seq=1, t_send_ns=0, t_deliver_ns=0,
                           q_y=0.0, q_ref_var=0.0, kp=1e-8, ki=1e-8, entry=5))
    assert agent.counts["q_stale_commands"] == 1


# --- a run with both loops ------------------------------------------------------------------------


def _series(run) -> RunSeries:
    series = RunSeries()
    for key, payload in run.messages:
        series.take(decode(key, payload))
    return series


@pytest.fixture(scope="module")
def pq_run(tmp_path_factory):
    config = _config(tmp_path_factory.mktemp("pq"))
    run = run_local(config, GainSchedule(config, None))
    return config, run, summarize(_series(run), end_ns=int(40e9))


def test_p_and_q_steps_are_compensated_together_with_the_coupling_in_the_summary(pq_run):
    config, run, summary = pq_run
    (p_step,), (q_step,) = summary.steps, summary.q_steps
    assert (p_step.t_s, p_step.step_w, q_step.t_s, q_step.step_w) == (5.0, 0.5e6, 20.0, 0.4e6)
    for step in (p_step, q_step):
        f = step.figures
        assert f.overshoot_pct < 1.0 and f.settling_time_s < 10.0
        assert abs(step.steady_error_w) < 1e-3 * abs(step.step_w)
    assert q_step.figures.rise_time_s < 2.0
    (check,) = summary.q_design_checks            # what the Q entry was certified for
    assert check.figures and not check.over and check.ders == ("SGen1", "SGen2", "SGen5")
    c = summary.coupling
    assert 0 < c.p_deviation_in_q_steps_w < 0.05 * 0.4e6
    assert 0 < c.q_deviation_in_p_steps_var < 0.2 * 0.5e6
    text = " ".join(str(x) for x in [summary.to_json()["coupling"]])
    assert "p_deviation_in_q_steps_w" in text
    stats = run.nodes["cpfc"].agent.stats()
    assert stats["q_samples"] == stats["samples"] == 4001 and stats["q_rollbacks"] == 0
    # the DERs' reactive set-points entered the power flow: Q_IP moved by the step
    keys = Keys(config.grid)
    states = [decode(k, p) for k, p in run.messages if k == keys.of("der_state", "SGen1")]
    assert states[-1].q_setpoint_var > 0 and states[0].q_var == 0.0


def test_the_run_is_deterministic_and_p_only_configs_send_no_q(pq_run, tmp_path):
    config, run, _ = pq_run
    again = run_local(config, GainSchedule(config, None), end_s=3.0)
    assert again.messages == [m for m in run.messages
                              if decode(*m).t_send_ns <= 3_000_000_000][:len(again.messages)]
    plain = _config(tmp_path, "plain", reactive=None)
    keys = {k for k, _ in run_local(plain, GainSchedule(plain, None), end_s=1.0).messages}
    assert not any(k.endswith(("/q_y", "/q_ref")) for k in keys)


@pytest.mark.parametrize("mode", ["cos_phi", "q_u"])
def test_the_interface_services_move_q_ip(tmp_path, mode):
    changes = {"reactive": {"mode": mode, "cos_phi": 0.999, "cos_phi_q_with_p": False,
                            "q_u": {"slope_var_per_pu": 2e7, "q_max_var": 0.5e6}},
               "scenario": {"duration_s": 15, "p_ref_steps": [{"t_s": 5, "delta_w": 0.5e6}],
                            "q_ref_steps": [], "u_hv_steps": [{"t_s": 5, "u_pu": 1.03}]}}
    config = _config(tmp_path, mode, **changes)
    run = run_local(config, GainSchedule(config, None))
    last = {}
    for key, payload in run.messages:
        message = decode(key, payload)
        last[message.type] = message
    p_ip, q_ip = last["p_ip"].p_ip_w, last["p_ip"].q_ip_var
    if mode == "cos_phi":              # Q against P at cos phi 0.999 (P_IP exports)
        assert q_ip == pytest.approx(-p_ip * math.tan(math.acos(0.999)), rel=2e-3)
    else:                              # 1.03 p.u.: 0.02 p.u. above the band, -0.4 Mvar
        series = _series(run)
        assert series.q_ref_var[-1] - series.q_ref_var[0] == pytest.approx(-0.4e6)
        assert q_ip == pytest.approx(series.q_ref_var[-1], abs=2e3)


# --- P and Q together: the coupled loop against python-control -----------------------------------


def test_the_coupled_loop_against_python_control(tmp_path):
    """det(I + L(jw)) of the coupling analysis equals python-control's Padé model of the 2x2
    loop, and its small-gain verdict holds: the Padé closed loop has no pole in the right
    half-plane; with a grid made to couple strongly, max |M| exceeds 1."""
    from adnmesh.analysis.coupling import coupled_loop, loop_side

    config = _config(tmp_path, reactive={})
    view = reactive_view(config)
    ids = list(config.der_ids())
    p, q = loop_side(config, tune_subset(config, ids)), loop_side(view, tune_subset(view, ids))
    sens = {"SGen1": [0.98, -0.01, -0.08, 1.004], "SGen2": [0.97, -0.012, -0.09, 1.005],
            "SGen5": [0.96, -0.016, -0.085, 1.005]}
    t_com, t_meas = config.design_t_com_s, config.t_meas_s
    result = coupled_loop(p, q, sens, t_com, t_meas)
    assert result.stable and 1e-5 < result.mu < 1e-2

    order = 8
    def path(side, row, d_index):
        act, cap, d = side.actuators[d_index], side.capacity[d_index], side.ids[d_index]
        return (ct.tf([sens[d][row] * cap], [act.t_lag_s, 1.0])
                * ct.tf(*ct.pade(t_com + act.t_delay_s, order)))

    def g(side, row):
        total = path(side, row, 0)
        for i in range(1, len(side.ids)):
            total = total + path(side, row, i)
        return total

    meas = ct.tf(*ct.pade(t_meas, order))
    c_p, c_q = ct.tf([p.kp, p.ki], [1.0, 0.0]), ct.tf([q.kp, q.ki], [1.0, 0.0])
    l11, l12 = meas * g(p, 0) * c_p, meas * g(q, 1) * c_q
    l21, l22 = meas * g(p, 2) * c_p, meas * g(q, 3) * c_q
    omega = np.array([0.01, 0.3, 1.0, 3.0])
    resp = [np.squeeze(sys(1j * omega)) for sys in (l11, l12, l21, l22)]
    det_ref = (1 + resp[0]) * (1 + resp[3]) - resp[1] * resp[2]
    m = np.interp(omega, result.omega, result.m.real) + 1j * np.interp(omega, result.omega,
                                                                          result.m.imag)
    delay = np.exp(-1j * omega * (t_com + t_meas))
    l_p = delay * p.pi(omega) * p.forward(omega, np.array([sens[d][0] for d in p.ids]))
    l_q = delay * q.pi(omega) * q.forward(omega, np.array([sens[d][3] for d in q.ids]))
    det_exact = (1 + l_p) * (1 + l_q) * (1 - m)
    assert det_exact == pytest.approx(det_ref, rel=2e-3)
    # the closed 2x2 loop (Padé): stable, as the small-gain verdict says
    blocks = ct.append(*(ct.ss(x) for x in (g(p, 0), g(p, 2), g(q, 1), g(q, 3))))
    fan_out = ct.ss([], [], [], [[1, 0], [1, 0], [0, 1], [0, 1]])
    sum_up = ct.ss([], [], [], [[1, 0, 1, 0], [0, 1, 0, 1]])
    loop = (ct.append(ct.ss(meas), ct.ss(meas)) * sum_up * blocks * fan_out
            * ct.append(ct.ss(c_p), ct.ss(c_q)))
    closed = ct.feedback(loop, np.eye(2))
    assert np.max(closed.poles().real) < 0
    strong = {d: [v[0], 8.0 * (1 if v[1] > 0 else -1), -20.0, v[3]] for d, v in sens.items()}
    assert coupled_loop(p, q, strong, t_com, t_meas).mu > 1


def test_grid_sensitivities_agree_with_pandapower_runpp(tmp_path):
    """The linearised grid of the coupling analysis: central differences of the fast power flow
    against the same differences of pandapower's runpp on the SimBench net."""
    import pandapower as pp
    import simbench

    from adnmesh.control.operating_point import grid_solver
    from adnmesh.grid.sensitivity import interface_sensitivities
    from adnmesh.grid.simbench_net import apply_operating_point, loads_as_impedances

    config = _config(tmp_path)
    solver = grid_solver(config)
    p = [d.p_sched_w for d in config.ders]
    rows = interface_sensitivities(solver, p, [0.0] * 3, step=1e4)
    assert np.all((rows[0] > 0.9) & (rows[0] < 1.0)) and np.all(rows[3] > 0.99)
    net = simbench.get_simbench_net(config.simbench_code)
    apply_operating_point(net, "lW")
    loads_as_impedances(net)
    index = [int(net.sgen.index[net.sgen.name == d.sgen][0]) for d in config.ders]
    for i, k in enumerate(index):
        net.sgen.at[k, "p_mw"], net.sgen.at[k, "q_mvar"] = p[i] * 1e-6, 0.0

    def exchange():
        pp.runpp(net, calculate_voltage_angles=True, tolerance_mva=1e-10)
        return -net.res_ext_grid.p_mw.sum() * 1e6, -net.res_ext_grid.q_mvar.sum() * 1e6

    for i, k in enumerate(index[:2]):
        for column, field in ((0, "p_mw"), (1, "q_mvar")):
            base = net.sgen.at[k, field]
            net.sgen.at[k, field] = base + 0.01
            hi = exchange()
            net.sgen.at[k, field] = base - 0.01
            lo = exchange()
            net.sgen.at[k, field] = base
            want = [(hi[0] - lo[0]) / 2e4, (hi[1] - lo[1]) / 2e4]
            assert rows[column, i] == pytest.approx(want[0], abs=2e-4)
            assert rows[2 + column, i] == pytest.approx(want[1], abs=2e-4)


def test_a_fault_on_the_q_path_leaves_no_wind_up(tmp_path):
    """SGen1 cut off from the ICT (both ways) for 3 s right after a Q_ref step: the Q loop
    switches to the gains of the DERs left when SI drops SGen1 and back when it returns, as
    the P loop does, and Q_IP settles on Q_ref without an overshoot from a wound-up
    integrator."""
    config = _config(tmp_path, runtime={"faults": [{"kind": "der_offline", "der": "SGen1",
                                                    "t_s": 20.5, "duration_s": 3.0}]},
                     scenario={"duration_s": 40, "p_ref_steps": [],
                               "q_ref_steps": [{"t_s": 20, "delta_var": 0.4e6}]})
    run = run_local(config, GainSchedule(config, None))
    switches: dict[str, list] = {}
    for key, payload in run.messages:
        message = decode(key, payload)
        if message.type in ("p_y", "q_y") and message.switch is not msgspec.UNSET:
            switches.setdefault(message.type, []).append(
                (round(message.t_send_ns / 1e9, 2), sorted(message.w)))
    assert switches["q_y"] == switches["p_y"]
    assert [ders for _, ders in switches["q_y"]] == [["SGen2", "SGen5"],
                                                      ["SGen1", "SGen2", "SGen5"]]
    assert 22.0 < switches["q_y"][0][0] < 23.5 < switches["q_y"][1][0] < 25.0
    series = _series(run)
    t = np.asarray(series.q_ip_t_ns) / 1e9
    q = np.asarray(series.q_ip_var)
    q_ref = series.q_ref_var[-1]
    after = t > 30.0
    assert np.max(np.abs(q[after] - q_ref)) < 0.01 * 0.4e6          # settled on Q_ref
    assert np.max(q[t > 23.5]) < q_ref + 0.05 * 0.4e6                 # no wound-up overshoot


def test_up_runs_both_loops_as_the_in_process_run_does(tmp_path, capsys):
    """The distributed runtime (``adnmesh up``: a process per agent, Zenoh) records the same
    messages as the in-process run, Q loop included, and its summary has the Q figures."""
    import up_runs
    from adnmesh.cli import main

    config_path, table = up_runs.write_case(
        tmp_path, "pq", reactive={"priority": "q"},
        scenario={"duration_s": 6, "p_ref_steps": [{"t_s": 1, "delta_w": 0.5e6}],
                  "q_ref_steps": [{"t_s": 3, "delta_var": -0.3e6}], "availability": []})
    q_table = tmp_path / "q.json"
    assert main(["tune", str(config_path), "--quantity", "q", "--out", str(q_table),
                 "--workers", "1"]) == 0
    capsys.readouterr()
    _, recording, summary = up_runs.run_up(tmp_path, config_path, table, "pq",
                                           "--q-table", str(q_table))
    config = load_config(config_path)
    from adnmesh.tuning.table import load_table
    local = run_local(config, GainSchedule(config, load_table(table, config)),
                      q_schedule=GainSchedule(reactive_view(config),
                                              load_table(q_table, reactive_view(config))))
    assert up_runs.data_messages(recording) == sorted(
        local.messages, key=lambda m: (decode(*m).t_deliver_ns, m[0], decode(*m).seq))
    (q_step,) = summary["q_steps"]
    assert q_step["step_w"] == -0.3e6 and q_step["figures"]["overshoot_pct"] < 1.0
    assert summary["coupling"]["q_deviation_in_p_steps_var"] == 0.0   # no grid: decoupled


def test_junk_on_every_key_of_a_reactive_run_is_rejected_and_counted(tmp_path):
    """The junk of the bad-input test (tests/test_runtime_faults.py) on every key an agent of
    a run with both loops receives (cpfc/q_y included): each piece rejected and counted at the
    gate, no agent ever sees one."""
    from adnmesh.control.registry import build_agent
    from adnmesh.sim.node import Node
    from adnmesh.sim.topology import Topology
    from adnmesh.wire.keys import route
    from test_runtime_faults import junk_payloads

    config = _config(tmp_path)
    topology = Topology.from_config(config)
    assert Keys(config.grid).of("q_y") in topology.subscriptions["der/SGen1"]
    for agent, keys in topology.subscriptions.items():
        node = Node(build_agent(agent, config, GainSchedule(config, None)), topology, 0)
        before = node.agent.stats()
        fed = 0
        for key in keys:
            sender = route(key).sender
            impostor = "der/SGen2" if sender != "der/SGen2" else "der/SGen1"
            for payload in junk_payloads(key, sender, impostor, 200):
                node.receive(key, payload)
                fed += 1
        assert node.counts.rejected_total == fed
        assert node.agent.stats() == before
    plain = _config(tmp_path, "plain", reactive=None)
    assert Keys(plain.grid).of("q_y") not in Topology.from_config(plain).subscriptions[
        "der/SGen1"]


def test_a_q_step_beyond_the_range_holds_the_q_integrator(tmp_path):
    """+3 Mvar asked of the two WTs (the CHP has no reactive range here) at 1.99 MW of their
    2 MVA: their apparent power holds Q at 0.2 Mvar each, far below the 0.66 Mvar of their
    range, which the CPFC's output limit knows nothing of. They say so (``q_held``), the Q
    integrator freezes, and the step back finds Q_IP leaving its limit within 2 s. (Without the
    freeze Q_Y winds up to the output limit, 0.498, and Q_IP is still at its limit 2 s after
    the step back.)"""
    document = yaml.safe_load(_config(tmp_path, "base").path.read_text())
    ders = document["ders"]
    for der in ders[:2]:
        der["p_sched_w"] = 1.99e6
    ders[2]["q_capability"] = "unity"
    config = _config(tmp_path, ders=ders,
                     scenario={"duration_s": 30, "p_ref_steps": [],
                               "q_ref_steps": [{"t_s": 2, "delta_var": 3e6},
                                               {"t_s": 15, "delta_var": -3e6}]})
    run = run_local(config, GainSchedule(config, None))
    held, q_ys = [], []
    for key, payload in run.messages:
        message = decode(key, payload)
        if message.type == "p_ip" and message.q_held is not msgspec.UNSET:
            held.append((message.t_send_ns / 1e9, message.q_held))
        elif message.type == "q_y":
            q_ys.append((message.t_send_ns / 1e9, message.q_y))
    assert held and all(h == "up" for _, h in held) and 2 < held[0][0] < 4
    t, y = np.array(q_ys).T
    # frozen: Q_Y stays where the DERs saturated, far below the output limit (0.498)
    frozen = y[(t > 10) & (t < 15)]
    assert np.ptp(frozen) < 1e-3 and frozen.max() < 0.4
    series = _series(run)
    t_q, q = np.asarray(series.q_ip_t_ns) / 1e9, np.asarray(series.q_ip_var)
    top = q[(t_q > 10) & (t_q < 15)].max()
    assert q[np.searchsorted(t_q, 17.0)] < top - 0.1e6          # moving back within 2 s
    assert abs(q[-1] - series.q_ref_var[-1]) < 2e3
