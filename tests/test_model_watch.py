"""The run-time model watch (docs/method.md#model-watch): the per-type fit from P_IP and the
commanded set-points, the set a fit implies, and the CPFC saying (and retuning) a step over its
design, in process. The run through ``adnmesh up`` is in tests/test_reference_case.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from adnmesh.config import load_config
from adnmesh.identify.model_fit import model_response
from adnmesh.identify.type_fit import MIN_SHARE, fit_types
from adnmesh.loopmodel.plant import RISE_PER_LAG, Actuator
from adnmesh.tuning.retune import widened_set

PERIOD = 0.01


def _setpoints(n: int, seed: int) -> dict[str, np.ndarray]:
    """Two types' summed set-points: a closed loop's ramps and holds, made of random steps of
    random length (W)."""
    rng = np.random.default_rng(seed)
    out = {}
    for t, size in (("CHP", 8e5), ("PV", 8e5)):
        changes = np.zeros(n)
        at = rng.integers(100, n - 100, 40)
        changes[at] = rng.normal(0, size / 10, at.size)
        out[t] = 2e5 + np.cumsum(changes)
    return out


@pytest.mark.parametrize("seed", [1, 2])
def test_the_fit_recovers_each_types_dynamics_from_p_ip(seed) -> None:
    """P_IP = a rest (constant) + each type's model response to its summed set-points + 5 kW of
    noise: the CHPs' dead time and rise time come back within 2 % and inside their intervals;
    the PVs' too (their share is above MIN_SHARE), a type too small to see keeps its model."""
    n = 12_000                                       # 120 s at 10 ms
    u = _setpoints(n, seed)
    u["WT"] = np.full(n, 5e5)
    u["WT"][6000:] += 0.01 * np.ptp(u["CHP"])        # below MIN_SHARE: not fitted
    truth = {"CHP": Actuator(6.37, 52.0 / RISE_PER_LAG), "PV": Actuator(0.25, 2.0 / RISE_PER_LAG),
             "WT": Actuator(0.01, 0.5 / RISE_PER_LAG)}
    rng = np.random.default_rng(seed + 10)
    y = 1.2e7 + sum(model_response(truth[t], PERIOD, v, v[0]) - v[0] for t, v in u.items())
    y = y + rng.normal(0, 5e3, n)
    configured = {"CHP": Actuator(1.0, 24.57 / RISE_PER_LAG),
                  "PV": Actuator(0.01, 0.1 / RISE_PER_LAG), "WT": truth["WT"]}
    fits = fit_types(PERIOD, u, y, configured)
    assert set(fits) == {"CHP", "PV"}
    for t in fits:
        fit, true = fits[t], truth[t]
        assert fit.delay_s == pytest.approx(true.t_delay_s, rel=0.02, abs=0.02), t
        assert fit.rise_s == pytest.approx(true.t_lag_s * RISE_PER_LAG, rel=0.02), t
        assert fit.delay_ci_s[0] - 0.02 <= true.t_delay_s <= fit.delay_ci_s[1] + 0.02, t
        assert fit.rise_ci_s[0] * 0.98 <= true.t_lag_s * RISE_PER_LAG <= fit.rise_ci_s[1] * 1.02
    assert fits["CHP"].r2 > 0.99
    assert np.ptp(u["WT"]) < MIN_SHARE * sum(np.ptp(v) for v in u.values())


def test_the_fit_refuses_what_it_cannot_fit() -> None:
    flat = {"CHP": np.full(100, 1e5)}
    with pytest.raises(ValueError, match="nothing to identify"):
        fit_types(PERIOD, flat, np.full(100, 3e6), {"CHP": Actuator(1.0, 10.0)})
    with pytest.raises(ValueError, match="at least 10"):
        fit_types(PERIOD, {"CHP": np.arange(5.0)}, np.arange(5.0), {"CHP": Actuator(1.0, 10.0)})
    with pytest.raises(ValueError, match="one length"):
        fit_types(PERIOD, {"CHP": np.arange(50.0)}, np.arange(40.0), {"CHP": Actuator(1, 10)})


