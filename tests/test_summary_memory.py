"""The summary's series stay small in a long run (issue 39: up's memory flat over an hour)."""

from __future__ import annotations

import math
import random
import tracemalloc

from adnmesh.results.summary import GridFigures, GridFold, RunSeries


def _listed(bodies: list[dict]) -> GridFigures:
    """The grid figures as ``min``/``max``/``sum`` over the list of every body take them."""
    g = bodies
    return GridFigures(min(x["v_min_pu"] for x in g), max(x["v_max_pu"] for x in g),
                       max(x["line_loading_max_pct"] for x in g),
                       max(x["trafo_loading_max_pct"] for x in g), sum(x["samples"] for x in g),
                       sum(x["outside_band"] for x in g), sum(x["not_converged"] for x in g),
                       tuple(x["t_send_ns"] * 1e-9 for x in g if x["outside_band"]))


def _body(rng: random.Random, t_ns: int) -> dict:
    def value(low, high):
        return math.nan if rng.random() < 0.05 else rng.uniform(low, high)
    return {"t_send_ns": t_ns, "v_min_pu": value(0.9, 1.0), "v_max_pu": value(1.0, 1.1),
            "line_loading_max_pct": value(0, 120), "trafo_loading_max_pct": value(0, 120),
            "samples": 100, "outside_band": rng.choice([0, 0, 0, 3]),
            "not_converged": rng.choice([0, 0, 1])}


def test_grid_fold_gives_what_the_list_of_bodies_gave_nans_included():
    rng = random.Random(7)
    for run in range(30):
        bodies = [_body(rng, i * 1_000_000_000) for i in range(rng.randint(1, 60))]
        fold = GridFold()
        for body in bodies:
            fold.add(body)
        assert repr(fold.figures()) == repr(_listed(bodies)), run   # NaN == NaN by repr
    assert GridFold().figures() is None and not GridFold()


def test_p_ip_series_costs_about_16_bytes_a_sample():
    series = RunSeries()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for i in range(100_000):        # 1,000 s of 10 ms samples
            series.add("p_ip", {"t_send_ns": i * 10_000_000, "p_ip_w": 1.0e6 + i * 0.25})
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert len(series.p_ip_w) == 100_000 and series.p_ip_w[-1] == 1.0e6 + 99_999 * 0.25
    assert grown < 100_000 * 24, grown     # a list of Python int and float: ~100 bytes a sample
