"""Benchmark: what the CPFC's model watch (``runtime.model_watch: retune``) costs when it acts.

Runs the reference case's CHP and PV steps early, in process (the wind turbines drop out at
10 s, +1 MW at 20 s; by default without the power flow, ``--grid`` with it) until the watch
has the first step's data, then times, ``--repeat`` times:

- **the type fit** (:func:`adnmesh.identify.type_fit.fit_types`: every DER type of the subset
  from ``P_IP`` and the commanded set-points), against its peer in the same run: fitting each
  of the subset's DERs from its own set-point and infeed (``adnmesh identify``'s
  :func:`~adnmesh.identify.model_fit.fit_model`, the DERs' state messages);
- **the robust re-tune** (:func:`adnmesh.tuning.retune.retune`), against tuning the same
  subset on demand without the set.

Prints wall seconds as ranges and the ratios to the peers, and the fits themselves.

    .venv/bin/python benchmarks/bench_model_watch.py [--grid] [--repeat 3]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from adnmesh import one_blas_thread  # noqa: E402

one_blas_thread()

from adnmesh.config import load_config  # noqa: E402
from adnmesh.control.cpfc_controller import GainSchedule  # noqa: E402
from adnmesh.identify.model_fit import fit_model  # noqa: E402
from adnmesh.identify.resample import on_grid  # noqa: E402
from adnmesh.identify.type_fit import fit_types  # noqa: E402
from adnmesh.results.model_watch import ModelWatch  # noqa: E402
from adnmesh.sim.local import run_local  # noqa: E402
from adnmesh.tuning.ondemand import OnDemandTuner  # noqa: E402
from adnmesh.tuning.problem import nominal_by_type  # noqa: E402
from adnmesh.tuning.retune import retune  # noqa: E402

SCENARIO = """extends: {base}
scenario:
  duration_s: 120
  p_ref_steps:
    - {{t_s: 20, delta_w: +1.0e+6}}
  availability:
    - {{t_s: 10, available: false, ders: [SGen1, SGen2, SGen3, SGen4, SGen7, SGen8]}}
runtime:
  model_watch: retune
"""


def _range(values) -> str:
    return f"{min(values):.3g}-{max(values):.3g}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", action="store_true", help="with the SimBench power flow")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    from tuned_tables import tuned_table

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "watched.yaml"
        path.write_text(SCENARIO.format(base=ROOT / "configs" / "simbench.yaml")
                        + ("" if args.grid else "grid_model: null\n"))
        config = load_config(path)
        table = tuned_table(config)
        kept = []

        class Keeping(ModelWatch):
            def step_data(self, found):
                kept.append((found, super().step_data(found)))
                return kept[-1][1]

        t0 = time.perf_counter()
        run = run_local(config, GainSchedule(config, table, on_demand=False),
                        model_watch=lambda: Keeping(config, keep_setpoints=True))
        print(f"run of {config.scenario.duration_s:g} s in process: "
              f"{time.perf_counter() - t0:.1f} s wall (grid {'on' if args.grid else 'off'}, "
              f"load {os.getloadavg()[0]:.2f})")
    if not kept:
        print("the step was within its design: nothing to fit")
        return 1
    found, data = kept[0]
    ders = found.check.ders
    configured = {t: a for t, a in nominal_by_type(config, ders).items()
                  if t in data.setpoints_w}
    states: dict[str, list] = {}
    for _, payload in run.messages:
        body = json.loads(payload)
        if body["type"] == "der_state" and body["src"].split("/")[-1] in ders:
            states.setdefault(body["src"].split("/")[-1], []).append(
                (body["t_send_ns"] * 1e-9, body["setpoint_w"], body["p_w"]))
    start, stop = found.check.t_s - data.period_s, found.closed_ns * 1e-9
    type_fit, per_der, robust, nominal = [], [], [], []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        fits = fit_types(data.period_s, data.setpoints_w, data.p_ip_w, configured)
        type_fit.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        for der, rows in states.items():
            t, u, y = (list(c) for c in zip(*rows))
            _, held, measured = on_grid(t, u, t, y, data.period_s, start, stop)
            fit_model(data.period_s, held, measured)
        per_der.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        entry, box = retune(config, table, ders, fits)
        robust.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        OnDemandTuner(config, table).tune(list(ders))
        nominal.append(time.perf_counter() - t0)
    print(f"step at {found.check.t_s:g} s, judged at {found.closed_ns / 1e9:g} s: "
          f"{len(data.p_ip_w)} samples of P_IP, types {', '.join(data.setpoints_w)}")
    for t, fit in fits.items():
        print(f"  {t}: dead time {fit.delay_s:.4g} s ({fit.delay_ci_s[0]:.4g}-"
              f"{fit.delay_ci_s[1]:.4g}), T_rise {fit.rise_s:.4g} s ({fit.rise_ci_s[0]:.4g}-"
              f"{fit.rise_ci_s[1]:.4g}), R² {fit.r2:.4f}")
    print(f"  set: {box.model_dump()['types']}")
    print(f"  entry: K_P {entry.kp:.4g}, K_I {entry.ki:.4g}, designed rise "
          f"{entry.figures['rise_time_s']:.4g} s, settling {entry.figures['settling_time_s']:.4g}"
          f" s, feasible {entry.feasible}")
    print(f"type fit     {_range(type_fit)} s | per-DER fits ({len(states)} DERs) "
          f"{_range(per_der)} s | ratio {_range([a / b for a, b in zip(type_fit, per_der)])}")
    print(f"robust tune  {_range(robust)} s | nominal tune {_range(nominal)} s | ratio "
          f"{_range([a / b for a, b in zip(robust, nominal)])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
