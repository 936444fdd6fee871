"""The agent fork server: one interpreter that has imported the agent programs and loaded the
config once, from which ``adnmesh up`` forks every agent process (``runtime.agent_start:
fork``, the default).

Started as its own program, an agent pays its interpreter's start, the import of its modules
(numpy, pydantic, Zenoh's binding, adnmesh: about 0.5 s of CPU) and the config's validation,
and 14 agents pay it 14 times on two cores. The fork server pays it once, while ``up`` prepares
its router, and then forks each agent in milliseconds; the agents share the pages of what it
loaded (copy-on-write, the objects frozen out of the garbage collector's reach so that it does
not touch them), so an agent's own memory is what it makes, not what it imports.

A forked agent is the program ``python -m adnmesh.agents.<kind>`` would run, with the same
arguments and environment: the child begins a session of its own, takes the environment ``up``
gives it, drops the fork server's file descriptors and signal handlers, names itself
(``/proc/PID/comm``: ``der SGen1``, ``cpfc``...) and calls the kind's ``main``; its exit status
is what ``python -m`` would give. It dies with the fork server (``PR_SET_PDEATHSIG``), and the
fork server with ``up``. The fork server starts no thread of its own and no Zenoh runtime (a
session is opened only in the child); numpy's OpenBLAS pool, which OpenBLAS makes safe across
a fork, is the one other thread it has.

The protocol, a line each way (``up`` writes requests on the server's stdin and reads replies
from a pipe; the server's stdout and stderr are ``up``'s, and so its agents'):

- server: ``ready`` once loaded (or ``failed WHY`` and it exits);
- ``up``: ``{"argv": [...], "env": {...}, "name": "..."}`` (JSON; ``argv`` as for ``python``:
  ``[exe, "-m", "adnmesh.agents.<kind>", args...]``) -- server: ``started PID``, or
  ``refused WHY`` (a fork that failed: ``up`` starts that agent as a program);
- ``up``: ``signal PID SIGNUM`` -- sent only while the server has not reaped PID (the server is
  its parent, so the PID cannot have been reused);
- server: ``exited PID STATUS`` (``waitpid``'s status) when a child ends;
- ``up`` closes stdin: the server exits once its last child has ended.

``up``'s side is :class:`ForkServer`, whose :class:`ForkedProcess` stands for a
:class:`subprocess.Popen` where ``up`` tracks its agents (PID, ``poll``, ``wait``, ``kill``).
A fork server that cannot start, is not ready within :data:`READY_TIMEOUT_S`, does not answer
a fork within :data:`FORK_TIMEOUT_S` or dies makes ``up`` start the remaining agents as
programs, and say so in one line; a late answer to a fork ``up`` gave up on is killed, so that
no agent runs twice.
"""

from __future__ import annotations

import ctypes
import gc
import importlib
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time

from adnmesh.runtime.children import PARENT_ENV

__all__ = ["FORK_TIMEOUT_S", "ForkServer", "ForkedProcess", "PRELOADED_MODULES", "READY_TIMEOUT_S",
           "SERVER_NAME"]

PRELOADED_MODULES = (
    "adnmesh.agents.der", "adnmesh.agents.cpfc", "adnmesh.agents.measurement",
    "adnmesh.agents.availability",
    # imported by the agents only once they run:
    "adnmesh.runtime.bus", "adnmesh.errors", "adnmesh.config", "adnmesh.control.registry",
)
"""What the fork server imports before it forks: every agent program and what they import
only once they run."""

GRID_MODULES = (
    "adnmesh.grid.solver", "adnmesh.grid.simbench_net", "adnmesh.grid.cache",
    "adnmesh.control.grid_side", "adnmesh.control.grid_guard",
    "adnmesh.control.measurement_point", "adnmesh.analysis.pq_region",
)
"""What the measurement and the CPFC import as they are built with a grid model (the AC power
flow: pandas, lightsim2grid; the P-Q region: scipy), imported once by the fork server too
when the config has one, so that the two share it instead of importing it each."""

