"""The lookahead as it was computed before scipy's shortest paths replaced it: all-pairs least
delay by Floyd-Warshall in plain Python (cubic in the agents: minutes for 1,000 DERs).
:func:`adnmesh.sim.topology._lookahead` must return exactly this dict (tests/test_sim.py)."""
from __future__ import annotations

import math

INF_NS = math.inf


def lookahead_reference(agents, links, receivers) -> dict[tuple[str, str], int]:
    """All-pairs least delay (Floyd-Warshall); the diagonal holds the shortest cycle."""
    dist = {(a, b): INF_NS for a in agents for b in agents}
    for (sender, key), link in links.items():
        for to in receivers[key]:
            dist[(sender, to)] = min(dist[(sender, to)], link.min_delay_ns)
    for k in agents:
        for i in agents:
            d_ik = dist[(i, k)]
            if d_ik == INF_NS:
                continue
            for j in agents:
                through = d_ik + dist[(k, j)]
                if through < dist[(i, j)]:
                    dist[(i, j)] = through
    return {pair: int(d) for pair, d in dist.items() if d != INF_NS}


def coordinator_sources_reference(agents, lookahead_ns) -> list[tuple[tuple[int, int], ...]]:
    """For each receiver ``b``: ``(index of p, lookahead(p, b))`` over the agents ``p`` that
    reach it, nearest first (then by index), as :class:`adnmesh.sim.clock.Coordinator` built
    them before (a pass over every pair per receiver: cubic)."""
    index = {a: i for i, a in enumerate(agents)}
    return [tuple(sorted(((index[p], d) for (p, q), d in lookahead_ns.items() if q == b),
                         key=lambda pd: (pd[1], pd[0])))
            for b in agents]
