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
