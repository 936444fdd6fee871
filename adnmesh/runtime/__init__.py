"""The distributed runtime behind ``adnmesh up`` (see README, section Runtime).

- :mod:`~adnmesh.runtime.messages`: bus keys, JSON Schemas, envelopes, framing;
  :mod:`~adnmesh.runtime.validator`: the schema validator generated for them;
- :mod:`~adnmesh.runtime.links`: the ICT channel model (delay, jitter, loss, outages);
- :mod:`~adnmesh.runtime.topology`: who sends what to whom, and the lookahead between agents;
- :mod:`~adnmesh.runtime.clock`: the sim clock's coordinator (conservative time advance);
- :mod:`~adnmesh.runtime.node`: one agent's event order, envelopes, links and counts, bus-free;
- :mod:`~adnmesh.runtime.process`: a node on a Zenoh session (what ``agents/*.py`` run);
- :mod:`~adnmesh.runtime.bus`: Zenoh session configuration and the shared connection flags;
- :mod:`~adnmesh.runtime.launcher`: router, agent processes, clock, recorder, shutdown;
- :mod:`~adnmesh.runtime.local`: every agent in one process, for tests and analyses;
- :mod:`~adnmesh.runtime.summary`: the end-of-run figures, from the recorded series.
"""
