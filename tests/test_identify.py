"""``adnmesh identify``: the models' exact responses (against a closed form and
python-control), their fit on synthetic data with known parameters and noise, the resampling
of recorded series, and the command on a CSV and on a real recording."""

from __future__ import annotations

import math
from pathlib import Path

import control
import numpy as np
import pytest
from up_runs import REPO, run_up, write_case

from adnmesh.cli import main
from adnmesh.config import load_config
from adnmesh.identify.model_fit import RISE_PER_LAG, fit_model, model_response
from adnmesh.loopmodel.plant import Actuator
from adnmesh.identify.resample import on_grid, sample_period

H = 0.01


def pt1_response(period_s, u, y0, delay_s, lag_s):
    return model_response(Actuator(delay_s, lag_s, "pt1"), period_s, u, y0)


def fit_pt1(period_s, u, y):
    return fit_model(period_s, u, y, "pt1")


def test_one_step_is_the_closed_form() -> None:
    u = np.full(400, 2e5)
    u[50:] = 7e5
    delay, lag = 0.0437, 0.3
    y = pt1_response(H, u, 2e5, delay, lag)
    t = H * np.arange(400)
    after = np.clip(t - (0.5 + delay), 0.0, None)
    exact = 2e5 + 5e5 * np.where(t > 0.5 + delay, 1.0 - np.exp(-after / lag), 0.0)
    assert np.max(np.abs(y - exact)) < 1e-6


def test_any_set_point_agrees_with_python_control() -> None:
    """A ramp, steps and a start off its steady state, against python-control's simulation
    of the lag on a 100x finer grid with the input shifted by the dead time (which it
    interpolates linearly: the difference shrinks with that grid, 2e-4 of the range here)."""
    n = 600
    u = np.full(n, 1e6)
    u[100:] = 1.5e6
    u[300:] = 0.8e6
    u[400:] += np.linspace(0.0, 2e5, 200)
    delay, lag = 0.237, 0.4
    y = pt1_response(H, u, 1.1e6, delay, lag)
    fine = 100
    t = np.arange(n * fine) * (H / fine)
    shift = int(round(delay / (H / fine)))
    held = np.repeat(u, fine)
    delayed = np.concatenate([np.full(shift, u[0]), held[:-shift]])
    peer = control.forced_response(control.ss(-1 / lag, 1 / lag, 1, 0), t, delayed,
                                   X0=1.1e6).outputs[::fine]
    assert np.max(np.abs(y - peer)) < 2e-4 * np.ptp(u)


def _python_control(actuator: Actuator, u: np.ndarray, fine: int) -> np.ndarray:
    """python-control's simulation of ``actuator`` from rest at ``u[0]``, on a grid ``fine``
    times finer than ``H`` with the input shifted by the dead time, at the samples."""
    t = np.arange(len(u) * fine) * (H / fine)
    shift = int(round(actuator.t_delay_s / (H / fine)))
    held = np.repeat(u, fine)
    delayed = np.concatenate([np.full(shift, u[0]), held[:-shift]])
    peer = control.tf(actuator.numerator[::-1], actuator.denominator[::-1])
    return control.forced_response(peer, t, delayed - u[0]).outputs[::fine] + u[0]


@pytest.mark.parametrize("model", ["pt1", "pt2", "rhpz"])
def test_every_model_converges_to_python_control(model: str) -> None:
    """python-control interpolates its input linearly between its samples, so its result
    approaches the exact one as its grid gets finer: the difference shrinks as 1/fine."""
    n = 600
    u = np.full(n, 1e6)
    u[100:] = 1.5e6
    u[300:] = 0.8e6
    u[400:] += np.linspace(0.0, 2e5, 200)
    actuator = Actuator(0.237, 0.4, model)
    y = model_response(actuator, H, u, 1e6)
    coarse, finer = (np.max(np.abs(y - _python_control(actuator, u, fine))) for fine in (100, 400))
    assert coarse < 1e-3 * np.ptp(u)
    assert 3.5 < coarse / finer < 4.5


