"""Every agent accounted for at the end of a run (adnmesh.runtime.accounting): a goodbye, or a
fault that the overload of a realtime run explains, or a failure; and the launcher's use of it
(on a faked launch state: no processes)."""

from pathlib import Path
from types import SimpleNamespace

from adnmesh.config import load_config
from adnmesh.runtime import launcher
from adnmesh.runtime.accounting import account_agents
from adnmesh.sim.topology import Topology

AGENTS = ["cpfc", "der/SGen1", "der/SGen2", "measurement"]
RECORDED = {"cpfc": 10, "der/SGen1": 7, "der/SGen2": 3, "measurement": 12}


def test_every_goodbye_accounts_for_every_agent():
    account = account_agents(AGENTS, set(AGENTS), set(), set(), overloaded=False,
                             recorded=RECORDED)
    assert account.said_bye == tuple(AGENTS)
    assert account.overloaded == account.failed == account.lines == ()


def test_an_overloaded_run_excuses_a_missing_goodbye_and_says_what_was_recorded():
    byes = set(AGENTS) - {"der/SGen2"}
    account = account_agents(AGENTS, byes, set(), set(), overloaded=True, recorded=RECORDED)
    assert account.overloaded == ("der/SGen2",) and account.failed == ()
    assert account.said_bye == ("cpfc", "der/SGen1", "measurement")
    assert len(account.lines) == 1
    assert account.lines[0].startswith("der/SGen2: no goodbye, because the machine could not "
                                       "keep up")
    assert "3 message(s) of it recorded, counts not verified" in account.lines[0]


def test_a_crash_fails_even_an_overloaded_run_and_a_kept_up_run_excuses_nothing():
    byes = set(AGENTS) - {"der/SGen1", "der/SGen2"}
    account = account_agents(AGENTS, byes, {"der/SGen1"}, {"der/SGen1"}, overloaded=True,
                             recorded=RECORDED)
    assert account.failed == ("der/SGen1",) and account.overloaded == ("der/SGen2",)
    kept_up = account_agents(AGENTS, byes, set(), set(), overloaded=False, recorded=RECORDED)
    assert kept_up.failed == ("der/SGen1", "der/SGen2") and kept_up.overloaded == ()


def test_an_agent_lost_under_load_that_said_goodbye_late_is_both_heard_and_excused():
    account = account_agents(AGENTS, set(AGENTS), {"measurement"}, set(), overloaded=True,
                             recorded=RECORDED)
    assert "measurement" in account.said_bye and account.overloaded == ("measurement",)
    assert account.lines[0].startswith("measurement: lost during the run, because")


# --- the launcher's use of it (no processes: the launch state it reads, faked) ------------------

CASE = Path(__file__).resolve().parents[1] / "configs" / "examples" / "runtime-step.yaml"


def fake_launch(*, clock="realtime", overruns=1, byes=(), dropped=(), lost=(), killed=(),
                recorded=None):
    topology = Topology.from_config(load_config(CASE))
    lines = []
    launch = SimpleNamespace(
        options=SimpleNamespace(clock=clock, log=lines.append), topology=topology,
        keys=topology.keys, roster=SimpleNamespace(byes={a: None for a in byes}),
        children=SimpleNamespace(procs={}), killed_at_shutdown=set(),
        injector=SimpleNamespace(lost=list(lost), killed=set(killed) | set(lost)),
        recorder=SimpleNamespace(counts=lambda: recorded or {}), dropped=set(dropped),
        result=SimpleNamespace(problems=[], published={}, recorded={}),
        overloaded=lambda: overruns > 0, lines=lines)
    return launch


def test_the_launcher_excuses_only_an_overloaded_realtime_run():
    agents = fake_launch().topology.agents
    late = fake_launch(byes=[a for a in agents if a != "cpfc"])
    assert launcher._overloaded_agents(late) == {"cpfc"}
    assert late.result.problems[0].startswith("cpfc: no goodbye, because the machine")
    assert late.lines == [f"{len(agents) - 1} of {len(agents)} agents said goodbye; 1 lost to "
                          "the overload (not real time)"]
    kept_up = fake_launch(overruns=0, byes=[a for a in agents if a != "cpfc"])
    assert launcher._overloaded_agents(kept_up) == set() and kept_up.result.problems == []
    sim = fake_launch(clock="sim", byes=[a for a in agents if a != "cpfc"])
    assert launcher._overloaded_agents(sim) == set()


def test_an_injected_kill_is_not_blamed_on_the_overload():
    agents = fake_launch().topology.agents
    launch = fake_launch(byes=[a for a in agents if a != "der/SGen1"], killed=["der/SGen1"])
    assert launcher._overloaded_agents(launch) == set()
    assert launch.lines == [f"{len(agents) - 1} of {len(agents) - 1} agents said goodbye; 0 "
                            "lost to the overload (not real time)"]


def test_messages_lost_on_a_dropped_session_are_a_fault_of_the_overload_only():
    launch = fake_launch(dropped=["der/SGen2"])
    state = launch.keys.root + "/der/SGen2/state"
    assert state in launcher._keys_of(launch, ["der/SGen2"])
    other = next(k for k in launcher._keys_of(launch, ["cpfc"]) if "bye" not in k)
    launch.result.published = {state: 10, other: 5}
    launch.result.recorded = {state: 7, other: 4}
    assert launcher._short_by_overload(launch, [other, state]) == [other]
    assert launch.result.problems == ["3 message(s) on 1 key(s) of 1 agent(s) whose session "
                                      "dropped under the overload were lost while it was down "
                                      "(not real time): der/SGen2"]
    kept_up = fake_launch(overruns=0, dropped=["der/SGen2"])
    kept_up.result.published, kept_up.result.recorded = {state: 10}, {state: 7}
    assert launcher._short_by_overload(kept_up, [state]) == [state]
