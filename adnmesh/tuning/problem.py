"""The tuning problem of one config: subsets as normalised plants, and the feasibility check.

Every subset A of a config's DERs is a *normalised plant*: the config's distinct actuator
groups (same dynamics) with the fraction ``f_g = sum_{d in A, d in g} P_inst,d / sum_A P_inst``
of the subset's installed power in each group. Two subsets with equal fraction vectors are the
same tuning problem (e.g. every subset of identical wind turbines): the normalised gains
``kp_n = K_P * sum_A P_inst`` (dimensionless) and ``ki_n = K_I * sum_A P_inst`` (1/s) are
shared, and ``K_P = kp_n / sum_A P_inst`` (1/W), ``K_I = ki_n / sum_A P_inst`` (1/(W s)).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from adnmesh.loopmodel.evaluation import LoopFigures, disk_margin_bound, evaluate
from adnmesh.loopmodel.plant import Actuator, Plant
from adnmesh.loopmodel.step_response import integral_rate, step_info
from adnmesh.tuning.robust_set import Member, UncertaintyBox
from adnmesh.tuning.subset_selection import all_subsets

__all__ = ["TuningProblem", "Check", "all_subsets", "T_MAX_S", "horizon_s", "MAX_EXACT_CLASSES",
           "nominal_by_type"]

#: longest simulated step response in a constraint check, s
T_MAX_S = 20000.0
#: frequencies per decade of :meth:`TuningProblem.may_meet_disk_margin`'s sampled bound (the
#: certified grid has 100: 4x the cost, and on SimBench's global grid only 0.3 % fewer
#: candidates left for a full check)
SCREEN_PER_DECADE = 25
#: a weak loop is simulated for this many of its slow time constants at least: twice the
#: step response's own horizon floor (20 / bandwidth, the bandwidth at least the integral
#: rate), so that it can settle within the horizon
SLOW_MODES = 40.0
#: ... but never longer than this, s
HORIZON_CAP_S = 1e6
#: more distinct dynamics (actuator groups) than this: the searches run on the per-type
#: design plant (:meth:`TuningProblem.design`)
MAX_EXACT_CLASSES = 8


def horizon_s(gains: np.ndarray, kp, ki) -> np.ndarray:
    """Longest step-response horizon of loops, s: ``T_MAX_S``, or ``SLOW_MODES`` times the
    loop's slow time constant ``(1 + K_P K) / (K_I K)`` (``K`` its gain in W: the PI's
    integral mode with the plant at its DC gain, :func:`adnmesh.loopmodel.step_response.integral_rate`)
    if that is longer, capped at ``HORIZON_CAP_S``; shape (M,).

    A DER with a tiny share of a subset's power (Find W), or a small subset under a static
    pair that suits the largest ones, has a loop so weak that it settles only after hours of
    simulated time; judged on ``T_MAX_S`` alone it counts as "slow". Its constraints (disk
    margin, overshoot) still have to be decided, so its response is simulated until it
    settles.
    """
    return np.clip(SLOW_MODES / integral_rate(gains, kp, ki), T_MAX_S, HORIZON_CAP_S)


@dataclass(frozen=True)
class Check:
    """Feasibility of candidates (arrays of shape (M,)).

    ``rise_time_s`` is NaN where infeasible; ``overshoot_pct`` may be a lower bound there.
    ``disk_margin`` is an upper bound (below the limit) where the sampled disk margin already
    decided the candidate (reason ``disk margin``; see :func:`adnmesh.loopmodel.evaluation.evaluate`'s
    ``screen``). ``simulated_rise_s`` is the rise time of every simulated response, feasible
    or not (NaN where not simulated or not at 90 % when the simulation stopped).
    """

    feasible: np.ndarray
    disk_margin: np.ndarray
    overshoot_pct: np.ndarray
    rise_time_s: np.ndarray
    reason: np.ndarray            # "", "unstable", "disk margin", "overshoot", "slow"
    simulated_rise_s: np.ndarray


def nominal_by_type(config, der_ids=None) -> dict:
    """Per DER type, the actuator with the installed-power-weighted mean delay (to 10 ms) and
    lag, s, of the config's DERs (of ``der_ids`` only, if given)."""
    out = {}
    chosen = config.ders if der_ids is None else config.ders_by_id(der_ids)
    for t in dict.fromkeys(d.type for d in chosen):
        ders = [d for d in chosen if d.type == t]
        p = np.array([float(d.p_inst_w) for d in ders])
        # to 10 ms: a mean of delays is no common multiple of them (tiny simulation steps)
        delay = round(float(np.dot(p, [float(d.t_delay_s) for d in ders]) / p.sum()), 2)
        lag = float(np.dot(p, [config.t_lag_s(d) for d in ders]) / p.sum())
        out[t] = Actuator(delay, lag)
    return out


