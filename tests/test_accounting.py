"""Every agent accounted for at the end of a run (adnmesh.runtime.accounting): a goodbye, or a
fault that the overload of a realtime run explains, or a failure."""

from adnmesh.runtime.accounting import account_agents

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
