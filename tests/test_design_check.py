"""Said when over (docs/method.md#said-when-over): each step against what its table entry was
certified for, in ``up``'s summary (text and JSON), ``adnmesh inspect`` (text and ``--json``)
and the recorder's Foxglove log, by one rule (:mod:`adnmesh.results.design_check`)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from adnmesh.cli import main
from adnmesh.config import load_config
from adnmesh.control.cpfc_controller import GainSchedule
from adnmesh.loopmodel.step_figures import ReferenceStep, StepFigures
from adnmesh.recording import Recorder, read_recording
from adnmesh.results.design_check import FIGURE_TOLERANCE, design_checks, design_lines
from adnmesh.results.eventlog import EventLog
from adnmesh.results.summary import RunSeries, format_summary, summarize
from adnmesh.sim.local import run_local
from adnmesh.wire.keys import Keys
from adnmesh.wire.schemas import message_schemas
from payloads import payload
from tuned_tables import tuned_table

DESIGN = {"rise_time_s": 10.0, "settling_time_s": 20.0, "overshoot_pct": 0.5,
          "overshoot_max_pct": 1.0, "settling_band_pct": 5.0}


def _step(t_s: float, rise: float, settling: float, overshoot: float,
          window_s: float = 100.0) -> ReferenceStep:
    figures = StepFigures(rise, settling, settling, overshoot, 1 + overshoot / 100, rise, 0.0,
                          5.0)
    return ReferenceStep(t_s, 1e6, 1e6, figures, 0.0, window_s)


def test_a_step_is_over_its_design_beyond_the_limit_or_the_tolerance() -> None:
    entries = [{"t_ns": 0, "entry": 0, "design": DESIGN, "ders": ["A", "B"]},
               {"t_ns": 50_000_000_000, "entry": 1, "design": None, "ders": ["A"]}]
    slow = 10.0 * (1 + FIGURE_TOLERANCE) * 1.01
    checks = design_checks([_step(1, 10.9, 21.9, 1.0),            # within: at the limit
                            _step(2, slow, 19.0, 1.2),            # rise, overshoot
                            _step(3, math.nan, math.inf, 0.0),    # never rose nor settled
                            _step(4, math.nan, math.inf, 0.0, window_s=5.0),   # too short
                            _step(60, 30.0, 40.0, 3.0)], entries)  # static: no figures
    assert [c.over for c in checks] == [(), ("overshoot", "rise"), ("rise", "settling"), (),
                                        ()]
    assert [c.entry for c in checks] == [0, 0, 0, 0, 1] and checks[4].figures == ()
    overshoot, rise, settling = checks[1].figures
    assert (overshoot.measured, overshoot.design, overshoot.limit) == (1.2, 0.5, 1.0)
    assert rise.limit == pytest.approx(11.0) and rise.design == 10.0
    lines = design_lines(checks)
    assert len(lines) == 2
    assert lines[0] == ("  step at 2 s (+1.000 MW) OVER THE DESIGN of entry 0 (A, B): overshoot "
                        "1.200 % > the 1 % it was certified for (designed 0.500 %); rise "
                        f"{slow:.3f} s against 10.000 s designed (+11 %, more than +10 %)")
    assert "no rise in the window against 10.000 s designed" in lines[1]


def test_the_entry_of_a_step_is_the_one_in_use_when_it_is_applied() -> None:
    """A directional switch one sample before the next step must not lend that step's entry
    to the step before (docs/method.md#directional-availability)."""
    other = dict(DESIGN, rise_time_s=1.0)
    entries = [{"t_ns": 0, "entry": 0, "design": DESIGN, "ders": []},
               {"t_ns": 99_990_000_000, "entry": 1, "design": other, "ders": []}]
    first, second = design_checks([_step(5, 10, 20, 0), _step(100, 10, 20, 0)], entries)
    assert (first.entry, first.over) == (0, ())
    assert (second.entry, second.over) == (1, ("rise",))


@pytest.fixture(scope="module")
def recorded(tmp_path_factory, configs_dir: Path):
    """configs/examples/one-sided.yaml run in process and recorded as ``up`` records it (the
    config in the metadata, the recorder's Foxglove log, the clock's start and stop); its last
    step, back to the schedules from above, overshoots 1.12 % against the 1 % limit."""
    config = load_config(configs_dir / "examples" / "one-sided.yaml")
    messages = run_local(config, GainSchedule(config, tuned_table(config), on_demand=False)
                         ).messages
    keys, end_ns = Keys(config.grid), int(config.scenario.duration_s * 1e9)
    path = tmp_path_factory.mktemp("over") / "one-sided.mcap"
    start = (keys.of("clock_start"), payload(keys.of("clock_start"), {
        "clock": "sim", "epoch_ns": 0, "speed": 1.0, "end_ns": end_ns, "seed": 0}))
    stop = (keys.of("clock_stop"), payload(keys.of("clock_stop"), {"reason": "finished"},
                                           t_send_ns=end_ns))
    series = RunSeries()
    with Recorder(path, metadata={"run_id": "over", "config": Path(config.path).read_text(),
                                  "clock": "sim", "t0_ns": "0"},
                  schemas=message_schemas(), events_topic=f"{keys.root}/log",
                  events=EventLog().observe) as recorder:
        for key, data in [start, *messages, stop]:
            body = json.loads(data)
            recorder.write(key, body["type"], data, log_time_ns=body["t_deliver_ns"],
                           publish_time_ns=body["t_send_ns"])
            if key not in (start[0], stop[0]):
                series.add(body["type"], body)
    summary = summarize(series, end_ns=end_ns, band_pct=config.constraints.settling_band_pct)
    return config, path, summary


def test_the_summary_flags_the_step_with_the_design_beside(recorded) -> None:
    _, _, summary = recorded
    assert [c.over for c in summary.design_checks] == [(), (), (), ("overshoot",)]
    (line,) = design_lines(summary.design_checks)
    assert line.startswith("  step at 180 s (-0.500 MW) OVER THE DESIGN of entry 2 (C1, C2, "
                           "P1, P2): overshoot 1.1")
    assert line.endswith("% > the 1 % it was certified for (designed 1.000 %)")
    assert line in format_summary(summary)
    (flagged,) = [c for c in summary.to_json()["design_checks"] if c["over"]]
    assert flagged["t_s"] == 180 and flagged["figures"][0]["limit"] == 1.0
    assert flagged["figures"][0]["design"] == pytest.approx(1.0, abs=1e-3)


def _lines(text: str) -> list[str]:
    return [" ".join(line.replace("│", " ").split()) for line in text.splitlines()]


def test_inspect_says_it_in_text_and_json(recorded, capsys) -> None:
    _, path, summary = recorded
    assert main(["inspect", str(path)]) == 0
    lines = _lines(capsys.readouterr().out)
    (line,) = design_lines(summary.design_checks)
    assert " ".join(line.split()) in lines
    (row,) = [x for x in lines if x.startswith("180.00 -0.500 ")]
    assert row.endswith("(e2) OVER: overshoot")
    assert main(["inspect", str(path), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["figures"]["design_checks"] == summary.to_json()["design_checks"]


def test_the_foxglove_log_says_it_once_the_window_closed(recorded) -> None:
    _, path, summary = recorded
    (line,) = design_lines(summary.design_checks)
    logs = [m for m in read_recording(path).messages if m.schema_name == "foxglove.Log"
            and "OVER THE DESIGN" in m.payload()["message"]]
    (log,) = logs
    assert log.payload()["message"].endswith(line.strip()) and "over_design" in \
        log.payload()["message"] + log.payload()["name"]
    assert log.payload()["level"] == 3      # WARNING
    t = log.payload()["timestamp"]        # when the step's window closed: the run's end
    assert t["sec"] * 10**9 + t["nsec"] == log.publish_time_ns == 240 * 10**9


def test_the_watch_holds_the_open_windows_not_the_run(recorded, monkeypatch) -> None:
    """The recorder's watch forgets the P_IP samples of checked steps (up's memory stays
    flat over a long run) and finds the same steps over their design as when it keeps all."""
    from adnmesh.results import design_watch

    _, path, _ = recorded
    messages = [(m.schema_name, m.data, m.publish_time_ns) for m in read_recording(path).messages
                if m.schema_name != "foxglove.Log"]

    def watched(trim: int):
        monkeypatch.setattr(design_watch, "_TRIM", trim)
        watch, found, held = design_watch.OverDesignWatch(), [], 0
        for schema_name, data, t_ns in messages:
            found += watch.observe(schema_name, data, t_ns)
            held = max(held, len(watch.series.p_ip_t_ns))
        return found, held, len(watch.series.p_ip_t_ns)

    found_all, held_all, _ = watched(10**9)
    found, held, left = watched(500)
    assert found == found_all and len(found) == 1 and "OVER THE DESIGN" in found[0][1]
    assert held_all == 24_001          # every P_IP sample of the 240 s run at 10 ms
    assert left == 6_001               # the last step's open window: 180 s to the end at 240 s
    assert held < held_all / 3, held