class TuningProblem:
    """Normalised plants of a config's subsets and the constraint check.

    Parameters
    ----------
    config : adnmesh.config.Config
    disk_margin_min : float, optional
        Constraint alpha >= this (default: the config's).
    overshoot_max_pct : float, optional
        Constraint overshoot < this, percent (default: the config's).
    by_type : bool
        One *design* group per DER type, with the installed-power-weighted mean delay (to
        10 ms) and lag of its DERs (a reduced plant for configs whose DERs all differ; entries are still
        certified on the exact plant), instead of one group per distinct dynamics.
    """

    def __init__(self, config, disk_margin_min: float | None = None,
                 overshoot_max_pct: float | None = None, by_type: bool = False):
        self.config = config
        c = config.constraints
        self.disk_margin_min = c.disk_margin_min if disk_margin_min is None else disk_margin_min
        self.overshoot_max_pct = (c.overshoot_max_pct if overshoot_max_pct is None
                                  else overshoot_max_pct)
        self.band_pct = c.settling_band_pct
        robust = c.robust
        # with an uncertainty set every group is of one DER type (types stray independently)
        groups: dict[tuple, int] = {}
        self.group_of: dict[str, int] = {}
        nominal = nominal_by_type(config) if by_type else {}
        for der in config.ders:
            act = nominal.get(der.type) or Actuator(float(der.t_delay_s), config.t_lag_s(der))
            key = (act, der.type if robust is not None else None)
            self.group_of[der.id] = groups.setdefault(key, len(groups))
        self.actuators = tuple(a for a, _ in groups)
        self.group_types = tuple(next(d.type for d in config.ders if self.group_of[d.id] == g)
                                 for g in range(len(groups)))
        self.p_inst = {d.id: float(d.p_inst_w) for d in config.ders}
        #: the uncertainty set (None: the reference model alone)
        self.box = (None if robust is None
                    else UncertaintyBox(robust, self.actuators, self.group_types))
        #: members of the set every check covers besides the reference model
        self.members: list[Member] = []
        self._member_actuators: list[tuple[Actuator, ...]] = []
        if self.box is not None:
            self.add_members(self.box.design_members())

    def add_members(self, members) -> None:
        """Make every check cover ``members`` of the set too (the certificate adds a member
        an entry failed on before it backs the entry off)."""
        for m in members:
            acts = self.box.actuators_of(m)
            # a member that is the reference model (a set of pt1 with b = 1 and no added
            # dead time somewhere) is checked already
            if m not in self.members and acts != self.actuators:
                self.members.append(m)
                self._member_actuators.append(acts)

    def types_in(self, gains: np.ndarray) -> set[str]:
        """The DER types of the groups with a gain in ``gains`` (shape (G,))."""
        return {t for t, g in zip(self.group_types, gains) if g > 0}

    def member_plant(self, member: Member, gains: np.ndarray) -> Plant:
        """The plant of ``member`` of the set with group gains ``gains`` (shape (G,) or
        (M, G))."""
        return Plant(self.box.actuators_of(member), gains, self.config.design_t_com_s,
                     self.config.t_meas_s)

    def design(self) -> "TuningProblem":
        """The problem the searches run on: this one, or with more than
        :data:`MAX_EXACT_CLASSES` dynamics classes the per-type design plant (``by_type``,
        same constraints); entries are certified on this one either way."""
        if len(self.actuators) <= MAX_EXACT_CLASSES:
            return self
        return TuningProblem(self.config, self.disk_margin_min, self.overshoot_max_pct,
                             by_type=True)

    @property
    def constraints(self) -> dict:
        return {"disk_margin_min": self.disk_margin_min,
                "overshoot_max_pct": self.overshoot_max_pct,
                "settling_band_pct": self.band_pct}

    def group_power(self, ders: Sequence[str], weights: dict | None = None) -> np.ndarray:
        """Installed power (times weight) of the subset per actuator group, W; shape (G,)."""
        out = np.zeros(len(self.actuators))
        for d in ders:
            out[self.group_of[d]] += self.p_inst[d] * (1.0 if weights is None else weights[d])
        return out

    def fractions(self, ders: Sequence[str]) -> tuple[np.ndarray, float]:
        """(normalised plant f_g, shape (G,); total installed power of the subset, W)."""
        power = self.group_power(ders)
        return power / power.sum(), float(power.sum())

    @staticmethod
    def key(fractions: np.ndarray) -> tuple:
        """Hashable identity of a normalised plant (fractions to 12 digits)."""
        return tuple(np.round(fractions, 12))

    def plant(self, gains: np.ndarray) -> Plant:
        """Plant with group gains ``gains`` (shape (G,) or (M, G))."""
        return Plant(self.actuators, gains, self.config.design_t_com_s, self.config.t_meas_s)

    def average_time_s(self, fractions: np.ndarray) -> np.ndarray:
        """``T_avg = sum_a (T_delay,a + T_rise,a) P_a / sum_a P_a``, s; shape (M,)
        (docs/method.md#convexity-indicator-and-area-search)."""
        per_group = np.array([a.t_delay_s + a.t_lag_s * self.config.rise_per_lag
                              for a in self.actuators])
        return np.atleast_2d(fractions) @ per_group

    def figures(self, gains: np.ndarray, kp, ki, classical: bool = True,
                t_max_s=T_MAX_S) -> LoopFigures:
        """All figures of merit (full step info, no shortcuts) — for reporting; step
        responses simulated for at most ``t_max_s`` (s, one or one per candidate)."""
        return evaluate(self.plant(gains), kp, ki, band_pct=self.band_pct, classical=classical,
                        t_max_s=t_max_s)

    def may_meet_disk_margin(self, gains: np.ndarray, kp, ki) -> np.ndarray:
        """False where a candidate violates the disk-margin constraint for certain (its
        disk margin sampled at :data:`SCREEN_PER_DECADE` frequencies per decade, an upper
        bound, is below the limit); True where only :meth:`check` can tell. Far cheaper than
        a check: no certification, no refinement."""
        ok = disk_margin_bound(self.plant(gains), kp, ki, SCREEN_PER_DECADE) >= self.disk_margin_min
        if not self._member_actuators:
            return ok
        gains = np.atleast_2d(gains)
        for acts in self._member_actuators:
            rows = np.nonzero(ok)[0]
            if rows.size == 0:
                break
            plant = Plant(acts, np.broadcast_to(gains, (ok.size, gains.shape[1]))[rows],
                          self.config.design_t_com_s, self.config.t_meas_s)
            ok[rows] = (disk_margin_bound(plant, np.broadcast_to(kp, ok.shape)[rows],
                                          np.broadcast_to(ki, ok.shape)[rows], SCREEN_PER_DECADE)
                        >= self.disk_margin_min)
        return ok

    def check(self, gains: np.ndarray, kp, ki, simulate=None,
              t_max_s: float = T_MAX_S) -> Check:
        """Constraint check of M candidates; rise time of the feasible ones.

        ``gains`` (M, G) or (G,) are group gains (fractions for normalised gains). Candidates
        violating the disk margin are not simulated, and a simulation stops as soon as the
        overshoot limit is exceeded. ``simulate`` (bool, shape (M,)) restricts the step
        responses to some candidates: the others get only the frequency-domain verdict
        (``feasible`` False, ``reason`` "" if they meet the disk margin — not yet decided).
        A response that has not settled within ``t_max_s`` (s) is not feasible either (its
        overshoot is not known): reason ``slow``.

        With an uncertainty set, a candidate is feasible only if it is on the reference model
        and on every member in :attr:`members` too; its disk margin is the lowest and its
        overshoot the highest of those checked, its rise time the reference model's (the
        objective), its reason the first failing plant's.
        """
        nominal = self._check_plant(self.plant(gains), kp, ki, simulate, t_max_s)
        if not self._member_actuators:
            return nominal
        m = nominal.feasible.size
        gains = np.broadcast_to(np.atleast_2d(gains), (m, len(self.actuators)))
        kp, ki = np.broadcast_to(kp, (m,)), np.broadcast_to(ki, (m,))
        sim = np.ones(m, bool) if simulate is None else np.asarray(simulate, bool)
        t_max = np.broadcast_to(np.asarray(t_max_s, float), (m,))
        feasible = nominal.feasible.copy()
        reason = nominal.reason.copy()
        dm, over = nominal.disk_margin.copy(), nominal.overshoot_pct.copy()
        for acts in self._member_actuators:
            rows = np.nonzero(reason == "")[0]          # feasible, or met the disk margin
            if rows.size == 0:
                break
            plant = Plant(acts, gains[rows], self.config.design_t_com_s, self.config.t_meas_s)
            c = self._check_plant(plant, kp[rows], ki[rows], sim[rows], t_max[rows])
            feasible[rows] &= c.feasible
            reason[rows] = np.where(c.reason != "", c.reason, reason[rows])
            dm[rows] = np.fmin(dm[rows], c.disk_margin)
            over[rows] = np.fmax(over[rows], c.overshoot_pct)
        return Check(feasible, dm, over, np.where(feasible, nominal.rise_time_s, np.nan),
                     reason, nominal.simulated_rise_s)

    def _check_plant(self, plant: Plant, kp, ki, simulate, t_max_s) -> Check:
        """:meth:`check` of one plant (the reference model's or a member's of the set)."""
        f = evaluate(plant, kp, ki, band_pct=self.band_pct, classical=False,
                     overshoot_stop_pct=self.overshoot_max_pct,
                     disk_margin_min=self.disk_margin_min, time_mask=simulate,
                     t_max_s=t_max_s, screen=True)
        dm_ok = f.stable & (f.disk_margin >= self.disk_margin_min)
        over = dm_ok & ~(f.overshoot_pct < self.overshoot_max_pct)
        os_ok = (dm_ok & ~over & np.isfinite(f.rise_time_s)
                 & np.isfinite(f.settling_time_s))
        undecided = (np.zeros_like(dm_ok) if simulate is None
                     else dm_ok & ~np.asarray(simulate, bool))
        # screened out (not certified, sampled disk margin below the limit): "disk margin"
        screened = ~f.certified & (f.disk_margin > 0)
        reason = np.where(~f.stable & ~screened, "unstable",
                          np.where(~dm_ok, "disk margin",
                                   np.where(os_ok | undecided, "",
                                            np.where(over, "overshoot", "slow"))))
        return Check(os_ok, f.disk_margin, f.overshoot_pct,
                     np.where(os_ok, f.rise_time_s, np.nan), reason, f.rise_time_s)

    def first_rise_s(self, gains: np.ndarray, kp, ki, t_max_s: float = T_MAX_S) -> np.ndarray:
        """10-90 % rise time of candidates' step responses, each simulated only until it
        first reaches 90 %, s; shape (M,), NaN where it has not by ``t_max_s``.

        Whatever the constraints say (a loop short of the disk margin or unstable is
        simulated as well): rise time falls as K_I grows along a column of fixed ``kp_n``, so
        it bounds the rise time of every pair below on that column, which a search uses to
        drop columns that cannot beat its best.
        """
        return step_info(self.plant(gains), kp, ki, band_pct=self.band_pct, t_max_s=t_max_s,
                         until_rise=True).rise_time_s
