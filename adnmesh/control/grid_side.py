"""The grid as the measurement agent runs it: the power flow of every sample, its report, the
grid guard and the tap changer (docs/method.md#grid-guard, docs/models.md#tap-changer).

:class:`GridSide` is what the measurement has when the config has a grid model. Each sample
(:meth:`GridSide.sample`) it solves the AC power flow with the DERs' infeeds, folds the result
into the period's report (:class:`GridReport`: extremes and where they were, the samples and
seconds outside the band), lets the guard (:class:`~adnmesh.control.grid_guard.GridGuard`)
look at every bus voltage and branch loading, and gives the tap changer
(:class:`~adnmesh.control.tap_changer.TapChangerControl`) the MV busbar's voltage; a tap step
changes the model's ratio from the next sample on.
"""

from __future__ import annotations

import math

from adnmesh.config import Config
from adnmesh.control.grid_guard import GridGuard, GuardValues

__all__ = ["GridReport", "GridSide", "tap_changer_of"]


class GridReport:
    """The extremes of the grid samples of one report period, where they were, and the
    samples outside the band."""

    def __init__(self, limits, period_s: float) -> None:
        self.limits = limits
        self.period_s = period_s
        self.reset()

    def reset(self) -> None:
        self.v_min, self.v_max, self.line, self.trafo = math.inf, 0.0, 0.0, 0.0
        self.at = {"v_min_at": "", "v_max_at": "", "line_max_at": "", "trafo_max_at": ""}
        self.samples = self.outside = self.not_converged = 0

    def add(self, sample) -> None:
        self.samples += 1
        if not sample.converged:
            self.not_converged += 1
            return
        lim, at = self.limits, self.at
        if sample.vm_min_pu < self.v_min:
            self.v_min, at["v_min_at"] = sample.vm_min_pu, getattr(sample, "vm_min_at", "")
        if sample.vm_max_pu > self.v_max:
            self.v_max, at["v_max_at"] = sample.vm_max_pu, getattr(sample, "vm_max_at", "")
        if sample.line_loading_max_pct > self.line:
            self.line = sample.line_loading_max_pct
            at["line_max_at"] = getattr(sample, "line_max_at", "")
        if sample.trafo_loading_max_pct > self.trafo:
            self.trafo = sample.trafo_loading_max_pct
            at["trafo_max_at"] = getattr(sample, "trafo_max_at", "")
        self.outside += (sample.vm_min_pu < lim.v_min_pu or sample.vm_max_pu > lim.v_max_pu
                         or max(sample.line_loading_max_pct, sample.trafo_loading_max_pct)
                         > lim.loading_max_pct)

    def body(self, q_ip_var: float) -> dict:
        body = {"v_min_pu": self.v_min if self.v_min < math.inf else 0.0,
                "v_max_pu": self.v_max, "line_loading_max_pct": self.line,
                "trafo_loading_max_pct": self.trafo, "q_ip_var": q_ip_var,
                "samples": self.samples, "outside_band": self.outside,
                "not_converged": self.not_converged,
                "outside_s": self.outside * self.period_s}
        body.update({k: v for k, v in self.at.items() if v})
        return body


class GridSide:
    """The measurement's grid (see the module docstring).

    Parameters
    ----------
    config : Config
    solver : GridSolver
        The config's power flow (:func:`adnmesh.control.operating_point.grid_solver`).
    """

    def __init__(self, config: Config, solver) -> None:
        model = config.grid_model
        self.solver = solver
        self.report = GridReport(model.limits, config.runtime.measurement_period_s)
        self.reactive = config.reactive is not None
        self.guard = GridGuard(model.guard, model.limits, config.der_ids(), self.reactive)
        self.sends_guard = "guard" in config.features()
        self.tap = None
        if model.tap_changer is not None:
            self.tap, self.tap_trafos, self._tap_bus = tap_changer_of(model.tap_changer,
                                                                      solver)
            settings, limits = model.tap_changer, model.limits
            self._tap_band = None if settings.regulates == "busbar" else (
                limits.v_min_pu + settings.extremes_margin_pu,
                limits.v_max_pu - settings.extremes_margin_pu)
        self._last_p: list[float] | None = None
        self._last_q: list[float] | None = None

    def sample(self, t_ns: int, p_w: list[float], q_var: list[float] | None,
               pressing: frozenset = frozenset()):
        """Solve the power flow of one sample; returns ``(sample, guard_body, events)``: the
        :class:`~adnmesh.grid.GridSample`, the guard's new state if it changed (else None),
        and the events (dicts) of the guard and the tap changer. ``pressing``: the ways in
        which every DER following the loops is held (:meth:`GridGuard.observe`)."""
        solver = self.solver
        sample = solver.solve(p_w, q_var)
        self.report.add(sample)
        if not sample.converged:
            return sample, None, []
        self._last_p, self._last_q = p_w, q_var
        events: list[dict] = []
        changed = False
        if not self._quiet(sample):
            values = GuardValues(solver.bus_vm_pu(), solver.line_loading_pct(),
                                 solver.trafo_loading_pct(), solver.bus_names,
                                 solver.line_names, solver.trafo_names)
            changed, events = self.guard.observe(t_ns, values, self._sensitivities, pressing)
        if self.tap is not None:
            events += self._tap_step(t_ns, sample)
        body = self.guard.state() if changed and self.sends_guard else None
        return sample, body, events

    def report_bodies(self, q_ip_var: float) -> tuple[dict, dict | None]:
        """The period's ``grid_state`` body (then reset) and, with the guard on, its state
        (so that a CPFC that missed a change, or a CPFC after a restarted measurement whose
        guard starts anew, learns it)."""
        body = self.report.body(q_ip_var)
        if self.tap is not None:
            body["tap_pos"] = self.tap.position
        self.report.reset()
        again = self.guard.state() if self.sends_guard else None
        return body, again

    def _quiet(self, sample) -> bool:
        """Nothing for the guard to do: no quantity engaged or beyond its limit, no hold, and
        every extreme of the sample inside its engaging level (four comparisons)."""
        guard = self.guard
        if guard.watched or guard.hold or guard.violation is not None:
            return False
        lv = guard.levels
        return (sample.vm_max_pu <= lv["v_high"][1] and sample.vm_min_pu >= lv["v_low"][1]
                and not sample.line_loading_max_pct > lv["line"][1]
                and not sample.trafo_loading_max_pct > lv["trafo"][1])

    def _sensitivities(self):
        from adnmesh.grid.sensitivity import limit_sensitivities
        q = self._last_q
        if q is None:
            q = [float(v) for v in self.solver.data.sgen_q_mvar[
                self.solver.data.sgen_index(self.solver.actuator_sgens)] * 1e6]
        return limit_sensitivities(self.solver, self._last_p, q)

    def _tap_step(self, t_ns: int, sample) -> list[dict]:
        tap = self.tap
        v_pu = abs(self.solver.voltages_pu[self._tap_bus])
        if self._tap_band is None:
            step, note = tap.observe(t_ns, v_pu)
        else:
            step, note = tap.observe_extremes(t_ns, sample.vm_min_pu, sample.vm_max_pu,
                                              *self._tap_band)
        if note:
            return [{"level": "WARNING", "kind": "tap_limit", "subject": "tap_changer",
                     "text": note}]
        if not step:
            return []
        for trafo in self.tap_trafos:             # parallel transformers step together
            self.solver.set_tap(trafo, tap.position)
        if self._tap_band is None:
            why = f"MV busbar at {v_pu:.4f} p.u., band {tap.v_set_pu:.4f} ± {tap.dead_band_pu:g}"
        else:
            why = (f"bus voltages {sample.vm_min_pu:.4f} to {sample.vm_max_pu:.4f} p.u., band "
                   f"{self._tap_band[0]:g} to {self._tap_band[1]:g}")
        return [{"level": "INFO", "kind": "tap", "subject": "tap_changer",
                 "text": f"tap changer: position {tap.position - step} -> {tap.position} "
                         f"({why} p.u.)"}]


