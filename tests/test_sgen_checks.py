"""``check`` knows what ``up`` knows of the grid (issue 40.2): closest names for a misspelt
sgen and study case, ``p_inst_w`` against the sgen's rating, a type against the sgen's."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from adnmesh.cli import main

SIMBENCH = Path(__file__).resolve().parents[1] / "configs" / "simbench.yaml"


def _variant(tmp_path: Path, edit) -> Path:
    document = yaml.safe_load(SIMBENCH.read_text())
    edit(document)
    path = tmp_path / "variant.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["ders"][1].update(sgen="MV1.101 MV SGen2"),
     "no static generator named 'MV1.101 MV SGen2' (102 sgens; closest: 'MV1.101 MV SGen 2'"),
    (lambda d: d["grid_model"].update(study_case="lw"),
     "unknown study case 'lw' (this grid has: hL, n1, hW, hPV, lW, lPV); did you mean 'lW'? "
     "study cases are case-sensitive"),
    (lambda d: d["ders"][6].update(p_inst_w=9.9e6),
     "ders[6].p_inst_w: 9.9 MW is more than its sgen 'MV1.101 MV SGen 7' is rated for, 1.8 MW "
     "(the net's sn_mva)"),
    (lambda d: d["ders"][10].update(sgen="MV1.101 MV SGen 11"),      # the hydro plant as a CHP
     "ders[10].type: CHP, but its sgen 'MV1.101 MV SGen 11' is a Hydro_MV plant (HYDRO)"),
])
def test_check_refuses_in_one_line_what_up_would(tmp_path, capsys, edit, message) -> None:
    path = _variant(tmp_path, edit)
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"adnmesh: error: {path}: "), err
    assert message in err, err