def test_the_set_a_fit_implies_holds_the_configs_own(simbench_config, tmp_path) -> None:
    """The set covers the configured model (b = 1, nothing added) and the fit's intervals of the
    fitted types; with a set in the config, that set too (union per type; structures of both)."""
    from adnmesh.identify.model_fit import ModelFit
    fit = ModelFit("pt1", 9.0, 49.0, (8.9, 9.1), (48.8, 49.4), 4e4, 0.96, 9000)
    ders = ["SGen5", "SGen6", "SGen9"]
    found = widened_set(simbench_config, ders, {"CHP": fit})
    chp = found.of_type("CHP")
    assert found.models == ("pt1",)
    assert chp.lag_scale == (1.0, pytest.approx(49.4 / 24.57, rel=1e-3))
    assert chp.delay_add_s == (0.0, pytest.approx(8.1, rel=1e-3))
    assert found.of_type("PV").lag_scale == (1.0, 1.0)            # not fitted: as configured
    own = tmp_path / "own.yaml"
    own.write_text(f"extends: {simbench_config.path}\nconstraints:\n  robust:\n"
                   "    models: [pt2]\n    types:\n"
                   "      CHP: {lag_scale: [0.8, 1.2], delay_add_s: [0, 20]}\n"
                   "      WT: {lag_scale: [0.5, 1]}\n")
    both = widened_set(load_config(own), ders, {"CHP": fit})
    assert both.models == ("pt2", "pt1")
    assert both.of_type("CHP").lag_scale == (0.8, pytest.approx(49.4 / 24.57, rel=1e-3))
    assert both.of_type("CHP").delay_add_s == (0.0, 20.0)
    assert both.of_type("WT").lag_scale == (0.5, 1.0)


WATCHED = """extends: {base}
scenario:
  duration_s: 230
  p_ref_steps:
    - {{t_s: 20,  delta_w: +1.0e+6}}
    - {{t_s: 120, delta_w: -1.0e+6}}
  availability:
    - {{t_s: 10, available: false, ders: [SGen1, SGen2, SGen3, SGen4, SGen7, SGen8]}}
runtime:
  model_watch: {mode}
"""
"""The reference case's CHP and PV step (200 s there) early: the wind turbines drop out at
10 s, the CHPs and PVs alone take +1 MW at 20 s and -1 MW at 120 s."""


def watched_config(base, mode: str, tmp_path, extra: str = ""):
    path = tmp_path / f"watched-{mode}.yaml"
    path.write_text(WATCHED.format(base=base, mode=mode) + extra)
    return load_config(path)


def test_the_cpfc_says_each_step_over_its_design_as_the_summary_does(simbench_config,
                                                                     tmp_path) -> None:
    """``model_watch: event``, in process, without the grid (P_IP the DERs' sum): both steps of
    the CHPs and PVs (detailed models, a table designed on PT1) are over their design; the CPFC
    says each on event/cpfc with the summary's words once 3 design settling times have passed
    (the second one 93 s after it, as the run ends), and tunes nothing again."""
    from tuned_tables import tuned_table

    from adnmesh.control.cpfc_controller import GainSchedule
    from adnmesh.loopmodel.step_figures import reference_step_figures
    from adnmesh.results.design_check import design_checks, design_lines
    from adnmesh.results.model_watch import ModelWatch
    from adnmesh.results.summary import RunSeries
    from adnmesh.sim.local import run_local

    config = watched_config(simbench_config.path, "event", tmp_path, "grid_model: null\n")
    assert config.grid_model is None and config.runtime.der_models == "detailed"
    run = run_local(config, GainSchedule(config, tuned_table(config), on_demand=False),
                    model_watch=lambda: ModelWatch(config, keep_setpoints=False))
    series, events = RunSeries(), []
    for key, data in run.messages:
        body = json.loads(data)
        series.add(body["type"], body)
        if key.endswith("/event/cpfc"):
            events.append((body["t_send_ns"], body["kind"], body["text"]))
    end_ns = int(config.scenario.duration_s * 1e9)
    steps = reference_step_figures(series.p_ip_t_ns, series.p_ip_w, series.p_ref_t_ns,
                                   series.p_ref_w, series.windows.instants, end_ns)
    lines = [line.strip() for line in design_lines(design_checks(steps, series.entries))]
    assert len(lines) == 2 and "step at 20 s" in lines[0] and "step at 120 s" in lines[1]
    said = [(t, text) for t, kind, text in events if kind == "model_mismatch"]
    assert [text.split(" OVER")[0] for _, text in said] == [line.split(" OVER")[0]
                                                           for line in lines]
    assert "(SGen5, SGen6, SGen9, SGen10, SGen11)" in said[0][1]
    # judged at the first P_IP sample a grace (1 s) after 3 design settling times, which
    # reaches the CPFC t_meas_s (0.1 s) later
    designed = float(series.entries[-1]["design"]["settling_time_s"])
    assert designed == pytest.approx(30.66, abs=0.01)
    assert [t / 1e9 for t, _ in said] == pytest.approx([20 + 3 * designed + 1.1,
                                                        120 + 3 * designed + 1.1], abs=0.011)
    assert not [kind for _, kind, _ in events if kind.startswith("model_retune")]
    cpfc = run.nodes["cpfc"].agent
    assert cpfc.counts["model_mismatches"] == 2 and cpfc.counts["retunes"] == 0
    assert len(cpfc.switches) == 1                       # the wind turbines' drop-out only