def tap_changer_of(settings, solver):
    """``(TapChangerControl, trafos, busbar)`` for the config's tap changer: the regulator,
    the transformers it steps (the config's, else those at the slack: parallel transformers
    step together, or a circulating current flows between them) and their MV bus in the
    model."""
    from adnmesh.control.tap_changer import TapChangerControl
    from adnmesh.errors import GridError

    data, model = solver.data, solver.model
    trafos = model.get_trafos()
    slack_bus = model.get_generators()[data.slack_gen].bus_id
    if settings.trafo is not None:
        if settings.trafo >= len(trafos):
            raise GridError(f"grid_model.tap_changer.trafo: the net has {len(trafos)} "
                            f"transformer(s), no {settings.trafo}")
        index = settings.trafo
        stepped = list(range(len(trafos)))     # with the transformers parallel to it
    else:
        at_slack = [i for i, t in enumerate(trafos) if slack_bus in (t.bus1_id, t.bus2_id)]
        if not at_slack:
            raise GridError("grid_model.tap_changer: no transformer at the interconnection "
                            "point; name one with grid_model.tap_changer.trafo")
        index = at_slack[0]
        stepped = at_slack
    trafo = trafos[index]
    if trafo.bus2_id == slack_bus:
        mv_bus = trafo.bus1_id
    else:                               # the side away from the slack, else side 2: the LV
        mv_bus = trafo.bus2_id          # side (pandapower's lv_bus)
    tap_min, tap_max = data.tap_min[index], data.tap_max[index]
    if not (tap_min == tap_min and tap_max == tap_max) or tap_min >= tap_max:
        raise GridError(f"grid_model.tap_changer: transformer {index} has no tap changer in "
                        "the net (no tap range)")
    parallel = [i for i in stepped
                if {trafos[i].bus1_id, trafos[i].bus2_id} == {trafo.bus1_id, trafo.bus2_id}]
    stepped = [i for i in parallel                        # the same taps: they step together
               if data.tap_min[i] == data.tap_min[index]
               and data.tap_max[i] == data.tap_max[index]
               and data.tap_step_percent[i] == data.tap_step_percent[index]
               and str(data.tap_side[i]) == str(data.tap_side[index])
               and solver.tap_pos(i) == solver.tap_pos(index)]
    if len(stepped) != len(parallel):
        names = ", ".join(solver.trafo_names[i] for i in parallel)
        raise GridError(f"grid_model.tap_changer: the parallel transformers {names} differ in "
                        "their tap changers (range, step, side or position): one tap changer "
                        "cannot step them together")
    step_pu = abs(float(data.tap_step_percent[index])) / 100.0
    if settings.regulates == "busbar" and settings.dead_band_pu < step_pu / 2:
        raise GridError(f"grid_model.tap_changer.dead_band_pu: {settings.dead_band_pu:g} p.u. "
                        f"is less than half a tap step ({step_pu:g} p.u.): it would hunt")
    v_set = settings.v_set_pu
    if v_set is None:
        v_set = float(abs(solver.voltages_pu[mv_bus]))
    raises = 1 if str(data.tap_side[index]) == "lv" else -1
    control = TapChangerControl(v_set, settings.dead_band_pu, settings.delay_s,
                                int(solver.tap_pos(index)), int(tap_min), int(tap_max), raises)
    return control, stepped, mv_bus
