"""What ``adnmesh up`` prints after a run: the summary of a grid's run
(:func:`run_summary`, :mod:`adnmesh.results.summary`), on stdout (:func:`print_summary`, with
the way to a robust table where a step broke its certified overshoot) and as JSON
(:func:`write_summary_json`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rich.console import Console

from adnmesh.config import Config

__all__ = ["print_and_write_summary", "print_summary", "run_summary", "write_summary_json"]


def _robust_hint(args, config: Config, checks, out) -> str | None:
    """Where a step broke the overshoot its entry was certified for and the config has no
    uncertainty set: the commands that certify a table for plants like the ones just run
    (docs/tuning.md#robust-tables); else None."""
    if config.constraints.robust is not None or out is None:
        return None
    over = [c for c in checks if "overshoot" in c.over]
    if not over:
        return None
    robust = Path(args.config).with_name(Path(args.config).stem + "-robust.yaml")
    during = ("" if config.runtime.model_watch == "retune" else
              " With runtime.model_watch: retune the CPFC tunes such a subset again during the "
              "run (docs/method.md#model-watch).")
    return (f"{len(over)} step(s) broke the overshoot their entry was certified for: the DERs "
            f"do not behave as the reference model. A table certified for plants like these: "
            f"adnmesh identify {args.config} {out} --steps auto --robust-out {robust}; adnmesh "
            f"tune {robust} --robust; adnmesh up {robust} (docs/tuning.md#robust-tables).{during}")


def print_and_write_summary(args: argparse.Namespace, config: Config, run_id: str, result,
                   recording: Path | None = None) -> str | None:
    """The summary on stdout (and as JSON with ``--summary-json``), with the way to a robust
    table where a step broke its certified overshoot (``recording``: the run's, if complete);
    return the line that says the JSON could not be written (a full disk, say), or None."""
    summary = run_summary(args, config, run_id, result)
    print_summary(args, config, summary, recording)
    return write_summary_json(args.summary_json, summary.to_json())


def run_summary(args: argparse.Namespace, config: Config, run_id: str, result):
    """The :class:`~adnmesh.results.summary.Summary` of the run of ``config`` (``result``: its
    :class:`~adnmesh.runtime.launcher.UpResult`)."""
    from adnmesh.results.realtime_report import realtime_figures
    from adnmesh.results.summary import summarize

    byes = result.byes.values()
    extra = {
        "run_id": run_id,
        "clock": args.clock,
        "ended": result.reason,
        "agents": len(byes),
        "messages_recorded": sum(result.recorded.values()),
        "messages_received_by_agents": sum(int(b.stats.get("received", 0)) for b in byes),
        "rejected_by_agents": sum(sum(r.values()) for b in byes for r in b.rejected.values()),
        "rejected_by_recorder": sum(sum(r.values()) for r in result.rejected.values()),
        "lost_on_links": sum(b.lost for b in byes),
        "startup_s": round(result.startup_s, 3),
        "profile": "secure" if args.secure or args.certs else "open",
        "links_accepted": sum(result.sessions.opened.values()),
        "unexpected_sessions": len(result.sessions.unexpected),
    }
    if result.recording_failed:
        extra["recording_failed"] = result.recording_failed
        extra["messages_on_disk"] = result.on_disk[0]
    if args.clock == "sim":
        extra["clock_grants"] = result.grants
        extra["grants_per_s"] = round(result.grants / result.wall_time_s, 1) \
            if result.wall_time_s else None
    realtime = None
    if args.clock == "realtime":
        realtime = realtime_figures(byes, result.series.alarms, result.series.faults.values(),
                                    config, speed=args.speed or 1.0,
                                    tolerance_ns=result.tolerance_ns)
    return summarize(result.series, end_ns=result.reached_ns,
                     band_pct=config.constraints.settling_band_pct,
                     wall_time_s=result.wall_time_s, extra=extra, realtime=realtime,
                     planned_steps=[(s.t_s, s.delta_w) for s in config.scenario.p_ref_steps],
                     sample_s=config.runtime.pi_period_s)


def print_summary(args: argparse.Namespace, config: Config, summary,
                  recording: Path | None = None) -> None:
    """``summary`` on stdout, with the way to a robust table where a step broke its certified
    overshoot (``recording``: the run's, if complete)."""
    from adnmesh.results.summary import format_summary

    # piped into a file or another program: wide enough that no table cell is cut
    console = Console(highlight=False, markup=False, soft_wrap=True,
                      width=None if sys.stdout.isatty() else 200)
    for item in format_summary(summary):
        console.print(item)
    hint = _robust_hint(args, config, summary.design_checks, recording)
    if hint:
        console.print(hint)
    sys.stdout.flush()


def write_summary_json(path: str | None, document: dict) -> str | None:
    """Write ``document`` to ``path`` (``--summary-json``; None: nothing); return the line
    that says it could not be written (a full disk, say), or None."""
    if not path:
        return None
    from adnmesh.files import write_atomic

    try:         # atomic: a full disk leaves no half file (and an earlier one as it was)
        write_atomic(path, json.dumps(document, indent=1) + "\n")
    except OSError as exc:
        return (f"--summary-json {path}: not written ({exc.strerror or exc}); "
                "the summary above is the whole of it")
    return None
