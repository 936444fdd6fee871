"""The bus-free simulation layer: everything that drives agents except the bus itself.

- :mod:`~adnmesh.sim.links`: the ICT channel model (delay, jitter, loss, outages);
- :mod:`~adnmesh.sim.topology`: who sends what to whom, and the lookahead between agents;
- :mod:`~adnmesh.sim.clock`: the sim clock's coordinator (conservative time advance);
- :mod:`~adnmesh.sim.node`: one agent's event order, validation, envelopes, links and counts;
- :mod:`~adnmesh.sim.local`: every agent in one process, the same clock: the reference of the
  distributed runtime.
"""
