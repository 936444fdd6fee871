"""What happens at a switch to a subset the table lacks: step figures with and without its entry.

SimBench (``configs/simbench.yaml``) cut to 260 s, run in this process on the sim clock
(:func:`adnmesh.sim.local.run_local`): the six WTs drop out at 170 s (the CPFC switches to the
CHP+PV set), P_ref steps +1 MW at 200 s. Cases: the table has the CHP+PV entry; it lacks it and
the on-demand tuning takes ``TUNING_DELAY_S`` (1 s) of sim time, the static controller running
meanwhile; it lacks it and the tuning takes longer than the step's window (the step at 200 s
runs on the static controller). Prints, per case, the gains in use and P_IP's largest deviation
from P_ref in the 10 s after the switch, and the step figures of the step at 200 s.

    .venv/bin/python benchmarks/bench_switch.py --table tables/simbench-global.json
"""
from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import numpy as np

from adnmesh.config import load_config
from adnmesh.control.cpfc_controller import TUNING_DELAY_S, GainSchedule
from adnmesh.sim.local import run_local
from adnmesh.loopmodel.step_figures import reference_step_figures
from adnmesh.tuning.table import load_table
from adnmesh.wire.envelope import decode
from adnmesh.wire.keys import Keys

ROOT = Path(__file__).resolve().parent.parent
END_S = 260.0
WTS = frozenset({"SGen1", "SGen2", "SGen3", "SGen4", "SGen7", "SGen8"})


def _series(config, run):
    keys = Keys(config.grid)
    ip_t, ip, ref_t, ref, switches = [], [], [], [], []
    for key, payload in run.messages:
        if key == keys.of("p_ip"):
            m = decode(key, payload)
            ip_t.append(m.t_send_ns)
            ip.append(m.p_ip_w)
        elif key == keys.of("p_ref"):
            m = decode(key, payload)
            ref_t.append(m.t_send_ns)
            ref.append(m.p_ref_w)
    return np.array(ip_t), np.array(ip), np.array(ref_t), np.array(ref)


def case(config, table, name: str, delay_s: float) -> None:
    schedule = GainSchedule(config, table, tuning_delay_s=delay_s)
    w0 = time.perf_counter()
    run = run_local(config, schedule, end_s=END_S)
    wall = time.perf_counter() - w0
    ip_t, ip, ref_t, ref = _series(config, run)
    cpfc = run.nodes["cpfc"].agent
    sw = [(e.t_ns * 1e-9, e.source, e.record.kp_after if hasattr(e.record, "kp_after") else None)
          for e in cpfc.switches]
    t_sw = int(170.0e9)
    inside = (ip_t >= t_sw) & (ip_t <= t_sw + int(10e9))
    ref_at = ref[np.searchsorted(ref_t, ip_t[inside], side="right") - 1]
    dev = np.max(np.abs(ip[inside] - ref_at))
    steps = reference_step_figures(ip_t, ip, ref_t, ref, [int(t * 1e9) for t, _, _ in sw],
                                   int(END_S * 1e9))
    step = next(s for s in steps if abs(s.t_s - 200.0) < 1e-6)
    f = step.figures
    print(f"{name}: switches {[(round(t, 2), s) for t, s, _ in sw]}; "
          f"max |P_IP - P_ref| in 10 s after 170 s {dev / 1e3:.1f} kW; "
          f"step at 200 s: rise {f.rise_time_s:.3f} s, settling {f.settling_time_s:.3f} s, "
          f"overshoot {f.overshoot_pct:.3f} % (run {wall:.1f} s wall)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "simbench.yaml"))
    ap.add_argument("--table", required=True)
    args = ap.parse_args(argv)
    config = load_config(args.config)
    table = load_table(args.table, config)
    rest = frozenset(config.der_ids()) - WTS
    case(config, table, "table has the entry", TUNING_DELAY_S)
    lacking = copy.deepcopy(table)
    del lacking.entries[rest]
    case(config, lacking, f"on demand, tuning {TUNING_DELAY_S:g} s", TUNING_DELAY_S)
    case(config, lacking, "on demand, tuning 60 s (static for the step)", 60.0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
