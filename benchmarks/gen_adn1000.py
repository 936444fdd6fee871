"""Write a config with 1,000 DERs (the documented maximum), as gen_adn100.py makes adn-100.yaml.

SimBench has no net with 1,000 static generators (1-MVLV-semiurb-all, the largest MV/LV net,
has 794), so this config has no grid model: P_IP is runtime.rest_of_grid_w plus the infeeds,
and the sgen names are placeholders. Types and parameters are spread as in adn-100.yaml: 60 %
PV, 20 % WT, 20 % CHP, each DER's delay and rise time its type's times a factor in
[0.8, 1.25]. The scenario: two P_ref steps, a tenth of the DERs (WTs) out and back.

    .venv/bin/python benchmarks/gen_adn1000.py /tmp/adn-1000.yaml [N]

Not written into configs/: the tests run on every config there, and the lookahead reference
(tests/lookahead_reference.py) takes minutes on 1,000 DERs.
"""
import sys

import numpy as np
import yaml

BASE = {"WT": (0.01, 0.515, 2.0e6), "CHP": (1.0, 24.57, 0.5e6), "PV": (0.01, 0.1, 0.3e6)}
"""Per type: delay s, rise time s, installed power W (the reference case's plants)."""


def der_types(n: int, rng) -> list[str]:
    """The types of ``n`` DERs: 60 % PV, 20 % WT, the rest CHP, in an order ``rng`` shuffles."""
    types = ["PV"] * (n * 6 // 10) + ["WT"] * (n * 2 // 10)
    types += ["CHP"] * (n - len(types))
    rng.shuffle(types)
    return types


def main() -> None:
    out, n = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 1000
    rng = np.random.default_rng(n)
    ders = []
    for i, typ in enumerate(der_types(n, rng)):
        d0, r0, p0 = BASE[typ]
        spread = rng.uniform(0.8, 1.25, 3)
        der = {"id": f"D{i:04d}", "type": typ, "p_inst_w": float(round(p0 * spread[2], 3)),
               "t_delay_s": float(round(d0 * spread[0], 2 if typ != "CHP" else 1)) or 0.01,
               "t_rise_s": float(round(r0 * spread[1], 3)), "sgen": f"sgen {i}"}
        if typ == "WT":
            der["p_sched_w"] = round(der["p_inst_w"] / 2, 3)
        ders.append(der)
    wts = [d["id"] for d in ders if d["type"] == "WT"][: n // 10]
    cfg = {"grid": f"adn-{n}", "simbench_code": "1-MV-rural--0-no_sw", "t_com_s": 0.1,
           "t_meas_s": 0.1, "ders": ders,
           "scenario": {"duration_s": 300,
                        "p_ref_steps": [{"t_s": 10, "delta_w": 1.0e6}, {"t_s": 120, "delta_w": -1.0e6}],
                        "availability": [{"t_s": 60, "available": False, "ders": wts},
                                         {"t_s": 150, "available": True, "ders": list(wts)}]},
           "runtime": {"rest_of_grid_w": -1.0e7}}
    head = (f"# A generated ADN with {n} DERs and no grid model, made by benchmarks/gen_adn1000.py.\n")
    with open(out, "w") as fh:
        fh.write(head + yaml.safe_dump(cfg, sort_keys=False, width=120))


if __name__ == "__main__":
    main()
