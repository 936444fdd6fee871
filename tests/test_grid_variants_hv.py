"""The SimBench HV scenarios 1 and 2 (storages, more generation), each in one switch
variant (both are checked on scenario 0), build at lW, their model checked against pandapower's
runpp by the build itself."""

from __future__ import annotations

import pytest

from simbench_variants import check_code, simbench_codes

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("code", simbench_codes("HV", ("1", "2"), one_switch_variant=True))
def test_simbench_scenario_code_builds(code):
    check_code(code, operating_points=False)
