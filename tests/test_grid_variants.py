"""Every SimBench MV and HV grid topology (scenario 0, with and without switches) builds and
solves as pandapower's runpp does, at lW and at three other operating points."""

from __future__ import annotations

import pytest

from simbench_variants import check_code, simbench_codes

pytestmark = pytest.mark.slow

CODES = simbench_codes("MV", ("0",)) + simbench_codes("HV", ("0",))


def test_the_codes_are_every_grid_with_and_without_switches():
    grids = {c.split("--")[0] for c in CODES}
    assert grids == {"1-MV-rural", "1-MV-semiurb", "1-MV-urban", "1-MV-comm", "1-HV-mixed",
                     "1-HV-urban"}
    assert sorted(CODES) == sorted(f"{g}--0-{s}" for g in grids for s in ("sw", "no_sw"))


@pytest.mark.parametrize("code", CODES)
def test_simbench_code_builds_and_solves_as_runpp(code):
    check_code(code, operating_points=True)