@pytest.mark.parametrize("model", ["pt2", "rhpz"])
def test_each_model_is_recovered_and_told_from_the_others(model: str) -> None:
    rng = np.random.default_rng(3)
    u = np.full(2000, 1e6)
    u[100:] = 1.5e6
    u[1000:] = 0.7e6
    truth = Actuator(0.12, 0.9, model)
    y = model_response(truth, H, u, 1e6) + rng.normal(0.0, 2e3, len(u))
    fits = {m: fit_model(H, u, y, m) for m in ("pt1", "pt2", "rhpz")}
    assert min(fits, key=lambda m: fits[m].rmse_w) == model
    assert math.isclose(fits[model].delay_s, 0.12, abs_tol=0.005)
    assert math.isclose(fits[model].rise_s, 0.9 * RISE_PER_LAG, rel_tol=0.01)


def test_the_fit_recovers_known_parameters_through_noise() -> None:
    rng = np.random.default_rng(7)
    u = np.full(3000, 1e6)
    for at, level in ((100, 1.5e6), (900, 0.7e6), (1700, 1.2e6), (2400, 0.9e6)):
        u[at:] = level
    delay, rise = 0.237, 0.88
    clean = pt1_response(H, u, 1e6, delay, rise / RISE_PER_LAG)
    fit = fit_pt1(H, u, clean + rng.normal(0.0, 5e3, len(u)))
    assert fit.delay_ci_s[0] <= delay <= fit.delay_ci_s[1]
    assert fit.rise_ci_s[0] <= rise <= fit.rise_ci_s[1]
    assert abs(fit.delay_s - delay) < 0.005 and abs(fit.rise_s - rise) < 0.02
    assert 4e3 < fit.rmse_w < 6e3 and fit.r2 > 0.99
    slow = pt1_response(H, u, 1e6, 1.7, 20.0)          # a slow plant: the dead time's start
    fit = fit_pt1(H, u, slow)                            # values must not trap it near 0
    assert math.isclose(fit.delay_s, 1.7, abs_tol=1e-3)
    assert math.isclose(fit.rise_s, 20.0 * RISE_PER_LAG, rel_tol=1e-3)


def test_nothing_to_fit_is_said() -> None:
    with pytest.raises(ValueError, match="never moves"):
        fit_pt1(H, np.full(100, 5.0), np.full(100, 5.0))
    with pytest.raises(ValueError, match="at least 10"):
        fit_pt1(H, np.arange(5.0), np.arange(5.0))


def test_recorded_times_in_float_seconds_keep_their_samples() -> None:
    """Times converted from whole ns are not exact multiples of the period in float; the set-
    point must not slip by a sample (it did: the fitted dead time came out one period short)."""
    t = np.arange(20_001) * 10_000_000 / 1e9 + 200.0
    u = np.where(t >= 250.0, 1.0, 0.0)
    period = sample_period(t)
    assert period == 0.01
    grid, held, measured = on_grid(t, u, t, u, period)
    assert np.array_equal(held, u) and np.array_equal(measured, u)
    assert len(grid) == len(t)


def _write_csv(path: Path) -> None:
    u = np.full(1500, 3e5)
    u[200:] = 6e5
    u[900:] = 4e5
    y = pt1_response(H, u, 3e5, 0.52, 4.0 / RISE_PER_LAG)
    rows = ["time_s,p_set_w,p_meas_w"] + [f"{k * H:.2f},{a:.1f},{b:.3f}"
                                          for k, (a, b) in enumerate(zip(u, y))]
    path.write_text("\n".join(rows) + "\n")


