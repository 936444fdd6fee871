"""An agent process loads what its kind runs, and no more (issue 41: half the memory).

Each case runs a fresh interpreter (``sys.modules`` of this one holds whatever other tests
loaded) and checks which packages it holds: behaviour, not timing.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from conftest import REPO_ROOT

HEAVY = ("scipy", "numba", "llvmlite", "pandas", "pyarrow", "pandapower")
"""Packages no agent program needs at import (the tuning numerics, the grid's model
building); the measurement agent's solver and a WT's or CHP's calibration load theirs when
they build the agent."""


def loaded(code: str) -> dict:
    """Top-level packages and adnmesh modules in ``sys.modules`` after ``code`` ran in a fresh
    interpreter."""
    probe = code + ("\nimport json, sys\nprint(json.dumps(sorted(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", probe], cwd=REPO_ROOT, capture_output=True,
                         text=True, timeout=120, check=True).stdout
    names = json.loads(out.splitlines()[-1])
    return {"packages": {n.split(".")[0] for n in names},
            "adnmesh": {n for n in names if n.startswith("adnmesh.")}}


@pytest.mark.parametrize("kind", ["der", "cpfc", "measurement", "availability"])
def test_agent_program_imports_no_heavy_package(kind):
    found = loaded(f"import adnmesh.agents.{kind}")
    assert not found["packages"] & set(HEAVY)


def test_der_process_loads_only_the_der(configs_dir):
    """A PV built as its agent process builds it: none of the other kinds' modules, no
    calibration (scipy), no grid model (its available power given, as ``up`` gives it)."""
    found = loaded(
        "from adnmesh.config import load_config\n"
        "from adnmesh.control.registry import build_agent\n"
        "from adnmesh.sim.node import Node\n"
        "import adnmesh.agents.der\n"
        f"config = load_config({str(configs_dir / 'simbench.yaml')!r})\n"
        "Node.for_config(build_agent('der/SGen9', config, p_avail_w=1e5), config)\n")
    assert not found["packages"] & set(HEAVY)
    others = {"adnmesh.control.cpfc_controller", "adnmesh.control.measurement_point",
              "adnmesh.control.availability_monitor", "adnmesh.tuning.problem",
              "adnmesh.loopmodel.evaluation", "adnmesh.grid"}
    assert not found["adnmesh"] & others
    assert "adnmesh.control.der_controller" in found["adnmesh"]


def test_model_params_round_trip_exactly(simbench_config):
    """The parameters ``up`` hands a DER process are the ones it would calibrate, bit for bit
    (every model of the reference case, the WT's ``inf`` ramp-down limit included)."""
    from adnmesh.control.der_model import der_params, params_from_json, params_json

    for der in simbench_config.ders:
        params = der_params(der, simbench_config, 0.7 * der.p_inst_w)
        assert params_from_json(params_json(params)) == params


def test_model_params_refused_in_one_line():
    from adnmesh.control.der_model import params_from_json

    for text in ("{", '{"model": "NoParams"}', '{"model": "PVParams", "x": 1}', "[]"):
        with pytest.raises(ValueError, match="not model parameters"):
            params_from_json(text)


def test_wt_process_with_handed_params_loads_no_scipy(configs_dir, simbench_config):
    """A WT given its parameters (as ``up`` gives them) does not calibrate: no scipy."""
    from adnmesh.control.der_model import der_params, params_json

    (wt,) = simbench_config.ders_by_id(["SGen1"])
    text = params_json(der_params(wt, simbench_config, wt.p_inst_w))
    found = loaded(
        "from adnmesh.config import load_config\n"
        "from adnmesh.control.der_model import params_from_json\n"
        "from adnmesh.control.registry import build_agent\n"
        f"config = load_config({str(configs_dir / 'simbench.yaml')!r})\n"
        f"build_agent('der/SGen1', config, p_avail_w=2e6, der_params=params_from_json({text!r}))\n")
    assert not found["packages"] & set(HEAVY)
