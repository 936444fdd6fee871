"""Which DERs are available in each interval of a year (docs/study.md#availability).

A DER is an actuator of the CPFC in an interval when all of these hold:

1. its available power exceeds its type's ``study.min_output_share`` of its installed power
   (reason ``low output`` otherwise: a wind turbine near cut-in, a PV plant at night, a
   plant out of service in the net, whose profile is zero);
2. it is not in a ``study.maintenance`` window (reason ``maintenance``);
3. its ICT link works: an independent draw per DER and interval with probability
   ``study.ict_availability`` from ``numpy.random.default_rng(seed)`` (reason ``ict``).

Reasons are checked in that order; the first that holds is the one recorded. Pure numpy.
"""

from __future__ import annotations

import numpy as np

__all__ = ["AVAILABLE", "LOW_OUTPUT", "MAINTENANCE", "ICT", "REASONS", "availability",
           "window_mask", "parse_time"]

AVAILABLE, LOW_OUTPUT, MAINTENANCE, ICT = 0, 1, 2, 3
#: reason code -> words
REASONS = {AVAILABLE: "available", LOW_OUTPUT: "low output", MAINTENANCE: "maintenance",
           ICT: "ict"}


def parse_time(text: str) -> np.datetime64:
    """``2016-06-01`` or ``2016-06-01T12:00`` (or with a space) as datetime64[m];
    ``ValueError`` for anything else (a zone, another format, a day that does not exist)."""
    import datetime
    import re

    if not re.fullmatch(r"\d{4}-\d{2}-\d{2}([T ]\d{2}:\d{2})?", text.strip()):
        raise ValueError(f"not a date or time: {text!r}")
    moment = datetime.datetime.fromisoformat(text.strip().replace(" ", "T"))
    return np.datetime64(moment.strftime("%Y-%m-%dT%H:%M"), "m")


def window_mask(times: np.ndarray, start: str, end: str) -> np.ndarray:
    """Which ``times`` (datetime64) lie in ``[start, end)``."""
    return (times >= parse_time(start)) & (times < parse_time(end))


def availability(p_avail_w: np.ndarray, p_inst_w: np.ndarray, min_share: np.ndarray,
                 times: np.ndarray, maintenance, der_ids, ict_availability: float,
                 seed: int, first_interval: int = 0) -> np.ndarray:
    """The reason code of every DER in every interval (``AVAILABLE`` where it is one).

    Parameters
    ----------
    p_avail_w : ndarray, shape (T, n)
        Each DER's available power per interval, W.
    p_inst_w, min_share : ndarray, shape (n,)
        Installed power, W, and the least share of it that counts as available.
    times : ndarray of datetime64, shape (T,)
    maintenance : sequence of ``adnmesh.config.Maintenance``
    der_ids : sequence of str
        The DERs' ids, in the columns' order.
    ict_availability : float
        Probability that a link works in an interval.
    seed : int
        Seed of the ICT draws.
    first_interval : int
        Index of the first row in the whole year: the draws of an interval do not depend on
        which part of the year is studied.
    """
    reason = np.full(p_avail_w.shape, AVAILABLE, dtype=np.int8)
    column = {d: i for i, d in enumerate(der_ids)}
    if ict_availability < 1.0:
        total = first_interval + p_avail_w.shape[0]
        draws = np.random.default_rng(seed).random((total, p_avail_w.shape[1]))
        reason[draws[first_interval:] >= ict_availability] = ICT
    for window in maintenance:
        rows = window_mask(times, window.start, window.end)
        cols = [column[d] for d in window.ders]
        reason[np.ix_(rows, cols)] = MAINTENANCE
    low = ~(p_avail_w > min_share[None, :] * p_inst_w[None, :])
    reason[low] = LOW_OUTPUT
    return reason
