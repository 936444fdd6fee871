"""Analyses of a scheduling table (docs/method.md#analyses), behind ``adnmesh analyze``.

- :mod:`~adnmesh.analysis.robustness`: figures of merit of every subset, adaptive vs static;
- :mod:`~adnmesh.analysis.uncertainty`: stability and doubling limits of the time-constant
  factor b for the PT1, PT2 and RHPZ actuator models;
- :mod:`~adnmesh.analysis.solution_space`: feasibility and rise time over one subset's
  (K_P, K_I) plane, with the paper method's search path;
- :mod:`~adnmesh.analysis.subset_loops`: subsets as one batch of loops (as deployed, weights applied);
- :mod:`~adnmesh.analysis.report` (markdown) and :mod:`~adnmesh.analysis.plots` (matplotlib,
  Agg canvas) turn results into text and figures.

The analysis functions are pure: they take a config and a table (or a batch) and return
dataclasses; files are written by :mod:`adnmesh.commands.analyze`.
"""
