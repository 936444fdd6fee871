"""The SimBench grid: its study case, a fast warm-started AC power flow and a disk cache.

Pure numerics plus one disk cache; no bus, no agents. The measurement agent needs two calls::

    data = load_grid("1-MV-rural--0-no_sw", case="lW")           # cached: ~1 s the second time
    solver = GridSolver(data, actuator_sgens=[der.sgen for der in config.ders])
    sample = solver.solve(p_w)                                   # GridSample, W / var / p.u. / %

and :func:`available_power_w` gives each actuator's available power at the study case.

Modules: :mod:`~adnmesh.grid.data` (the lightsim2grid model and arrays, the names of its buses,
lines and transformers, their tap changers), :mod:`~adnmesh.grid.solver` (the solver, where the
extremes are, taps), :mod:`~adnmesh.grid.sensitivity` (how P_IP and Q_IP, the bus voltages and
the branch loadings move with each actuator's P and Q), :mod:`~adnmesh.grid.cache` (the cache),
:mod:`~adnmesh.grid.simbench_net` and :mod:`~adnmesh.grid.from_net` (the only users of simbench and
pandapower, imported on a cache miss only).
"""

from adnmesh.grid.cache import default_cache_dir, load_grid
from adnmesh.grid.data import GridData
from adnmesh.errors import GridError
from adnmesh.grid.solver import GridSample, GridSolver, available_power_w

__all__ = ["GridData", "GridError", "GridSample", "GridSolver", "available_power_w",
           "default_cache_dir", "load_grid"]