def test_identify_a_csv_writes_a_config_that_loads_and_a_figure(tmp_path: Path, capsys) -> None:
    data = tmp_path / "scada.csv"
    _write_csv(data)
    config = REPO / "configs" / "simbench.yaml"
    out, fig = tmp_path / "fitted.yaml", tmp_path / "fit.png"
    assert main(["identify", str(config), "--csv", str(data), "--der", "SGen5", "--time",
                 "time_s", "--setpoint", "p_set_w", "--measured", "p_meas_w", "-o", str(out),
                 "--plot", str(fig)]) == 0
    said = capsys.readouterr().out
    assert "SGen5" in said
    assert "b = fitted T_rise / configured from 0.163 (SGen5) to 0.163 (SGen5)" in said
    assert "dead time -0.48 s (SGen5)" in said
    fitted = load_config(out)
    sgen5 = next(d for d in fitted.ders if d.id == "SGen5")
    assert math.isclose(sgen5.t_delay_s, 0.52, abs_tol=1e-3)
    assert math.isclose(sgen5.t_rise_s, 4.0, rel_tol=1e-3)
    assert [d.t_rise_s for d in fitted.ders if d.id != "SGen5"] == \
        [d.t_rise_s for d in load_config(config).ders if d.id != "SGen5"]
    assert fig.read_bytes()[:4] == b"\x89PNG"
    capsys.readouterr()
    assert main(["identify", str(config), "--csv", str(data), "--der", "SGen5", "--time",
                 "time_s", "--setpoint", "p_set_w", "--measured", "p_meas_w", "--steps",
                 "2,9"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines() if " pt1 " in line]
    text = "\n".join(" ".join(r) for r in rows)
    assert "2-8.98" in text and "9-14.99" in text
    assert [r for r in rows if "up" in r] and [r for r in rows if "down" in r]


@pytest.mark.parametrize("argv, said", [
    (["--csv", "{csv}", "--der", "SGen5", "--time", "t", "--setpoint", "p_set_w",
      "--measured", "p_meas_w"], "no column 't'"),
    (["--csv", "{csv}", "--time", "time_s", "--setpoint", "p_set_w", "--measured",
      "p_meas_w"], "--csv needs --der"),
    (["--csv", "{csv}", "--der", "SGen99", "--time", "time_s", "--setpoint", "p_set_w",
      "--measured", "p_meas_w"], "not a DER"),
    (["{csv}"], "not an MCAP"),
    (["--csv", "{csv}", "--der", "SGen5", "--time", "time_s", "--setpoint", "p_set_w",
      "--measured", "p_meas_w", "--steps", "auto"], "give the step times"),
    (["--csv", "{csv}", "--der", "SGen5", "--time", "time_s", "--setpoint", "p_set_w",
      "--measured", "p_meas_w", "--steps", "2,x"], "auto or times in s"),
])
def test_bad_input_is_one_line_exit_2(tmp_path: Path, capsys, argv, said) -> None:
    data = tmp_path / "scada.csv"
    _write_csv(data)
    argv = [a.format(csv=data) for a in argv]
    assert main(["identify", str(REPO / "configs" / "simbench.yaml"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert said in err and "\n" not in err and "Traceback" not in err


def test_identify_a_recording_recovers_the_reference_models(tmp_path: Path, capsys) -> None:
    """Two WTs running the reference model (dead time, then lag) in a real run: their fitted
    dead time and rise time are the config's."""
    config, table = write_case(tmp_path, runtime={"der_models": "reference"}, ders=[
        {"id": "SGen1", "type": "WT", "p_inst_w": 2.0e6, "t_delay_s": 0.037,
         "t_rise_s": 0.515, "sgen": "MV1.101 SGen 1"},
        {"id": "SGen2", "type": "WT", "p_inst_w": 2.0e6, "t_delay_s": 0.01,
         "t_rise_s": 1.2, "sgen": "MV1.101 MV SGen 2", "p_sched_w": 0.5e6}])
    _, recording, _ = run_up(tmp_path, config, table, "identify")
    out = tmp_path / "fitted.yaml"
    assert main(["identify", str(config), str(tmp_path / "identify.mcap"), "-o", str(out)]) == 0
    fitted = {d.id: d for d in load_config(out).ders}
    assert math.isclose(fitted["SGen1"].t_delay_s, 0.037, abs_tol=1e-4)
    assert math.isclose(fitted["SGen1"].t_rise_s, 0.515, rel_tol=1e-3)
    assert math.isclose(fitted["SGen2"].t_delay_s, 0.01, abs_tol=1e-4)
    assert math.isclose(fitted["SGen2"].t_rise_s, 1.2, rel_tol=1e-3)
    # each window from a P_ref step on apart: the step at 1 s, the set-points go up
    capsys.readouterr()
    assert main(["identify", str(config), str(tmp_path / "identify.mcap"), "--steps",
                 "auto"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if "pt1" in line]
    assert any("SGen1" in r and "1-" in r and " up " in r for r in rows)
    # before the step at 1 s no set-point moves: each DER is said and left out; none is left,
    # which is a one-line error, as is asking for one by name
    capsys.readouterr()
    recording = str(tmp_path / "identify.mcap")
    assert main(["identify", str(config), recording, "--to", "0.9"]) == 2
    err = capsys.readouterr().err
    assert "no DER could be fitted: SGen1 (the set-point never moves" in err
    assert main(["identify", str(config), recording, "--der", "SGen2", "--to", "0.9"]) == 2
    assert "SGen2: the set-point never moves" in capsys.readouterr().err

