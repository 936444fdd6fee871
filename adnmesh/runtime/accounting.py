"""Every agent of a run accounted for at its end: a goodbye, or a fault with what is known.

An agent that did not say goodbye (or was lost during the run) left its counts unverified.
Why decides what it does to the run's exit code:

- its process **crashed** (ended on its own with a non-zero exit code or a signal before the
  shutdown): a failure, whatever the clock;
- a **realtime run the machine could not keep up with** (an overrun was seen: the run is
  NOT REAL TIME): its session dropped under the load (Zenoh's lease ran out while a process
  was starved) and it missed the stop, or it was out of sight of ``up`` for longer than the
  grace and stopped. That is the machine's lateness, said as such; it is not a failure of
  the run (``--strict`` stops such a run at its first overrun, exit code 3);
- otherwise (sim clock, or a realtime run that kept up): a failure.

:func:`account_agents` is pure: the launcher hands it what it knows.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["AgentAccount", "account_agents"]


@dataclass(frozen=True)
class AgentAccount:
    """How the agents of a run ended.

    Attributes
    ----------
    said_bye : tuple of str
        Agents whose goodbye arrived (their counts are verified, unless they were lost).
    overloaded : tuple of str
        Agents without a goodbye, or lost, because the machine could not keep up: faults,
        not failures.
    failed : tuple of str
        Agents without a goodbye, or lost, for another reason: the run failed.
    lines : tuple of str
        One line per agent in ``overloaded`` and ``failed``, with what was recorded of it.
    """

    said_bye: tuple[str, ...]
    overloaded: tuple[str, ...]
    failed: tuple[str, ...]
    lines: tuple[str, ...]


def account_agents(agents, byes, lost, crashed, *, overloaded: bool,
                   recorded: dict[str, int]) -> AgentAccount:
    """Sort the agents of a run (see the module docstring).

    Parameters
    ----------
    agents : iterable of str
        Every agent of the run.
    byes : collection of str
        Agents whose goodbye arrived.
    lost : collection of str
        Agents lost during the run (an unplanned end; an injected kill is not a loss).
    crashed : collection of str
        Agents whose process ended on its own with a non-zero exit code or a signal.
    overloaded : bool
        A realtime run with an overrun (not real time).
    recorded : dict
        Agent -> messages of it in the recording.
    """
    said, late, failed, lines = [], [], [], []
    for agent in sorted(agents):
        missing = agent not in byes
        if not missing and agent not in lost:
            said.append(agent)
            continue
        if not missing:
            said.append(agent)
        what = "no goodbye" if missing else "lost during the run"
        count = f"{recorded.get(agent, 0)} message(s) of it recorded, counts not verified"
        if overloaded and agent not in crashed:
            late.append(agent)
            lines.append(f"{agent}: {what}, because the machine could not keep up (its "
                         f"session dropped or it missed the stop under load); {count}")
        else:
            failed.append(agent)
            lines.append(f"{agent}: {what}; {count}")
    return AgentAccount(tuple(said), tuple(late), tuple(failed), tuple(lines))