@pytest.mark.slow
def test_up_retunes_the_subset_whose_step_was_over_its_design(simbench_config,
                                                              tmp_path) -> None:
    """``model_watch: retune`` through ``adnmesh up`` (14 processes, the SimBench power flow,
    the detailed models): the +1 MW step of the CHPs and PVs overshoots its certified 1 %; the
    CPFC says so, fits the CHPs' dead time and rise time to it (their ramp: far slower than
    the configured PT1), tunes the subset over the set that implies and switches to that entry,
    so that the -1 MW step at 120 s is within its design; every event is recorded."""
    import subprocess
    import sys

    from adnmesh.recording import read_recording

    config = watched_config(simbench_config.path, "retune", tmp_path)
    out, summary_path = tmp_path / "watched.mcap", tmp_path / "watched.json"
    result = subprocess.run([sys.executable, "-m", "adnmesh", "up", str(config.path), "--out",
                             str(out), "--summary-json", str(summary_path)], cwd=tmp_path,
                            capture_output=True, text=True, timeout=900, check=False)
    assert result.returncode == 0, result.stderr
    summary = json.loads(summary_path.read_text())
    checks = {c["t_s"]: c for c in summary["design_checks"]}
    assert checks[20.0]["over"] == ["overshoot", "rise", "settling"]
    assert checks[120.0]["over"] == [] and checks[120.0]["entry"] == 2
    designed = {f["name"]: f["design"] for f in checks[120.0]["figures"]}
    assert designed["rise"] > 2 * {f["name"]: f["design"]
                                   for f in checks[20.0]["figures"]}["rise"]
    step = next(s for s in summary["steps"] if s["t_s"] == 120.0)
    assert step["figures"]["overshoot_pct"] < 1.0
    events = [m.payload() for m in read_recording(out).messages if m.schema_name == "event"]
    said = [(e["kind"], e["text"]) for e in events if e["kind"].startswith("model_")]
    assert [k for k, _ in said] == ["model_mismatch", "model_retune", "model_retuned"]
    assert "step at 20 s (+1.000 MW) OVER THE DESIGN of entry 1" in said[0][1]
    retuned = said[2][1]
    assert retuned.startswith("fitted CHP dead time") and "CHP b 1-" in retuned
    fitted_delay = float(retuned.split("CHP dead time ")[1].split(" s")[0])
    assert 5.0 < fitted_delay < 15.0                # the CHPs' ramp, against 1 s configured
    switches = [s["t_s"] for s in summary["switches"]]
    assert len(switches) == 2 and 110 < switches[1] < 120
    # up's summary lists what the watch said, in --summary-json and on the console
    assert [k for _, k, _ in summary["model_watch"]] == [k for k, _ in said]
    assert "the CPFC's model watch" in result.stdout and "s model_retuned: fitted CHP" in \
        result.stdout
    # the way to a table certified from the start is still named; the watch is not offered
    assert "--robust-out" in result.stdout and "model_watch: retune" not in result.stdout


@pytest.mark.parametrize("background", [False, True])
def test_a_retuned_entry_replaces_the_tables_once_released(simbench_config, tmp_path,
                                                          background) -> None:
    """GainSchedule.retune: on the sim clock the job runs at once and its entry is released
    tuning_delay_s later; in a realtime run it runs in a process of its own (the CPFC's
    interpreter stays free for the control loop). Handed over once, a feasible entry is what
    lookup returns for its set from then on; an infeasible one changes nothing, and a process
    that dies is said, not raised."""
    import functools

    from retune_jobs import dies, when_told

    from adnmesh.control.cpfc_controller import GainSchedule
    from adnmesh.tuning.table import TableEntry

    ids = ("SGen5", "SGen6")
    subset = frozenset(ids)
    table_entry = TableEntry(ids, 1e-6, 1e-7, dict.fromkeys(ids, 1.0))
    schedule = GainSchedule(simbench_config, None, tune=lambda c, d: table_entry,
                            tuning_delay_s=2.0, background=background)
    assert schedule.lookup(subset)[1] == "tuned"
    new = TableEntry(ids, 5e-7, 3e-8, dict.fromkeys(ids, 1.0))
    go = tmp_path / "go"
    if not background:
        go.touch()
    schedule.retune(subset, functools.partial(when_told, str(go), new), t_ns=10**9)
    assert schedule.retuned(subset, 2 * 10**9) is None            # not yet
    if background:
        go.touch()
        schedule._retunes[subset][0].result(timeout=60)
    assert schedule.retuned(subset, 3 * 10**9) == (new, "words")
    assert schedule.retuned(subset, 3 * 10**9) is None            # handed over once
    assert schedule.lookup(subset) == (new, "retuned")
    bad = TableEntry(ids, 0.0, 0.0, dict.fromkeys(ids, 1.0), False, "no")
    other = GainSchedule(simbench_config, None, tune=lambda c, d: table_entry,
                         background=background)
    other.retune(subset, functools.partial(when_told, str(go), bad, "none certified"), t_ns=0)
    if background:
        other._retunes[subset][0].exception(timeout=60)
    assert other.retuned(subset, 10**10) == (bad, "none certified")
    assert other.lookup(subset) == (table_entry, "tuned")
    if background:
        other.retune(subset, dies, t_ns=0)
        other._retunes[subset][0].exception(timeout=60)
        entry, words = other.retuned(subset, 10**10)
        assert entry is None and words.startswith("the retune's process failed")
        for pool in (schedule._processes, other._processes):
            pool.shutdown()


