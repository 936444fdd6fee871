"""The agent fork server (``adnmesh/runtime/forkserver.py``): what a forked child is (its
session, environment, name, standard input and preloaded config), the exit statuses ``up``
sees, signals by PID, and the server's death (its children die with it; ``up`` starts programs
instead). The agents forked in every ``up`` run are covered by the runtime tests
(``tests/test_runtime_up.py`` compares a forked run's messages with a run of programs)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from adnmesh.runtime.children import AgentProcesses
from adnmesh.runtime.forkserver import ForkServer
from up_runs import alive, write_case

TESTS = Path(__file__).resolve().parent


@pytest.fixture
def server(tmp_path):
    """A started fork server on the runtime case; closed (and its children ended) after."""
    config, _ = write_case(tmp_path)
    forks = ForkServer()
    forks.start(str(config), _env())
    yield forks, config
    forks.close(timeout_s=10)


def _env(**more) -> dict[str, str]:
    return dict(os.environ, ADNMESH_PARENT_PID=str(os.getpid()),
                PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
                **more)


def _probe(*args: str) -> list[str]:
    return [sys.executable, "-m", "fork_probe", *args]


def test_a_forked_child_is_the_program_it_would_be(server, tmp_path) -> None:
    forks, config = server
    out = tmp_path / "told.json"
    child = forks.spawn(_probe("tell", str(out), str(config)), _env(ONLY_IN_CHILD="yes"),
                        "der SGen1")
    assert child is not None and child.wait(timeout=30) == 0
    told = json.loads(out.read_text())
    assert told["pid"] == child.pid and told["sid"] == child.pid       # a session of its own
    assert told["ppid"] == forks.proc.pid
    assert told["env"]["ONLY_IN_CHILD"] == "yes"                       # the environment given
    assert told["env"]["ADNMESH_PARENT_PID"] == str(forks.proc.pid)    # dies with the server
    assert told["argv"] == ["fork_probe", "tell", str(out), str(config)]
    assert told["comm"] == "der SGen1" and told["stdin"] == os.devnull
    assert told["config_preloaded"]               # the server's config, not loaded again

    os.utime(config, ns=(1, 1))                   # the file changed: the child loads it
    assert forks.spawn(_probe("tell", str(out), str(config)), _env(), "x").wait(30) == 0
    assert not json.loads(out.read_text())["config_preloaded"]


def test_a_forked_child_can_spawn_worker_processes(server, tmp_path) -> None:
    """The CPFC's retune runs in a spawned process (realtime runs): that works from a forked
    agent, whose ``__main__`` is the fork server's module."""
    forks, _ = server
    out = tmp_path / "pool.txt"
    assert forks.spawn(_probe("pool", str(out)), _env(), "cpfc").wait(timeout=90) == 0
    assert out.read_text() == "1024"


def test_exit_statuses_are_those_of_the_program(server) -> None:
    forks, _ = server
    assert forks.spawn(_probe("exit", "3"), _env(), "three").wait(timeout=30) == 3
    raised = forks.spawn(_probe("raise"), _env(), "raises")
    assert raised.wait(timeout=30) == 1
    waiting = forks.spawn(_probe("wait"), _env(), "waits")
    with pytest.raises(subprocess.TimeoutExpired):
        waiting.wait(timeout=0.05)
    assert waiting.poll() is None and alive(waiting.pid)
    waiting.kill()
    assert waiting.wait(timeout=30) == -signal.SIGKILL and not alive(waiting.pid)
    waiting.kill()                                # ended and reaped: no signal to anybody


def test_a_dead_server_takes_its_children_and_up_starts_programs(server, tmp_path) -> None:
    forks, _ = server
    waiting = forks.spawn(_probe("wait"), _env(), "waits")
    assert waiting is not None and alive(waiting.pid)
    forks.proc.kill()                             # by PID: the server is gone
    assert waiting.wait(timeout=30) == -signal.SIGKILL
    assert forks.spawn(_probe("exit", "0"), _env(), "x") is None and forks.failed

    children = AgentProcesses()                   # up's side: a program instead
    children.forkserver = forks
    children.spawn("der/SGen1", [sys.executable, "-c", "raise SystemExit(4)"])
    assert isinstance(children.procs["der/SGen1"], subprocess.Popen)
    children.wait_all(30)
    assert children.dead() == [("der/SGen1", 4)]


def test_a_server_that_does_not_answer_is_ended_with_its_children(server, monkeypatch) -> None:
    """``up``'s last step kills every agent by PID and waits for each to be reported ended: a
    fork server that does not answer (stopped here) is itself killed after a bound, and its
    children with it, so that ``up`` never hangs on it."""
    import adnmesh.runtime.children as children_module

    forks, _ = server
    monkeypatch.setattr(children_module, "KILL_WAIT_S", 0.5)
    children = AgentProcesses()
    children.forkserver = forks
    children.spawn("der/SGen1", _probe("wait"))
    child = children.procs["der/SGen1"]
    assert alive(child.pid)
    os.kill(forks.proc.pid, signal.SIGSTOP)
    assert children.kill_all() == ["der/SGen1"]
    assert child.returncode == -signal.SIGKILL
    assert forks.proc.wait(timeout=30) == -signal.SIGKILL    # the server, killed by PID


def test_the_server_refuses_a_request_it_cannot_read_and_goes_on(server) -> None:
    forks, _ = server
    assert forks._send("not json")            # nobody waits for its answer: read it here
    assert forks._await(lambda: bool(forks._answers), 30)
    assert forks._answers.pop(0).startswith("JSONDecodeError")
    assert forks.spawn(_probe("exit", "5"), _env(), "five").wait(timeout=30) == 5


def test_a_refused_fork_starts_as_a_program_and_is_said(tmp_path) -> None:
    """A fork the server cannot make (``fork()`` fails: memory, processes) is refused; ``up``
    says so in one line and starts that agent as a program; the server stays in use."""
    config, _ = write_case(tmp_path)
    said = []
    forks = ForkServer(say=said.append)
    forks.start(str(config), _env(), program="fork_probe")    # a server that refuses forks
    try:
        children = AgentProcesses()
        children.forkserver = forks
        children.spawn("der/SGen9", [sys.executable, "-c", "raise SystemExit(6)"])
        assert isinstance(children.procs["der/SGen9"], subprocess.Popen)
        children.wait_all(30)
        assert children.dead() == [("der/SGen9", 6)]
        assert said == ["warning: the fork server refused to fork der SGen9 (OSError: [Errno "
                        "11] Resource temporarily unavailable); it starts as a program"]
        assert forks.failed is None
    finally:
        forks.close(timeout_s=10)


def test_host_of_names_the_hosting_process_until_the_agent_leaves_it() -> None:
    children = AgentProcesses()
    children.forkserver = None
    children.spawn_hosting(["der/A", "der/B"], [sys.executable, "-c", "pass"])
    children.spawn("cpfc", [sys.executable, "-c", "pass"])
    assert [children.host_of(a) for a in ("der/A", "der/B", "cpfc")] == ["der/A", "der/A", None]
    children.leave("der/B")
    children.spawn("der/B", [sys.executable, "-c", "pass"])      # restarted alone
    assert [children.host_of(a) for a in ("der/A", "der/B")] == ["der/A", None]
    children.wait_all(30)