SERVER_NAME = "adnmesh forks"
"""The fork server's process name (``/proc/PID/comm``); its agents take theirs (``der SGen1``,
``cpfc``...): forked, they keep its command line."""

READY_TIMEOUT_S = 15.0
"""How long ``up`` waits for the fork server's ``ready`` before it starts the agents as
programs instead, wall s: its imports take 0.5-1.5 s here; ``up``'s start-up timeout (60 s
and more) then still lies ahead of the programs."""

FORK_TIMEOUT_S = 15.0
"""How long ``up`` waits for the answer to one fork, wall s (a fork takes milliseconds)."""

_PR_SET_NAME = 15
_PR_SET_PDEATHSIG = 1


# -- the server ---------------------------------------------------------------------------------


def _prctl(option: int, value) -> None:
    """Linux ``prctl`` (nothing elsewhere)."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(option, value, 0, 0, 0)
        except (OSError, AttributeError):
            pass


def _write(fd: int, line: str) -> None:
    os.write(fd, (line + "\n").encode())


def _preload(config_path: str) -> None:
    """Import what the agents import; load (and validate) the config once."""
    for module in PRELOADED_MODULES:
        importlib.import_module(module)
    from adnmesh.runtime.process import preload_config
    config = preload_config(config_path)
    if config is not None and config.grid_model is not None:
        for module in GRID_MODULES:
            importlib.import_module(module)


def _become_agent(request: dict, closing: tuple[int, ...]) -> tuple:
    """In the forked child: leave the server's session, descriptors, signals and environment
    for the agent's own; return the agent's ``main`` and arguments."""
    os.setsid()
    signal.set_wakeup_fd(-1)
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)   # as in any Python program
    for fd in closing:
        os.close(fd)
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    server = os.getppid()
    os.environ.clear()
    os.environ.update(request["env"])
    # the agent dies with the process it was forked from, which dies with up
    os.environ[PARENT_ENV] = str(server)
    _prctl(_PR_SET_NAME, request.get("name", "agent")[:15].encode())
    _, _, module, *args = request["argv"]
    sys.argv = [module, *args]
    return importlib.import_module(module).main, args


def _reap(children: set[int], reply_fd: int) -> None:
    """Reap every child that has ended and say its status (``exited PID STATUS``)."""
    while children:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            children.clear()
            return
        if pid == 0:
            return
        children.discard(pid)
        _write(reply_fd, f"exited {pid} {status}")


def serve(config_path: str, reply_fd: int) -> int:
    """The fork server's loop (see the module docstring); in a forked child, the agent's
    ``main`` runs and its result is returned instead."""
    from adnmesh.runtime.process import die_with_parent
    die_with_parent()
    _prctl(_PR_SET_NAME, SERVER_NAME.encode())
    try:
        _preload(config_path)
    except Exception as exc:   # noqa: BLE001 -- said to up, which starts programs instead
        _write(reply_fd, f"failed {type(exc).__name__}: {exc}".replace("\n", " ")[:500])
        return 1
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGINT, signal.SIG_IGN)     # up ends the run and closes stdin
    gc.collect()
    gc.freeze()            # what the children share stays untouched by their collector
    sys.stdout.flush()
    sys.stderr.flush()
    children: set[int] = set()
    buffered, closing = b"", False
    _write(reply_fd, "ready")
    while not (closing and not children):
        readable, _, _ = select.select([0, wake_r] if not closing else [wake_r], [], [], 1.0)
        if wake_r in readable:
            os.read(wake_r, 4096)
        _reap(children, reply_fd)
        if 0 not in readable:
            continue
        chunk = os.read(0, 65536)
        if not chunk:
            closing = True
            continue
        buffered += chunk
        *lines, buffered = buffered.split(b"\n")
        for line in lines:
            words = line.split()
            if words[:1] == [b"signal"]:
                pid, signum = int(words[1]), int(words[2])
                if pid in children:
                    os.kill(pid, signum)
                continue
            try:
                request = json.loads(line)
                pid = os.fork()
            except (ValueError, OSError) as exc:    # up starts that agent as a program
                _write(reply_fd, f"refused {type(exc).__name__}: {exc}".replace("\n", " ")[:500])
                continue
            if pid == 0:
                main, args = _become_agent(request, (reply_fd, wake_r, wake_w))
                return main(args)
            children.add(pid)
            _write(reply_fd, f"started {pid}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m adnmesh.runtime.forkserver CONFIG REPLY_FD`` (started by ``adnmesh up``)."""
    config_path, reply_fd = argv if argv is not None else sys.argv[1:]
    return serve(config_path, int(reply_fd))


