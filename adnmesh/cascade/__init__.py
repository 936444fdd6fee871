"""ADNs as actuators of an upper controller: the nested (cascade) loop and its certificate
(docs/hierarchy.md).

An upper CPFC acts on whole MV ADNs. Each lower ADN runs its own PI on its own DERs, so what
the upper controller drives is the ADN's *closed* loop ``T_i(s)`` from its reference offset to
its DERs' infeed. This package holds the pure numerics of that cascade:

- :mod:`~adnmesh.cascade.lower_adn`: one ADN as an actuator (its active table entry's exact
  closed loop, its range, its equivalent first-order-plus-dead-time model),
- :mod:`~adnmesh.cascade.nested_loop`: the upper open loop over the ADNs' exact closed loops
  with the inter-site delays, its Nyquist stability and its disk margin,
- :mod:`~adnmesh.cascade.nested_step`: the step response of the whole nested loop with exact
  delays (every DER lag, every lower PI, every delay),
- :mod:`~adnmesh.cascade.certificate`: the upper loop's figures and verdict against the design
  constraints, and the back-off that restores them,
- :mod:`~adnmesh.cascade.upper_table`: the upper table, tuned on the equivalent models and
  certified on the exact cascade.
"""
