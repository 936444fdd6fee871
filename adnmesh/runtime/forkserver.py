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
fork server with ``up``. The fork server has no thread of its own: it imports no Zenoh runtime
before it forks (a session is opened only in the child).

The protocol, a line each way (``up`` writes requests on the server's stdin and reads replies
from a pipe; the server's stdout and stderr are ``up``'s, and so its agents'):

- server: ``ready`` once loaded (or ``failed WHY`` and it exits);
- ``up``: ``{"argv": [...], "env": {...}, "name": "..."}`` (JSON; ``argv`` as for ``python``:
  ``[exe, "-m", "adnmesh.agents.<kind>", args...]``) -- server: ``started PID``;
- ``up``: ``signal PID SIGNUM`` -- sent only while the server has not reaped PID (the server is
  its parent, so the PID cannot have been reused);
- server: ``exited PID STATUS`` (``waitpid``'s status) when a child ends;
- ``up`` closes stdin: the server exits once its last child has ended.

``up``'s side is :class:`ForkServer`, whose :class:`ForkedProcess` stands for a
:class:`subprocess.Popen` where ``up`` tracks its agents (PID, ``poll``, ``wait``, ``kill``).
A fork server that cannot start or dies makes ``up`` start the remaining agents as programs.
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

__all__ = ["ForkServer", "ForkedProcess", "PRELOADED_MODULES", "READY_TIMEOUT_S", "SERVER_NAME"]

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

READY_TIMEOUT_S = 60.0
"""How long ``up`` waits for the fork server's ``ready`` (or a ``started``) before it starts
the agents as programs instead, wall s: its imports take about 0.5 s on a quiet machine."""

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
        while children:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                children.clear()
                break
            if pid == 0:
                break
            children.discard(pid)
            _write(reply_fd, f"exited {pid} {status}")
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
            request = json.loads(line)
            pid = os.fork()
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
    prepares), :meth:`spawn` agents, :meth:`close` at the end."""

    def __init__(self) -> None:
        self.changed = threading.Condition()
        self.proc: subprocess.Popen | None = None
        self.failed: str | None = None        # why it cannot be used (then: programs)
        self._ready = False
        self._started: list[int] = []
        self._children: dict[int, ForkedProcess] = {}
        self._early: dict[int, int] = {}      # exit codes of children not yet handed out
        self._lock = threading.Lock()          # one request and its reply at a time
        self._reader: threading.Thread | None = None
        self.started_at = time.monotonic()     # when start() was called, monotonic s

    def start(self, config_path: str, env: dict[str, str]) -> None:
        """Start the server on ``config_path`` with ``env`` (``up``'s PID in it)."""
        self.started_at = time.monotonic()
        reply_r, reply_w = os.pipe()
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", __name__, config_path, str(reply_w)], env=env,
                stdin=subprocess.PIPE, pass_fds=(reply_w,), start_new_session=True)
        except OSError as exc:
            os.close(reply_r)
            self.failed = f"cannot start it: {exc}"
            return
        finally:
            os.close(reply_w)
        self._reader = threading.Thread(target=self._read, args=(reply_r,),
                                        name="adnmesh-up-forkserver", daemon=True)
        self._reader.start()

    def _read(self, fd: int) -> None:
        with os.fdopen(fd, "rb") as replies:
            for raw in replies:
                word, _, rest = raw.decode().strip().partition(" ")
                with self.changed:
                    if word == "ready":
                        self._ready = True
                    elif word == "started":
                        self._started.append(int(rest))
                    elif word == "exited":
                        pid, status = (int(x) for x in rest.split())
                        code = os.waitstatus_to_exitcode(status)
                        child = self._children.pop(pid, None)
                        if child is None:
                            self._early[pid] = code
                        else:
                            child.returncode = code
                    elif word == "failed":
                        self.failed = rest
                    self.changed.notify_all()
        with self.changed:       # the server is gone, and its children with it
            self.failed = self.failed or "it ended"
            for child in self._children.values():
                child.returncode = -signal.SIGKILL
            self._children.clear()
            self.changed.notify_all()

    def _await(self, test, timeout_s: float) -> bool:
        with self.changed:
            return self.changed.wait_for(lambda: test() or self.failed is not None, timeout_s) \
                and test()

    def spawn(self, argv: list[str], env: dict[str, str], name: str) -> ForkedProcess | None:
        """Fork the agent program ``argv`` (``[exe, "-m", module, args...]``) with ``env``;
        None if the server cannot (see :attr:`failed`): start it as a program then."""
        if self.proc is None or self.failed is not None:
            return None
        with self._lock:
            if not self._await(lambda: self._ready, READY_TIMEOUT_S):
                self.failed = self.failed or f"not ready after {READY_TIMEOUT_S:g} s"
                return None
            with self.changed:
                self._started.clear()
            try:
                self.proc.stdin.write(json.dumps({"argv": argv, "env": env, "name": name})
                                      .encode() + b"\n")
                self.proc.stdin.flush()
            except OSError as exc:
                self.failed = f"its pipe broke: {exc}"
                return None
            if not self._await(lambda: bool(self._started), READY_TIMEOUT_S):
                self.failed = self.failed or "no answer to a fork"
                return None
            with self.changed:
                child = ForkedProcess(self, self._started.pop(), argv)
                child.returncode = self._early.pop(child.pid, None)
                if child.returncode is None:
                    if self.failed is not None:      # the server is gone: so is its child
                        child.returncode = -signal.SIGKILL
                    else:
                        self._children[child.pid] = child
            return child

    def signal(self, pid: int, signum: int) -> None:
        """Have the server send ``signum`` to its child ``pid`` (if it has not reaped it)."""
        with self._lock:
            if self.proc is None or self.proc.stdin.closed:
                return
            try:
                self.proc.stdin.write(f"signal {pid} {int(signum)}\n".encode())
                self.proc.stdin.flush()
            except OSError:
                pass

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
        with self._lock:
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
