"""The grid guard in whole runs of the stress case (configs/examples/stress-rural1-lW*.yaml),
on the sim clock in one process (the same nodes and messages as ``adnmesh up``): without the
guard the +3 MW step at 40 s overloads Line 45 and lifts Bus 47 above 1.10 p.u.; with it no
sample leaves the band and the cost is said; with block mode and a tap changer the tap moves
and the control holds while the overload lasts (docs/method.md#grid-guard)."""

from __future__ import annotations

from pathlib import Path

import pytest

from adnmesh.config import load_config
from adnmesh.control.cpfc_controller import GainSchedule
from adnmesh.results.summary import RunSeries, summarize
from adnmesh.sim.local import run_local
from adnmesh.wire.envelope import decode

pytestmark = pytest.mark.slow


def _run(path: Path, end_s: float = 100.0):
    config = load_config(path)
    result = run_local(config, GainSchedule(config, None, tuning_delay_s=0.0), end_s=end_s)
    series, events = RunSeries(), []
    for key, payload in result.messages:
        message = decode(key, payload)
        series.take(message)
        if message.type == "event":
            events.append((message.t_send_ns, message.src, message.kind, message.text))
    return summarize(series, end_ns=int(end_s * 1e9)), events, result


@pytest.fixture(scope="module")
def runs(configs_dir: Path) -> dict:
    examples = configs_dir / "examples"
    return {name: _run(examples / f"stress-rural1-lW{name}.yaml")
            for name in ("", "-guard", "-tap")}


def test_without_the_guard_the_step_drives_the_grid_out_of_its_band(runs) -> None:
    summary, events, _ = runs[""]
    grid = summary.grid
    assert grid.violations == 1 and grid.outside_s > 30.0
    assert grid.line_loading_max_pct > 103.0 and grid.line_max_at == "MV1.101 Line 45"
    assert grid.v_max_pu > 1.10 and grid.v_max_at == "MV1.101 Bus 47"
    assert grid.guard_blocks == 0 and grid.energy_short_kwh is None
    assert [k for _, _, k, _ in events if k.startswith("limit_")] == ["limit_violated",
                                                                      "limit_restored"]


def test_with_the_guard_no_sample_leaves_the_band_and_the_cost_is_said(runs) -> None:
    summary, events, result = runs["-guard"]
    grid = summary.grid
    assert grid.violations == 0 and grid.outside_band == 0
    assert grid.line_loading_max_pct < 100.0 and grid.v_max_pu < 1.10
    assert grid.guard_blocks >= 2 and grid.energy_short_kwh > 1.0
    assert 40.0 in grid.steps_short                   # the +3 MW step is not fully delivered
    blocked = [text for _, src, kind, text in events if kind == "guard_block"]
    assert any("WT4" in t and "WT5" in t and "Line 45" in t for t in blocked)
    left_out = [text for _, src, kind, text in events if src == "cpfc" and kind == "guard"]
    assert left_out and "left out moving up" in left_out[0]
    kept = [s.keep for s in summary.switches if s.keep]       # capped, not sent back
    assert any({"WT4", "WT5"} <= set(k) for k in kept)
    repeats = sum(key.endswith("measurement/guard") for key, _ in result.messages)
    assert repeats >= 100                 # with every grid report, for a restarted CPFC too
    stats = result.nodes["measurement"].agent.stats()
    assert stats["guard_sensitivity_refreshes"] > 0 and stats["not_converged"] == 0


def test_block_mode_holds_and_the_tap_changer_moves(runs) -> None:
    summary, events, _ = runs["-tap"]
    grid = summary.grid
    assert grid.tap_moves >= 1 and grid.tap_range[1] >= 1       # HV side: up lowers the MV
    kinds = [k for _, _, k, _ in events]
    assert "tap" in kinds and "guard_hold" in kinds and "guard_resume" in kinds
    holds = [t for t, src, k, _ in events if src == "cpfc" and k == "hold"]
    assert holds and grid.guarded_s > 0.0
    assert grid.v_max_pu < 1.10                   # the tap step keeps the voltage in band
    assert grid.line_loading_max_pct > 100.0      # which no tap step can do for the overload
