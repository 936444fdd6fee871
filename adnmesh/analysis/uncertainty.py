"""Model uncertainty: how far the actuator time constants may stray before loops fail
(docs/method.md#model-uncertainty).

With the table fixed, every subset's loop (as deployed, weights applied) is analysed with DER
time constants ``T_unc,d = b T_d`` for the three actuator models of
docs/method.md#model-uncertainty (``pt1``, ``pt2``,
``rhpz``; see :mod:`adnmesh.loopmodel.plant`). Starting from ``b = 1``, ``b`` is scanned down and up:

- **stability limit**: ``b_min`` is the largest ``b < 1`` at which at least one subset's closed
  loop is unstable, ``b_max`` the smallest ``b > 1`` (certified Nyquist test, exact delays);
- **2 x rise time** / **2 x settling time**: the ``b`` nearest to 1 at which, for at least one
  subset, the rise time (10-90 %) or the settling time (configured band, 5 % by default)
  reaches twice that subset's *nominal* value. The nominal value is the reference model's
  (PT1, ``b = 1``) for all three model types, because the table was designed on PT1; so a PT2 or
  RHPZ loop that is already twice as slow at ``b = 1`` is reported as failing at ``b = 1``.
  An unstable loop counts as doubled (its settling time is infinite), so these limits never
  lie beyond the stability limit.

Scan: from ``b = 1`` the bracket grows by a factor 2 per step (down to 0.01, up to 100; a limit
not reached there is reported as ``< 0.01`` / ``> 100``), then the bracket is bisected
(geometrically) until both ends agree to 3 significant digits; the limit reported is the failing
end. Bracket points evaluate every subset; bisection evaluates only the subsets that fail at
the bracket's failing end (as bisection itself, this assumes that the first subset to fail
inside the bracket is one that fails at its end). Subsets whose nominal loop is unstable are
left out and listed. Subsets with identical loops (same ``K_P K_g`` and ``K_I K_g`` for every
actuator group, e.g. DERs of equal parameters) are evaluated once and named together.

Step responses near a limit may ring for a long time: a response is simulated for at most
20 x the largest nominal settling time of the subsets evaluated together (at least 60 s), and
one that has not settled by then counts as doubled.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from adnmesh.loopmodel.evaluation import evaluate
from adnmesh.loopmodel.plant import Plant
from adnmesh.loopmodel.step_response import choose_step, step_info
from adnmesh.analysis.subset_loops import SubsetBatch

__all__ = ["MODELS", "MODEL_LABELS", "QUANTITIES", "B_RANGE", "Limit", "ModelLimits", "Sample",
           "UncertaintyResult", "analyze_uncertainty", "round_sig"]

MODELS = ("pt1", "pt2", "rhpz")
MODEL_LABELS = {"pt1": "PT1", "pt2": "PT2", "rhpz": "RHPZ"}
QUANTITIES = ("stability", "rise_time", "settling_time")
QUANTITY_LABELS = {"stability": "stability limit", "rise_time": "2·rise time",
                   "settling_time": "2·settling time"}
#: the scanned range of b
B_RANGE = (0.01, 100.0)
_FACTOR = 2.0
_HORIZON_FACTOR = 20.0
_HORIZON_MIN_S = 60.0
_FREQ_CHUNK = 256
_RING_ELEMENTS = 2e7


def round_sig(x: float, digits: int = 3) -> float:
    """``x`` rounded to ``digits`` significant digits."""
    return float(f"{x:.{digits - 1}e}")


@dataclass(frozen=True)
class Limit:
    """Result of one scan (one model, one quantity, one direction).

    Attributes
    ----------
    quantity : str
        ``"stability"``, ``"rise_time"`` or ``"settling_time"``.
    direction : str
        ``"down"`` (b < 1, gives b_min) or ``"up"`` (b > 1, gives b_max).
    status : str
        ``"found"``; ``"beyond"`` (no subset fails within :data:`B_RANGE`); ``"at nominal"``
        (some subset already fails at b = 1); ``"no subsets"``.
    b : float or None
        The limit to 3 significant digits (found), 1.0 (at nominal), else None.
    b_pass : float
        The b nearest the limit (on the side of 1) at which no subset fails.
    b_fail : float or None
        The b at which the subsets below fail (unrounded).
    subsets : tuple of str
        Names of the subsets failing at ``b_fail``.
    unstable : bool
        Those subsets fail because their loop is unstable there (doubling scans).
    """

    quantity: str
    direction: str
    status: str
    b: float | None
    b_pass: float
    b_fail: float | None
    subsets: tuple[str, ...] = ()
    unstable: bool = False

    def text(self) -> str:
        """The table cell: ``0.312``, ``< 0.01``, ``> 100``, ``1 (at b = 1)``."""
        if self.status == "found":
            return f"{self.b:.3g}"
        if self.status == "beyond":
            return f"< {B_RANGE[0]:g}" if self.direction == "down" else f"> {B_RANGE[1]:g}"
        if self.status == "at nominal":
            return "1 (fails at b = 1)"
        return "—"

    def to_json(self) -> dict:
        return {"quantity": self.quantity, "direction": self.direction, "status": self.status,
                "b": self.b, "text": self.text(), "b_pass": self.b_pass, "b_fail": self.b_fail,
                "subsets": list(self.subsets), "unstable": self.unstable}


@dataclass(frozen=True)
class ModelLimits:
    """The six limits of one actuator model: ``limits[quantity] = (down, up)``."""

    model: str
    limits: dict

    def to_json(self) -> dict:
        return {"model": self.model, "label": MODEL_LABELS[self.model],
                **{q: {"b_min": lo.to_json(), "b_max": hi.to_json()}
                   for q, (lo, hi) in self.limits.items()}}


@dataclass(frozen=True)
class Sample:
    """One evaluation of a scan: how many of the subsets evaluated fail at b."""

    model: str
    quantity: str
    direction: str
    b: float
    evaluated: int
    failing: int


@dataclass(frozen=True)
class UncertaintyResult:
    """Model-uncertainty limits of one controller over all subsets.

    Attributes
    ----------
    controller : str
        ``"adaptive"`` or ``"static"``.
    models : tuple of ModelLimits
    names : tuple of str
        Subsets analysed.
    nominal_rise_s, nominal_settling_s : ndarray
        Reference (PT1, b = 1) rise time and settling time per subset, s.
    quantities : tuple of str
        The limits scanned (keys of every ``ModelLimits.limits``).
    excluded : tuple of str
        Subsets left out because their nominal loop is unstable or does not settle.
    without_gains : tuple of str
        Subsets left out because their table entry has no PI pair.
    band_pct : float
        Settling band, percent.
    samples : tuple of Sample
        Every evaluation made, in order (``evaluated`` counts distinct loops).
    loop_classes : int
        Distinct loops among the subsets (identical loops are evaluated once).
    """

    controller: str
    models: tuple[ModelLimits, ...]
    names: tuple[str, ...]
    nominal_rise_s: np.ndarray
    nominal_settling_s: np.ndarray
    excluded: tuple[str, ...]
    without_gains: tuple[str, ...]
    band_pct: float
    quantities: tuple[str, ...] = QUANTITIES
    samples: tuple[Sample, ...] = field(default=())
    loop_classes: int = 0

    def to_json(self) -> dict:
        return {"controller": self.controller, "band_pct": self.band_pct,
                "b_range": list(B_RANGE),
                "reference": "nominal PT1 loop (b = 1) of the same subset, for every model",
                "subsets": len(self.names), "distinct_loops": self.loop_classes,
                "excluded": list(self.excluded), "without_gains": list(self.without_gains),
                "models": [m.to_json() for m in self.models],
                "samples": [s.__dict__ for s in self.samples]}


class _Evaluator:
    """Stability and step figures of the batch per (model, b), cached per loop."""

    def __init__(self, batch: SubsetBatch, band_pct: float, ref_rise, ref_settle,
                 notify: Callable[[str], None] | None):
        self.batch, self.band = batch, band_pct
        self.ref_rise, self.ref_settle = ref_rise, ref_settle
        self.notify = notify
        self.cache: dict = {}

    def _entry(self, model: str, b: float) -> dict:
        key = (model, float(b))
        if key not in self.cache:
            m = len(self.batch)
            nan = np.full(m, np.nan)
            self.cache[key] = {"stable": np.zeros(m, bool), "freq": np.zeros(m, bool),
                               "omega": nan.copy(), "step": np.zeros(m, bool),
                               "rise": nan.copy(), "settle": nan.copy()}
        return self.cache[key]

    def stable(self, model: str, b: float, rows: np.ndarray) -> np.ndarray:
        e = self._entry(model, b)
        todo = rows[~e["freq"][rows]]
        # small chunks: the certified grid is refined for the whole chunk at once
        for start in range(0, todo.size, _FREQ_CHUNK):
            part = todo[start:start + _FREQ_CHUNK]
            kp, ki = self.batch.gains(part)
            f = evaluate(self.batch.plant(model, b, part), kp, ki, classical=False,
                         time_domain=False)
            e["stable"][part], e["omega"][part], e["freq"][part] = f.stable, f.disk_omega, True
        return e["stable"][rows]

    def _step_chunk(self, plant, rows: np.ndarray, omega: np.ndarray) -> int:
        """Loops per simulation so that the delay buffers stay within ~160 MB each."""
        h = min(choose_step(Plant(plant.actuators, plant.gains_w[i], plant.t_com_s,
                                  plant.t_meas_s), omega[i]) for i in range(rows.size))
        ring = (float(plant.loop_delays_s.max()) + plant.t_meas_s) / h + 3
        return max(16, int(_RING_ELEMENTS / ring))

    def step(self, model: str, b: float, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        stable = self.stable(model, b, rows)
        e = self._entry(model, b)
        todo = rows[stable & ~e["step"][rows]]
        todo = todo[np.argsort(self.ref_settle[todo], kind="stable")]   # similar horizons
        if todo.size:
            plant = self.batch.plant(model, b, todo)
            chunk = self._step_chunk(plant, todo, e["omega"][todo])
            for start in range(0, todo.size, chunk):
                part = todo[start:start + chunk]
                if self.notify is not None:
                    self.notify(f"{MODEL_LABELS[model]} b = {b:.4g}: step responses "
                                f"{start}/{todo.size}")
                t_max = max(_HORIZON_MIN_S,
                            _HORIZON_FACTOR * float(np.max(self.ref_settle[part])))
                kp, ki = self.batch.gains(part)
                info = step_info(self.batch.plant(model, b, part), kp, ki, band_pct=self.band,
                                 bandwidth_rad_s=e["omega"][part], t_max_s=t_max)
                e["rise"][part], e["settle"][part] = info.rise_time_s, info.settling_time_s
                e["step"][part] = True
        return e["rise"][rows], e["settle"][rows]

    def fails(self, quantity: str, model: str, b: float, rows: np.ndarray):
        """(fails per row, unstable per row) for ``quantity`` at ``b``."""
        stable = self.stable(model, b, rows)
        if quantity == "stability":
            return ~stable, ~stable
        rise, settle = self.step(model, b, rows)
        if quantity == "rise_time":
            ok = rise < 2.0 * self.ref_rise[rows]
        else:
            ok = settle < 2.0 * self.ref_settle[rows]
        return ~(stable & ok), ~stable


def _converged(a: float, b: float) -> bool:
    return round_sig(a) == round_sig(b) or max(a, b) / min(a, b) < 1.0 + 1e-6


def _scan(ev: _Evaluator, model: str, quantity: str, direction: str, rows: np.ndarray,
          edge: float, names: list[tuple[str, ...]], samples: list) -> Limit:
    """Bracket from b = 1 towards ``edge`` by factors of 2, then bisect (module docstring)."""
    if rows.size == 0:
        return Limit(quantity, direction, "no subsets", None, 1.0, None)

    def test(b, r):
        fails, unstable = ev.fails(quantity, model, b, r)
        samples.append(Sample(model, quantity, direction, float(b), int(r.size),
                              int(fails.sum())))
        return fails, unstable

    def result(status, b_pass, b_fail, r, fails, unstable):
        bad = r[fails]
        return Limit(quantity, direction, status,
                     None if b_fail is None else (1.0 if status == "at nominal"
                                                  else round_sig(b_fail)),
                     b_pass, b_fail, tuple(n for i in bad for n in names[i]),
                     bool(unstable[fails].all()) if fails.any() else False)

    fails, unstable = test(1.0, rows)
    if fails.any():
        return result("at nominal", 1.0, 1.0, rows, fails, unstable)
    up = direction == "up"
    b_pass, b_fail = 1.0, None
    while b_fail is None:
        b = b_pass * _FACTOR if up else b_pass / _FACTOR
        b = min(b, edge) if up else max(b, edge)
        fails, unstable = test(b, rows)
        if fails.any():
            b_fail, witnesses, wf, wu = b, rows[fails], fails[fails], unstable[fails]
        elif b == edge:
            return Limit(quantity, direction, "beyond", None, b, None)
        else:
            b_pass = b
    while not _converged(b_pass, b_fail):
        mid = float(np.sqrt(b_pass * b_fail))
        fails, unstable = test(mid, witnesses)
        if fails.any():
            b_fail, witnesses, wf, wu = mid, witnesses[fails], fails[fails], unstable[fails]
        else:
            b_pass = mid
    return result("found", b_pass, b_fail, witnesses, wf, wu)


def analyze_uncertainty(batch: SubsetBatch, band_pct: float, controller: str = "adaptive",
                        models=MODELS, quantities=QUANTITIES,
                        nominal: tuple[np.ndarray, np.ndarray] | None = None,
                        notify: Callable[[str], None] | None = None,
                        scan_done: Callable[[], None] | None = None) -> UncertaintyResult:
    """Stability and doubling limits in ``b`` for every model over all subsets of ``batch``.

    Parameters
    ----------
    batch : SubsetBatch
        The loops as deployed (gains 1/W and 1/(W s), weights applied).
    band_pct : float
        Settling band, percent.
    controller : str
        Name used in the result (``"adaptive"`` or ``"static"``).
    models : sequence of str
        Actuator models to analyse.
    quantities : sequence of str
        Which limits to scan (:data:`QUANTITIES`; the doubling scans use the stability
        limit as their bound when it is scanned too).
    nominal : (rise_time_s, settling_time_s), optional
        Nominal PT1 figures per subset if already known (e.g. from the robustness analysis).
    notify : callable, optional
        Called with a short status text before costly evaluations.
    scan_done : callable, optional
        Called after each of the ``2 len(models) len(quantities)`` scans.
    """
    names = batch.names
    valid = batch.has_gains
    if nominal is None:
        rise, settle = np.full(len(batch), np.nan), np.full(len(batch), np.nan)
        idx = np.nonzero(valid)[0]
        if idx.size:
            kp, ki = batch.gains(idx)
            f = evaluate(batch.plant(rows=idx), kp, ki, band_pct=band_pct, classical=False)
            rise[idx] = np.where(f.stable, f.rise_time_s, np.nan)
            settle[idx] = np.where(f.stable, f.settling_time_s, np.nan)
    else:
        rise, settle = (np.asarray(x, float) for x in nominal)
    good = valid & np.isfinite(rise) & np.isfinite(settle)
    # identical loops are evaluated once; a failing class names all its subsets
    first, cls = batch.loop_classes()
    members = [[] for _ in first]
    for i, c in enumerate(cls):
        members[c].append(names[i])
    reps = batch.select(first)
    ev = _Evaluator(reps, band_pct, rise[first], settle[first], notify)
    rows = np.nonzero(good[first])[0]
    class_names = [tuple(m) for m in members]
    samples: list[Sample] = []
    out = []
    for model in models:
        limits = {}
        for quantity in quantities:
            if quantity not in QUANTITIES:
                raise ValueError(f"unknown quantity {quantity!r}")
            pair = []
            for direction, edge in (("down", B_RANGE[0]), ("up", B_RANGE[1])):
                if quantity != "stability" and "stability" in limits:
                    stab = limits["stability"][0 if direction == "down" else 1]
                    if stab.status == "found":
                        edge = stab.b_fail
                if notify is not None:
                    notify(f"{MODEL_LABELS[model]} {QUANTITY_LABELS[quantity]} {direction}")
                pair.append(_scan(ev, model, quantity, direction, rows, edge, class_names,
                                  samples))
                if scan_done is not None:
                    scan_done()
            limits[quantity] = tuple(pair)
        out.append(ModelLimits(model, limits))
        ev.cache.clear()
    return UncertaintyResult(controller, tuple(out), tuple(names), rise, settle,
                             tuple(n for n, g, v in zip(names, good, valid) if v and not g),
                             tuple(n for n, v in zip(names, valid) if not v), band_pct,
                             tuple(quantities), tuple(samples), len(first))