def _watch_switch(simbench_config, tau_s: float, held: bool = False):
    """A ModelWatch fed a run by hand: P_ref steps by 1 MW at 10 s (entry 0), a gain switch at
    50 s to entry 1 (design settling time 5 s) after which P_IP is 200 kW short and recovers
    with time constant ``tau_s``; P_IP every 10 ms to 100 s. Returns what it found."""
    from adnmesh.results.model_watch import ModelWatch

    watch = ModelWatch(simbench_config, keep_setpoints=False)
    design = {"rise_time_s": 3.0, "settling_time_s": 5.0, "overshoot_pct": 0.0,
              "overshoot_max_pct": 1.0, "settling_band_pct": 5.0}
    ders = {"SGen5": 1.0, "SGen6": 1.0}
    found = []
    feed = [("p_ref", {"t_send_ns": 0, "p_ref_w": 0.0}),
            ("p_y", {"t_send_ns": 0, "p_y": 0.0, "entry": 0, "design": design, "w": ders}),
            ("p_ref", {"t_send_ns": 10 * 10**9, "p_ref_w": 1e6})]
    for body in feed:
        found += watch.observe(body[0], {**body[1], "src": "cpfc"})
    for k in range(10_001):
        t_ns = k * 10**7
        if t_ns == 50 * 10**9:
            found += watch.observe("p_y", {
                "t_send_ns": t_ns, "src": "cpfc", "p_y": 0.5, "entry": 1, "w": {"SGen5": 1.0},
                "design": design, "switch": {"p_y_before": 0.5, "p_y_limited": 0.5,
                                             "kp_before": 1e-6, "ki_before": 1e-7}})
        t = k * 0.01
        p_ip = 0.0 if t < 10 else 1e6 * (1 - np.exp(-(t - 10) / 0.5))
        if t >= 50:
            p_ip -= 2e5 * np.exp(-(t - 50) / tau_s)
        body = {"t_send_ns": t_ns, "src": "measurement", "p_ip_w": p_ip}
        if held and 55 <= t < 56:
            body["held"] = "up"
        found += watch.observe("p_ip", body)
    return found


def test_a_slow_recovery_after_a_gain_switch_is_said(simbench_config) -> None:
    """After a switch the error the lost DERs left must be back within the band (the larger of
    5 % of it and 5 % of the last step) within the new entry's design settling time + 10 %:
    200 kW recovering with a time constant of 1 s is (1.39 s), with 10 s it is not (13.86 s
    against 5.5 s), said once the window has closed (3 design settling times after the
    switch, a grace later); DERs held at their limits (no power to recover with) are no
    model mismatch."""
    from adnmesh.results.model_watch import SlowRecovery

    assert _watch_switch(simbench_config, 1.0) == []
    slow = _watch_switch(simbench_config, 10.0)
    assert len(slow) == 1 and isinstance(slow[0], SlowRecovery)
    found = slow[0]
    assert (found.t_s, found.entry, found.ders) == (50.0, 1, ("SGen5",))
    assert found.largest_w == pytest.approx(-2e5, rel=1e-9)
    assert found.recovered_s == pytest.approx(10 * np.log(4), abs=0.011)
    assert found.limit_s == pytest.approx(5.5) and found.window_s == pytest.approx(15.0)
    assert "SLOWER THAN DESIGNED" in found.text and "entry 1 (SGen5)" in found.text
    assert _watch_switch(simbench_config, 10.0, held=True) == []


def test_a_fit_that_cannot_be_made_leaves_the_entry_and_says_why(simbench_config) -> None:
    """The retune job never raises: data in which no set-point moved (the DERs held, say)
    gives no entry and the reason, which the CPFC says (``model_retune``) before it goes on
    with its entry."""
    from adnmesh.control.cpfc_controller import _retune_job
    from adnmesh.results.model_watch import StepData

    still = StepData(0.01, np.full(500, 1.6e7), {"CHP": np.full(500, 2e5)})
    entry, words = _retune_job(simbench_config, None, ("SGen5", "SGen6"), still)()
    assert entry is None and words.startswith("the fit or the tuning failed: no set-point")
