"""The year study: what an ADN can deliver over a year of profiles (``adnmesh study``).

- :mod:`~adnmesh.study.availability`: which DERs are available per interval (rules per type,
  maintenance calendar, ICT availability), a pure function of arrays.
- :mod:`~adnmesh.study.entries`: the gain table's entry and its figures for each subset (table
  lookup, on-demand tuning of the subsets it lacks, cached).
- :mod:`~adnmesh.study.ranges`: controllable range, linear range and service per interval and
  per DER left out, vectorised over the intervals of one subset.
- :mod:`~adnmesh.study.year`: the year itself: power flow per interval, the guard's blocked
  directions, the columns of the result.
- :mod:`~adnmesh.study.outputs` and :mod:`~adnmesh.study.figures`: tidy files and PNG figures.
- :mod:`~adnmesh.study.verify`: the distributed runtime on the most demanding intervals.
"""
