"""Where an agent process runs: the run of one grid, or a level of a hierarchy of ADNs.

An agent program loads its config and builds its agent and node (:class:`Place`). In the run
of one grid that is the config's own agent on the config's topology. In a hierarchy's run
(``adnmesh up HIERARCHY``, docs/hierarchy.md) ``up`` adds ``--levels FILE --level GRID``: the
config is the level's on the bus (:func:`adnmesh.sim.hierarchy_levels.on_bus`), the agent is
the level's (:meth:`adnmesh.sim.hierarchy_levels.Levels.agent`: the site agent, the ADN's
measurement with its exchange, the upper CPFC with its rule), and its node routes over the
whole hierarchy's topology under the name ``<grid>:<agent id>`` -- exactly as the in-process
run (:mod:`adnmesh.sim.hierarchy_run`) builds it.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

from adnmesh.runtime.process import load_config_or_exit
from adnmesh.sim.node import Node

__all__ = ["Place", "place_or_exit"]


class Place:
    """The config, agent and node of an agent process (see the module docstring).

    Parameters
    ----------
    config : Config
        The agent's config (a level's: as on the bus).
    levels : adnmesh.sim.hierarchy_levels.Levels, optional
        The hierarchy's levels; None in the run of one grid.
    """

    def __init__(self, config, levels=None) -> None:
        self.config = config
        self.levels = levels

    def agent(self, agent_id: str, make: Callable[[], object]):
        """The state machine of ``agent_id``: ``make()``, or the level's agent."""
        if self.levels is None:
            return make()
        return self.levels.agent(self.config.grid, agent_id, make)

    def schedule(self, make: Callable[[], object]):
        """The CPFC's gain schedule: ``make()``, or the level's (its table)."""
        if self.levels is None:
            return make()
        return self.levels.schedule(self.config.grid)

    def identity(self, agent_id: str) -> str:
        """Who the agent is on the bus (its certificate in the secure profile): its id, or in
        a hierarchy ``<grid>:<agent id>`` (agent ids repeat across the levels)."""
        if self.levels is None:
            return agent_id
        from adnmesh.sim.hierarchy_topology import qualified
        return qualified(self.config.grid, agent_id)

    def topology(self):
        """The topology of one process's agents (None: each node takes its config's)."""
        return None if self.levels is None else self.levels.topology

    def node(self, agent, start_ns: int = 0, topology=None) -> Node:
        """The node of ``agent`` (on ``topology``, if given: one for the agents of a process)."""
        if self.levels is None:
            return Node.for_config(agent, self.config, start_ns=start_ns, topology=topology)
        from adnmesh.sim.hierarchy_topology import qualified
        return Node(agent, topology or self.levels.topology, self.config.runtime.seed,
                    start_ns=start_ns, node_id=qualified(self.config.grid, agent.agent_id))


def place_or_exit(args) -> Place:
    """The place of an agent program from its arguments (``config``, ``--levels``,
    ``--level``); on an error print one line and exit with code 2."""
    from adnmesh.errors import ConfigError

    config = load_config_or_exit(args.config)
    if args.levels is None and args.level is None:
        return Place(config)
    if args.levels is None or args.level is None:
        _exit("--levels and --level go together (a hierarchy's run, set by adnmesh up)")
    from adnmesh.sim.hierarchy_levels import load_levels
    try:
        levels = load_levels(args.levels, lambda path: load_config_or_exit(path))
        level = levels.config(args.level)
    except ConfigError as exc:
        _exit(str(exc))
    if level.path is None or Path(level.path).resolve() != Path(config.path).resolve():
        _exit(f"{args.config} is not the config of level {args.level} in {args.levels}")
    return Place(level, levels)


def _exit(text: str) -> None:
    print(f"adnmesh agent: error: {text}", file=sys.stderr)
    raise SystemExit(2)