# -- up's side ------------------------------------------------------------------------------------


class ForkedProcess:
    """An agent process forked by the fork server, tracked as :class:`subprocess.Popen` is
    (``pid``, ``returncode``, ``poll``, ``wait``, ``send_signal``, ``kill``, ``terminate``)."""

    def __init__(self, server: ForkServer, pid: int, args: list[str]) -> None:
        self.server = server
        self.pid = pid
        self.args = args
        self.returncode: int | None = None

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        with self.server.changed:
            while self.returncode is None:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    raise subprocess.TimeoutExpired(self.args, timeout)
                self.server.changed.wait(left)
        return self.returncode

    def send_signal(self, signum: int) -> None:
        """Signal the process by PID, through its parent while it has not reaped it."""
        if self.returncode is None:
            self.server.signal(self.pid, signum)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)


class ForkServer:
    """``up``'s handle on its fork server: :meth:`start` it early (it loads while ``up``
    prepares), :meth:`spawn` agents, :meth:`close` at the end. ``say`` takes the one line
    said when the server cannot be used (or refuses a fork): the agents then start as
    programs."""

    def __init__(self, say=lambda line: None) -> None:
        self.changed = threading.Condition()
        self.proc: subprocess.Popen | None = None
        self.failed: str | None = None        # why it cannot be used (then: programs)
        self._say = say
        self._ready = False
        self._answers: list[int | str] = []   # PID started, or why a fork was refused
        self._abandoned = 0                   # forks given up on: their late PIDs are killed
        self._children: dict[int, ForkedProcess] = {}
        self._early: dict[int, int] = {}      # exit codes of children not yet handed out
        self._lock = threading.Lock()          # one request and its answer at a time
        self._stdin = threading.Lock()         # one line at a time on the server's stdin
        self._reader: threading.Thread | None = None
        self._closing = False                  # close() was called: its end is no failure
        self.started_at = time.monotonic()     # when start() was called, monotonic s

    def start(self, config_path: str, env: dict[str, str], program: str = __name__) -> None:
        """Start the server on ``config_path`` with ``env`` (``up``'s PID in it); ``program``:
        the module run as the server (``python -m PROGRAM CONFIG REPLY_FD``), this one."""
        self.started_at = time.monotonic()
        reply_r, reply_w = os.pipe()
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", program, config_path, str(reply_w)], env=env,
                stdin=subprocess.PIPE, pass_fds=(reply_w,), start_new_session=True)
        except OSError as exc:
            os.close(reply_r)
            self._fail(f"cannot start it: {exc}")
            return
        finally:
            os.close(reply_w)
        self._reader = threading.Thread(target=self._read, args=(reply_r,),
                                        name="adnmesh-up-forkserver", daemon=True)
        self._reader.start()

    def _fail(self, why: str) -> None:
        """The server is not to be used any more: say why, once (not when it ends because
        :meth:`close` told it to)."""
        with self.changed:
            first = self.failed is None and not self._closing
            self.failed = self.failed or why
            self.changed.notify_all()
        if first:
            self._say(f"warning: the agents' fork server failed ({why}); agents start as "
                      "programs")

    def _read(self, fd: int) -> None:
        try:
            with os.fdopen(fd, "rb") as replies:
                for raw in replies:
                    self._take_reply(raw.decode(errors="replace").strip())
        finally:                 # the server is gone, and its children with it
            with self.changed:
                for child in self._children.values():
                    child.returncode = -signal.SIGKILL
                self._children.clear()
            self._fail("it ended")

    def _take_reply(self, line: str) -> None:
        word, _, rest = line.partition(" ")
        if word == "failed":
            self._fail(rest)
            return
        late = None
        with self.changed:
            if word == "ready":
                self._ready = True
            elif word in ("started", "refused"):
                answer = int(rest) if word == "started" else rest
                if self._abandoned:       # up gave up on this fork and started a program
                    self._abandoned -= 1
                    late = answer if word == "started" else None
                else:
                    self._answers.append(answer)
            elif word == "exited":
                pid, status = (int(x) for x in rest.split())
                code = os.waitstatus_to_exitcode(status)
                child = self._children.pop(pid, None)
                if child is None:
                    self._early[pid] = code
                else:
                    child.returncode = code
            self.changed.notify_all()
        if late is not None:
            self._send(f"signal {late} {int(signal.SIGKILL)}")

    def _await(self, test, timeout_s: float) -> bool:
        with self.changed:
            return self.changed.wait_for(lambda: test() or self.failed is not None, timeout_s) \
                and test()

    def _send(self, line: str) -> bool:
        """Write one line to the server's stdin; False if it cannot take it."""
        with self._stdin:
            if self.proc is None or self.proc.stdin.closed:
                return False
            try:
                self.proc.stdin.write(line.encode() + b"\n")
                self.proc.stdin.flush()
            except (OSError, ValueError):
                return False
        return True

    def spawn(self, argv: list[str], env: dict[str, str], name: str) -> ForkedProcess | None:
        """Fork the agent program ``argv`` (``[exe, "-m", module, args...]``) with ``env``;
        None if the server cannot (see :attr:`failed`) or refused this fork: start it as a
        program then."""
        if self.proc is None or self.failed is not None:
            return None
        with self._lock:
            if not self._await(lambda: self._ready, READY_TIMEOUT_S):
                self._fail(f"not ready after {READY_TIMEOUT_S:g} s")
                return None
            if not self._send(json.dumps({"argv": argv, "env": env, "name": name})):
                self._fail("its stdin is closed")
                return None
            if not self._await(lambda: bool(self._answers), FORK_TIMEOUT_S):
                with self.changed:
                    if not self._answers:      # a late answer is killed (no agent twice)
                        self._abandoned += 1
                self._fail(f"no answer to a fork within {FORK_TIMEOUT_S:g} s")
                if not self._answers:
                    return None
            with self.changed:
                answer = self._answers.pop(0)
                if isinstance(answer, str):
                    refused = answer
                else:
                    refused = None
                    child = ForkedProcess(self, answer, argv)
                    child.returncode = self._early.pop(child.pid, None)
                    if child.returncode is None:
                        if self._reader_done():    # the server is gone: so is its child
                            child.returncode = -signal.SIGKILL
                        else:
                            self._children[child.pid] = child
            if refused is not None:
                self._say(f"warning: the fork server refused to fork {name} ({refused}); it "
                          "starts as a program")
                return None
            return child

    def _reader_done(self) -> bool:
        return self._reader is None or not self._reader.is_alive()

    def signal(self, pid: int, signum: int) -> None:
        """Have the server send ``signum`` to its child ``pid`` (if it has not reaped it)."""
        self._send(f"signal {pid} {int(signum)}")

    def abort(self) -> None:
        """SIGKILL the server by PID: its children die with it (``PR_SET_PDEATHSIG``), and are
        reported ended with -SIGKILL."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()

    def close(self, timeout_s: float = 10.0) -> None:
        """Tell the server to exit once its children have ended; wait that long, then kill it
        (and so, by ``PR_SET_PDEATHSIG``, what is left of them)."""
        if self.proc is None:
            return
        self._closing = True
        with self._stdin:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        if self._reader is not None:
            self._reader.join(timeout_s)


if __name__ == "__main__":
    sys.exit(main())
