"""Generate configs/examples/adn-100.yaml: 100 DERs on the SimBench 1-MV-rural sgens."""
import numpy as np, simbench as sb, yaml
net = sb.get_simbench_net("1-MV-rural--0-no_sw")
sg = net.sgen[net.sgen.type != "Hydro_MV"].iloc[:100]
rng = np.random.default_rng(100)
lv_types = ["PV"] * 60 + ["WT"] * 15 + ["CHP"] * 15
rng.shuffle(lv_types)
base = {"WT": (0.01, 0.515), "CHP": (1.0, 24.57), "PV": (0.01, 0.1)}
ders, lv = [], iter(lv_types)
for i, (_, row) in enumerate(sg.iterrows()):
    typ = {"Wind_MV": "WT", "Biomass_MV": "CHP", "PV_MV": "PV"}.get(row.type) or next(lv)
    d0, r0 = base[typ]
    spread = rng.uniform(0.8, 1.25, 2)             # per DER, not only per type
    der = {"id": f"D{i:03d}", "type": typ, "p_inst_w": float(round(row.p_mw * 1e6, 3)),
           "t_delay_s": float(round(d0 * spread[0], 2 if typ != "CHP" else 1)) or 0.01,
           "t_rise_s": float(round(r0 * spread[1], 3)), "sgen": row["name"]}
    if typ == "WT":
        der["p_sched_w"] = round(der["p_inst_w"] / 2, 3)
    ders.append(der)
ids = {t: [d["id"] for d in ders if d["type"] == t] for t in base}
cfg = {"grid": "simbench-1-MV-rural", "simbench_code": "1-MV-rural--0-no_sw",
       "t_com_s": 0.1, "t_meas_s": 0.1,
       "constraints": {"disk_margin_min": 1.5, "overshoot_max_pct": 1.0, "settling_band_pct": 5.0},
       "ders": ders,
       "scenario": {"duration_s": 300,
                    "p_ref_steps": [{"t_s": 10, "delta_w": 1.0e6}, {"t_s": 120, "delta_w": -1.0e6},
                                    {"t_s": 220, "delta_w": 0.5e6}],
                    "availability": [
                        {"t_s": 60, "available": False, "ders": ids["WT"][:10]},
                        {"t_s": 90, "available": False, "ders": ids["PV"][:30]},
                        {"t_s": 150, "available": True, "ders": ids["WT"][:10]},
                        {"t_s": 180, "available": True, "ders": ids["PV"][:30]},
                        {"t_s": 200, "available": False, "ders": ids["CHP"][:8]},
                        {"t_s": 260, "available": True, "ders": ids["CHP"][:8]}]}}
head = ("# yaml-language-server: $schema=../config.schema.json\n"
        "# A generated ADN with 100 DERs on the sgens of SimBench 1-MV-rural (all but the hydro\n"
        "# plant): the MV plants keep their types, the aggregated LV feeders become PV, WT or CHP;\n"
        "# every DER's delay and rise time is its type's spread by a factor in [0.8, 1.25].\n"
        "# Groups drop out and return in the scenario. Tune it with --subsets scenario (or\n"
        "# random:N); all 2^100 - 1 subsets are refused. Made by benchmarks/gen_adn100.py.\n")
open("configs/examples/adn-100.yaml", "w").write(head + yaml.safe_dump(cfg, sort_keys=False, width=120))
