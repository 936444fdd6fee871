#!/usr/bin/env python3
"""Hostile probe of an adnmesh build (issue 39, deliverable 5): the next probe is one command.

Runs classes of hostile cases against a build of ``adnmesh`` and prints, per class, how many
ran, passed and failed, and a one-line reason for each failure. A case passes when the build
gives a clean one-line error with the documented exit code, or survives as the docs promise
(docs/runtime.md, docs/faults.md, docs/deployment.md). The probe always exits 0: it measures,
it does not gate.

    python benchmarks/probe.py                         # the adnmesh of this interpreter
    python benchmarks/probe.py --quick                 # the issue's own cases (~3 min)
    python benchmarks/probe.py --tree /tmp/base/tree   # another checkout (PYTHONPATH=it, its configs)
    python benchmarks/probe.py --adnmesh "adnmesh" --classes cli,table --json probe.json

Classes: ``cli`` (bad command lines of every subcommand), ``config`` (configs that pass
validation but crash, stall or are refused late; hostile YAML), ``table`` (gain tables that
pass the loader but crash or stall), ``bus`` (junk and forged messages against a running
``up``, a stolen DER key), ``process`` (SIGKILL of agents by PID mid-run), ``resources`` (a
full disk, ``up``'s memory over a long run).

Each case is one declarative entry (see ``case(...)`` below): the adnmesh arguments, the files
to create in the case's own folder, the exit codes it may end with, a timeout, and optionally
a check of what it wrote (the summary JSON, say). Adding a case is one line. Cases that need a
running ``up`` or a timed kill have a small runner function instead.

Ground rules: every subprocess has a timeout and is killed by PID (with every descendant it
started, found in /proc) when it runs over, grows beyond a memory limit or starts more
processes than the case allows; at most one ``adnmesh up`` runs at a time; everything is
written below one temporary folder that is removed at the end (mounts made for the read-only
and disk-full cases are unmounted first).
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import math
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import yaml

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
CLASSES = ("cli", "config", "table", "bus", "process", "resources")
NAN, INF = float("nan"), float("inf")
SOAK_S = 3600                     # the memory case's scenario (issue 39: a 3,600 s run)


# ---------------------------------------------------------------------------------------------
# running a process: timeout, memory and process-count limits, everything ended by PID

def _stat(pid: int) -> list[str] | None:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text.rsplit(")", 1)[1].split()


def _alive(pid: int, start: str | None = None) -> bool:
    """``pid`` exists, is no zombie (and started at ``start``, so a reused PID is not it)."""
    fields = _stat(pid)
    return bool(fields) and fields[0] != "Z" and (start is None or fields[19] == start)


def _children(pid: int) -> set[int]:
    found = set()
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return found
    for tid in tasks:
        try:
            found |= {int(c) for c in Path(f"/proc/{pid}/task/{tid}/children").read_text().split()}
        except OSError:
            continue
    return found


def descendants(pid: int) -> dict[int, str]:
    """Every living descendant of ``pid`` with its start time (from /proc)."""
    found, todo = {}, [pid]
    while todo:
        for child in _children(todo.pop()):
            fields = _stat(child)
            if child not in found and fields and fields[0] != "Z":
                found[child] = fields[19]
                todo.append(child)
    return found


def rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def cmdline(pid: int) -> list[str]:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return []


@dataclass
class Result:
    rc: int | None
    out: str
    err: str
    elapsed: float
    killed: str = ""          # why the probe killed it ("" if it ended by itself)
    stopped: str = ""         # the case's stop_when line: the probe ended it on purpose
    peak_rss_mb: float = 0.0
    leftover: list = field(default_factory=list)   # descendants alive after it exited
    rss: list = field(default_factory=list)        # (s since start, MB) of the process itself
    notes: dict = field(default_factory=dict)      # what hooks found


class Proc:
    """One process of the build, watched by a thread: killed (with its descendants, by PID)
    beyond ``timeout`` s, beyond ``mem_mb`` MB in any one process, or beyond ``max_children``
    descendants; ``stop_when``: a stderr pattern at which the probe ends it (SIGKILL) as done."""

    def __init__(self, argv, cwd, env, timeout, mem_mb=2500, max_children=40, stop_when=None,
                 sample_rss=False, log_to: Path | None = None):
        self.log_to = log_to         # write <log_to>.stdout/.stderr at the end
        self.argv, self.cwd, self.env, self.timeout = argv, cwd, env, timeout
        self.mem_mb, self.max_children, self.stop_when = mem_mb, max_children, stop_when
        self.sample_rss = sample_rss
        self.err_lines: list[str] = []
        self.out_chunks: list[str] = []
        self.killed = self.stopped = ""
        self.peak = 0.0
        self.rss: list = []
        self.seen: dict[int, str] = {}
        self.notes: dict = {}
        self._line = threading.Condition()
        self._done = threading.Event()

    def start(self) -> Proc:
        self.t0 = time.monotonic()
        self.proc = subprocess.Popen(self.argv, cwd=self.cwd, env=self.env,
                                     stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, start_new_session=True)
        self._readers = [threading.Thread(target=self._read_out, daemon=True),
                         threading.Thread(target=self._read_err, daemon=True)]
        for t in self._readers:
            t.start()
        threading.Thread(target=self._watch, daemon=True).start()
        return self

    def _read_out(self) -> None:
        size = 0
        while chunk := self.proc.stdout.read1(1 << 16):
            if size < 1 << 20:
                self.out_chunks.append(chunk.decode(errors="replace"))
            size += len(chunk)

    def _read_err(self) -> None:
        for raw in iter(self.proc.stderr.readline, b""):
            line = raw.decode(errors="replace").rstrip("\n")
            with self._line:
                if len(self.err_lines) < 5000:
                    self.err_lines.append(line[:2000])
                self._line.notify_all()
            if self.stop_when and not self.stopped and re.search(self.stop_when, line):
                self.stopped = line
                self.kill("")
        with self._line:
            self._line.notify_all()

    def _watch(self) -> None:
        last_sample = -1.0
        while self.proc.poll() is None:
            now = time.monotonic() - self.t0
            tree = descendants(self.proc.pid)
            self.seen.update(tree)
            own = rss_mb(self.proc.pid)
            biggest = max([own, *(rss_mb(p) for p in tree)])
            self.peak = max(self.peak, biggest)
            if self.sample_rss and now - last_sample >= 0.5:
                self.rss.append((round(now, 2), round(own, 1)))
                last_sample = now
            if now > self.timeout:
                self.kill(f"no answer within {self.timeout:g} s (killed)")
            elif biggest > self.mem_mb:
                self.kill(f"a process grew beyond {self.mem_mb} MB (killed)")
            elif len(tree) > self.max_children:
                self.kill(f"started more than {self.max_children} processes (killed)")
            time.sleep(0.1)
        self._done.set()

    def kill(self, why: str) -> None:
        """SIGKILL the process and every descendant seen, by PID."""
        if why and not self.killed:
            self.killed = why
        self.seen.update(descendants(self.proc.pid))
        for pid, start in [(self.proc.pid, None), *self.seen.items()]:
            if _alive(pid, start):
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass

    def signal(self, sig: int) -> None:
        if self.proc.poll() is None:
            os.kill(self.proc.pid, sig)

    def wait_line(self, pattern: str, timeout: float) -> str | None:
        """The first stderr line matching ``pattern`` (None: not within ``timeout`` or the
        process ended first)."""
        deadline = time.monotonic() + timeout
        seen = 0
        with self._line:
            while True:
                for line in self.err_lines[seen:]:
                    if re.search(pattern, line):
                        return line
                seen = len(self.err_lines)
                left = deadline - time.monotonic()
                if left <= 0 or (self.proc.poll() is not None and not self._readers[1].is_alive()):
                    return None
                self._line.wait(min(left, 0.5))

    def agents(self) -> dict[str, int]:
        """The agents of a running ``up``: agent id -> PID (from their command lines)."""
        found = {}
        for pid in _children(self.proc.pid):
            argv = cmdline(pid)
            kinds = [a.rsplit(".", 1)[1] for a in argv if a.startswith("adnmesh.agents.")]
            if kinds:
                kind = kinds[0]
                if kind == "der" and "--der" in argv:
                    kind = "der/" + argv[argv.index("--der") + 1]
                found[kind] = pid
        return found

    def wait(self) -> Result:
        """Wait for the end (the watcher enforces the timeout); end what it left behind."""
        self.proc.wait()
        self._done.wait(5)
        for t in self._readers:        # agents holding the pipes past up's end: bounded
            t.join(10)
        time.sleep(0.2)
        leftover = [pid for pid, start in self.seen.items() if _alive(pid, start)]
        if leftover:
            time.sleep(2.0)            # agents get a moment to follow up (parent-death signal)
            leftover = [pid for pid, start in self.seen.items() if _alive(pid, start)]
            for pid in leftover:
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        rc = None if (self.killed or self.stopped) else self.proc.returncode
        if self.log_to is not None:
            try:
                Path(f"{self.log_to}.stdout").write_text("".join(self.out_chunks))
                Path(f"{self.log_to}.stderr").write_text("\n".join(self.err_lines))
                if self.rss:
                    Path(f"{self.log_to}.rss.json").write_text(json.dumps(self.rss))
            except OSError:
                pass
        return Result(rc, "".join(self.out_chunks), "\n".join(self.err_lines),
                      time.monotonic() - self.t0, self.killed, self.stopped, self.peak,
                      leftover, self.rss, self.notes)


# ---------------------------------------------------------------------------------------------
# what a clean answer is

def _without_usage(lines: list[str]) -> list[str]:
    """argparse's usage block (``usage: ...`` and its indented continuation) left out."""
    kept, usage = [], False
    for line in lines:
        if line.startswith("usage: "):
            usage = True
            continue
        if usage and line.startswith(" "):
            continue
        usage = False
        kept.append(line)
    return kept


OWN_LINE = re.compile(r"^adnmesh|^[\w.-]+( [\w./-]+)?: error: |.*━")
"""Lines a program of adnmesh may print on stderr: its own (``adnmesh ...``), argparse's error
line of an agent program (``der: error: ...``), a progress bar."""


def traceback_in(err: str) -> str | None:
    """``traceback: <the exception line>`` of the first traceback in ``err``, or None."""
    lines = [line for line in err.splitlines() if line.strip()]
    starts = [i for i, line in enumerate(lines) if "Traceback (most recent call last)" in line]
    if not starts:
        return None
    for line in lines[starts[0] + 1:]:
        if not line.startswith((" ", "\t")) and not line.startswith(("During handling",
                                                                     "The above exception")):
            return f"traceback: {line.strip()[:180]}"
    return "traceback"


def stderr_problem(err: str, rc: int | None, out: str = "") -> str | None:
    """Why ``err`` is not clean (None if it is): a traceback; output not from adnmesh (a
    warning, an exception printed by a thread); an agent's internal error; with exit code 2,
    not exactly one error line (on stdout if stderr is empty: ``adnmesh fault`` says a
    refusal there); with another non-zero code, nothing said at all."""
    problem = traceback_in(err)
    if problem:
        return problem
    lines = _without_usage([line for line in err.splitlines() if line.strip()])
    foreign = [line for line in lines if not OWN_LINE.match(line)]
    if foreign:
        more = f" (+{len(foreign) - 1} more)" if len(foreign) > 1 else ""
        return f"stray output on stderr: {foreign[0].strip()[:160]}{more}"
    internal = [line for line in lines if "internal error" in line]
    if internal:
        return internal[0][:180]
    said = lines or [line for line in out.splitlines() if line.strip()][-1:]
    if rc not in (0, 2, None) and not said:
        return f"exit {rc} without a word"
    if rc == 2:
        errors = [line for line in said if re.search(r"\berror\b|\brefus", line, re.I)]
        if not errors:
            return "exit 2 without an error line"
        if len(errors) > 1:
            return f"{len(errors)} error lines: {errors[0][:120]} | {errors[1][:60]}"
    return None


def first_line(err: str) -> str:
    lines = [line.strip() for line in _without_usage(err.splitlines()) if line.strip()]
    errors = [line for line in lines if re.search(r"\berror\b|\brefus", line, re.I)]
    return (errors or lines or ["(no stderr)"])[-1][:160]


# ---------------------------------------------------------------------------------------------
# the build under test and the fixtures its cases share

@dataclass
class Target:
    prefix: list[str]
    env: dict
    tree: Path

    def argv(self, *args: str) -> list[str]:
        return [*self.prefix, *map(str, args)]

    def describe(self) -> str:
        pp = self.env.get("PYTHONPATH")
        return " ".join(self.prefix) + (f" (PYTHONPATH={pp})" if pp else "")


class Skip(Exception):
    """The case cannot run here; the message says why."""


class Fixtures:
    """Shared inputs, built on first use (one at a time: some run the build), torn down at
    the end. ``fx[name]`` is the fixture's value (mostly a path)."""

    def __init__(self, target: Target, root: Path, log: Callable[[str], None]):
        self.target, self.root, self.log = target, root, log
        self._values, self._errors, self._teardown = {}, {}, []
        self._lock = threading.RLock()
        self.up_lock = threading.Lock()      # one adnmesh up at a time

    def __getitem__(self, name: str):
        with self._lock:
            if name in self._values:
                return self._values[name]
            if name in self._errors:
                raise Skip(self._errors[name])
            t0 = time.monotonic()
            try:
                self._values[name] = FIXTURES[name](self)
            except Skip as exc:
                self._errors[name] = f"fixture {name}: {exc}"
                self.log(f"  (fixture {name} unavailable: {exc})")
                raise Skip(self._errors[name]) from None
            except Exception as exc:     # noqa: BLE001 - a fixture's failure skips its cases
                self._errors[name] = f"fixture {name} failed: {type(exc).__name__}: {exc}"
                self.log(f"  (fixture {name} failed: {exc})")
                raise Skip(self._errors[name]) from None
            if time.monotonic() - t0 > 2:
                self.log(f"  (fixture {name}: {time.monotonic() - t0:.1f} s)")
            return self._values[name]

    def on_teardown(self, fn: Callable[[], None]) -> None:
        self._teardown.append(fn)

    def teardown(self) -> None:
        for fn in reversed(self._teardown):
            try:
                fn()
            except Exception as exc:     # noqa: BLE001
                self.log(f"  (teardown: {exc})")
        self._teardown.clear()

    def doc(self, which: str) -> dict:
        path = {"small": "configs/examples/runtime-step.yaml", "ref": "configs/simbench.yaml"}
        return yaml.safe_load((self.target.tree / path[which]).read_text())

    def run(self, *args, cwd: Path, timeout: float = 120, **kw) -> Result:
        """Run the build to completion (a fixture's or a runner's own step)."""
        if args and args[0] == "up":
            with self.up_lock:
                return Proc(self.target.argv(*args), cwd, self.target.env, timeout, **kw).start().wait()
        return Proc(self.target.argv(*args), cwd, self.target.env, timeout, **kw).start().wait()


def set_path(doc, path: str, value) -> None:
    """``doc`` with ``a.0.b`` set to ``value`` (``*``: every item; DELETE: remove the key)."""
    *parents, last = path.split(".")
    nodes = [doc]
    for part in parents:
        nodes = [n for node in nodes for n in (
            (node.values() if isinstance(node, dict) else node) if part == "*"
            else [node.setdefault(part, {}) if isinstance(node, dict) else node[int(part)]])]
    for node in nodes:
        keys = (list(node) if isinstance(node, dict) else range(len(node))) if last == "*" \
            else [last if isinstance(node, dict) else int(last)]
        for key in keys:
            if value is DELETE:
                node.pop(key, None)
            else:
                node[key] = copy.deepcopy(value)


DELETE = object()
FIFO = object()          # a file value: make a FIFO there
DIR = object()           # a file value: make a folder there


def cfg(edits: dict | None = None, base: str = "small", replace: tuple = ()):
    """A config file's text: the small runtime case (or the reference ``ref``) with
    ``edits`` (``{"ders.0.t_rise_s": 1e-12}``) and then text replacements (old, new)."""
    def make(fx: Fixtures) -> str:
        doc = copy.deepcopy(fx.doc(base))
        for path, value in (edits or {}).items():
            set_path(doc, path, value)
        text = yaml.safe_dump(doc, sort_keys=False)
        for old, new in replace:
            assert old in text, old
            text = text.replace(old, new)
        return text
    return make


GRID = {"grid_model": {"study_case": "lW"}}


def tbl(edit: Callable[[dict], object]):
    """A table file's text: the small case's tuned table after ``edit(table)``."""
    def make(fx: Fixtures) -> str:
        table = json.loads(Path(fx["table"]).read_text())
        edit(table)
        return json.dumps(table, allow_nan=True)
    return make


def every_entry(table: dict):
    return [*table["entries"], *([table["static"]] if table.get("static") else [])]


def all_ders(table: dict) -> dict:
    return max(table["entries"], key=lambda e: len(e["ders"]))


def set_gains(**values):
    def edit(table):
        for entry in every_entry(table):
            entry.update(values)
    return edit


def _fx_small(fx: Fixtures) -> Path:
    path = fx.root / "small.yaml"
    path.write_text(cfg()(fx))
    return path


def _fx_table(fx: Fixtures) -> Path:
    """The small case tuned by the build itself (``adnmesh tune``)."""
    out = fx.root / "small.table.json"
    res = fx.run("tune", fx["small"], "--method", "global", "--out", out, cwd=fx.root,
                 timeout=300)
    if res.rc != 0 or not out.exists():
        raise RuntimeError(f"adnmesh tune exit {res.rc}: {first_line(res.err)}")
    return out


def _fx_rec(fx: Fixtures) -> Path:
    """A recording of the small case (``adnmesh up``)."""
    folder = fx.root / "rec"
    folder.mkdir(exist_ok=True)
    out = folder / "rec.mcap"
    res = fx.run("up", fx["small"], "--table", fx["table"], "--out", out, cwd=folder,
                 timeout=180)
    if res.rc != 0 or not out.exists():
        raise RuntimeError(f"adnmesh up exit {res.rc}: {first_line(res.err)}")
    return out


def _fx_trunc(fx: Fixtures) -> Path:
    """The recording cut at 60 % (a killed run's file)."""
    data = Path(fx["rec"]).read_bytes()
    out = fx.root / "trunc.mcap"
    out.write_bytes(data[: int(len(data) * 0.6)])
    return out


def _mount_tmpfs(fx: Fixtures, where: Path, options: str) -> bool:
    where.mkdir(exist_ok=True)
    if os.geteuid() != 0 or not shutil.which("mount"):
        return False
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "adnmesh-probe", str(where)],
                          capture_output=True, timeout=20, check=False)
    if done.returncode != 0:
        return False
    def unmount() -> None:
        if subprocess.run(["umount", str(where)], capture_output=True, timeout=20,
                          check=False).returncode != 0:
            subprocess.run(["umount", "-l", str(where)], capture_output=True, timeout=20,
                           check=False)
    fx.on_teardown(unmount)
    return True


def _fx_ro(fx: Fixtures) -> Path:
    """A folder nothing can be written to: mode 0555 for a user, a read-only tmpfs for root
    (whom mode bits do not stop)."""
    where = fx.root / "ro"
    if os.geteuid() != 0:
        where.mkdir()
        where.chmod(0o555)
        fx.on_teardown(lambda: where.chmod(0o755))
        return where
    if _mount_tmpfs(fx, where, "ro,size=64k,mode=0755"):
        return where
    raise Skip("root without the right to mount a read-only tmpfs: no read-only place")


def _fx_full(fx: Fixtures) -> Path:
    """A 1 MiB file system (a full disk soon)."""
    where = fx.root / "full"
    if _mount_tmpfs(fx, where, "size=1m,mode=0755"):
        return where
    raise Skip("cannot make a small file system without privileges (mount refused)")


def _fx_busy_port(fx: Fixtures) -> int:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    sock.listen(1)
    fx.on_teardown(sock.close)
    return sock.getsockname()[1]


def _fx_run(fx: Fixtures) -> Path:
    """A running ``up`` of the small case (3,600 s scenario) for ``adnmesh fault``: its
    ``.run.json``. It is ended (SIGINT, then SIGKILL by PID) at teardown."""
    folder = fx.root / "live"
    folder.mkdir()
    config = folder / "live.yaml"
    config.write_text(cfg({"scenario.duration_s": 3600})(fx))
    fx.up_lock.acquire()
    proc = Proc(fx.target.argv("up", config, "--out", folder / "live.mcap"), folder,
                fx.target.env, timeout=1200).start()

    def end() -> None:
        try:
            proc.signal(signal.SIGINT)
            deadline = time.monotonic() + 30
            while proc.proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.2)
            proc.kill("")
            proc.wait()
        finally:
            fx.up_lock.release()
    fx.on_teardown(end)
    if proc.wait_line(r"agents ready", 120) is None:
        raise RuntimeError(f"the live run did not get ready: {first_line(proc_err(proc))}")
    run_json = folder / "live.run.json"
    if not run_json.exists():
        raise RuntimeError("the live run wrote no live.run.json")
    return run_json


def proc_err(proc: Proc) -> str:
    return "\n".join(proc.err_lines)


FIXTURES: dict[str, Callable[[Fixtures], object]] = {
    "small": _fx_small, "table": _fx_table, "rec": _fx_rec, "trunc": _fx_trunc, "ro": _fx_ro,
    "full": _fx_full, "busy_port": _fx_busy_port, "run": _fx_run,
}


# ---------------------------------------------------------------------------------------------
# cases

@dataclass
class Case:
    name: str
    cls: str
    argv: tuple = ()                 # adnmesh arguments; {fixture} placeholders
    files: dict = field(default_factory=dict)   # name in the case folder -> text, bytes,
    #                                  fn(fixtures) -> text/bytes, FIFO or DIR
    codes: frozenset = frozenset({2})
    timeout: float = 60
    quick: bool = False              # part of --quick
    check: Callable | None = None    # (result, ctx) -> reason it fails, or None
    skip: Callable | None = None     # () -> reason to skip, or None
    mem_mb: int = 2500
    max_children: int = 40
    stop_when: str | None = None     # stderr pattern: the answer came; the probe ends it
    runner: Callable | None = None   # (ctx) -> reason it fails, or None (bus, process, ...)
    env: dict = field(default_factory=dict)
    note: str = ""                   # what the case is (for the report)

    @property
    def runs_up(self) -> bool:
        return self.runner is not None or (bool(self.argv) and self.argv[0] == "up")

    @property
    def needs_live_run(self) -> bool:
        return any("{run}" in str(a) for a in self.argv)


CASES: list[Case] = []


def case(cls: str, name: str, *argv, codes=(2,), **kw) -> None:
    """Declare a case: ``case("cli", "name", "up", "{small}", "--seed", "-1")``."""
    assert cls in CLASSES
    CASES.append(Case(f"{cls}/{name}", cls, tuple(map(str, argv)), codes=frozenset(codes), **kw))


def runner_case(cls: str, name: str, fn: Callable, **kw) -> None:
    CASES.append(Case(f"{cls}/{name}", cls, runner=fn, **kw))


@dataclass
class Ctx:
    """What a case's check or runner gets: its folder, the fixtures, the build."""
    dir: Path
    fx: Fixtures
    case: Case
    detail: str = ""                 # what a runner measured, shown also when it passes

    def json(self, name: str):
        path = self.dir / name
        if not path.exists():
            return None
        try:
            return json.loads(path.read_text())
        except ValueError:
            return None

    def _log_to(self, args) -> Path:
        self.n = getattr(self, "n", 0) + 1
        return self.dir / f"probe-{self.n}-{args[0] if args else 'adnmesh'}"

    def run(self, *args, timeout=120, **kw) -> Result:
        return self.fx.run(*args, cwd=self.dir, timeout=timeout, log_to=self._log_to(args), **kw)

    def proc(self, *args, timeout=300, **kw) -> Proc:
        return Proc(self.fx.target.argv(*args), self.dir, self.fx.target.env, timeout,
                    log_to=self._log_to(args), **kw)


def root_skip() -> str | None:
    return "root reads files whatever their mode" if os.geteuid() == 0 else None


def no_warning(res: Result, ctx: Ctx) -> str | None:
    return "warnings on stderr" if "Warning" in res.err else None


def summary_has(path: str = "s.json"):
    def check(res: Result, ctx: Ctx) -> str | None:
        return None if res.rc != 0 or ctx.json(path) is not None else f"no {path} written"
    return check


def answered_within(seconds: float):
    def check(res: Result, ctx: Ctx) -> str | None:
        return None if res.elapsed <= seconds else f"answered only after {res.elapsed:.0f} s"
    return check


# ---- cli: the issue's 23 command lines -------------------------------------------------------

S, T, R = "{small}", "{table}", "{rec}"
UP = ("up", S, "--table", T)

case("cli", "up-listen-port-99999", *UP, "--listen", "tcp/127.0.0.1:99999", quick=True)
case("cli", "up-listen-garbage", *UP, "--listen", "garbage", quick=True)
case("cli", "up-listen-foreign-address", *UP, "--listen", "tcp/192.0.2.1:7447", quick=True)
case("cli", "up-listen-busy-port", *UP, "--listen", "tcp/127.0.0.1:{busy_port}", codes=(1, 2),
     quick=True)
case("cli", "up-table-directory", "up", S, "--table", "d", files={"d": DIR}, quick=True)
case("cli", "up-out-directory", *UP, "--out", "d", files={"d": DIR}, quick=True)
case("cli", "up-out-read-only", *UP, "--out", "{ro}/run.mcap", quick=True)
case("cli", "tune-out-read-only", "tune", S, "--out", "{ro}/t.json", quick=True)
case("cli", "analyze-out-read-only", "analyze", S, "--table", T, "--out", "{ro}/a",
     "--only", "robustness", quick=True)
case("cli", "inspect-recover-to-read-only", "inspect", "{trunc}", "--recover-to",
     "{ro}/r.mcap", quick=True)
case("cli", "plot-out-read-only", "plot", R, "-o", "{ro}/p.png", quick=True)
case("cli", "replay-rrd-read-only", "replay", R, "--rrd", "{ro}/r.rrd", quick=True)
case("cli", "certs-read-only", "certs", "{ro}/certs", quick=True)
case("cli", "up-dev-zero", "up", "/dev/zero", timeout=30, mem_mb=1500, quick=True)
case("cli", "check-dev-zero", "check", "/dev/zero", timeout=30, mem_mb=1500, quick=True)
case("cli", "up-fifo", "up", "f.yaml", files={"f.yaml": FIFO}, timeout=15, quick=True)
case("cli", "check-fifo", "check", "f.yaml", files={"f.yaml": FIFO}, timeout=15, quick=True)
case("cli", "margins-kp-1e400", "margins", S, "--kp", "1e400", "--ki", "1.9e-7", quick=True)
case("cli", "margins-kp-1e300", "margins", S, "--kp", "1e300", "--ki", "1.9e-7", codes=(0, 2),
     quick=True, note="0 only without warnings")
case("cli", "tune-subsets-binary", "tune", S, "--subsets", "b.txt", "--out", "t.json",
     files={"b.txt": bytes(range(256)) * 64}, quick=True)
case("cli", "router-connect-garbage", "router", S, "--name", "site", "--connect", "garbage",
     quick=True)
case("cli", "up-speed-1e-300", *UP, "--clock", "realtime", "--speed", "1e-300", timeout=30,
     quick=True)
case("cli", "fault-at-beyond-scenario", "fault", "{run}", "ict_outage", "--at", "99999",
     quick=True)

# ---- cli: a broad sweep of other bad arguments, every subcommand -----------------------------

case("cli", "no-command")
case("cli", "unknown-command", "frobnicate")
case("cli", "version", "--version", codes=(0,))
case("cli", "schema-unknown", "schema", "nothing")
case("cli", "schema-config", "schema", "config", codes=(0,))

# check
for name, arg, files in [
        ("missing", "nope.yaml", {}), ("directory", "d", {"d": DIR}), ("empty", "e.yaml", {"e.yaml": ""}),
        ("binary", "b.yaml", {"b.yaml": bytes(range(256)) * 16}),
        ("unicode-missing", "ĉonfig-✓-😀.yaml", {}), ("empty-name", "", {}),
        ("proc-file", "/proc/self/status", {}), ("dev-null", "/dev/null", {}),
        ("dev-urandom", "/dev/urandom", {})]:
    case("cli", f"check-{name}", "check", arg, files=files, timeout=30, mem_mb=1500)
case("cli", "check-unreadable", "check", "u.yaml", files={"u.yaml": cfg()}, skip=root_skip)
case("cli", "check-valid", "check", S, codes=(0,))

# up (every one refused before anything starts)
for name, args in [
        ("seed-negative", ("--seed", "-1")), ("seed-2**64", ("--seed", str(2**64))),
        ("seed-text", ("--seed", "abc")),
        ("speed-without-realtime", ("--speed", "2")),
        ("speed-zero", ("--clock", "realtime", "--speed", "0")),
        ("speed-negative", ("--clock", "realtime", "--speed", "-1")),
        ("speed-nan", ("--clock", "realtime", "--speed", "nan")),
        ("speed-1e400", ("--clock", "realtime", "--speed", "1e400")),
        ("clock-unknown", ("--clock", "lunar")),
        ("strict-without-realtime", ("--strict",)),
        ("rt-priority-unknown", ("--rt-priority", "max")),
        ("stall-timeout-negative", ("--stall-timeout", "-1")),
        ("stall-timeout-nan", ("--stall-timeout", "nan")),
        ("startup-timeout-zero", ("--startup-timeout", "0")),
        ("startup-timeout-nan", ("--startup-timeout", "nan")),
        ("startup-timeout-1e300", ("--startup-timeout", "1e300")),
        ("listen-empty", ("--listen", "")),
        ("listen-tls-open-profile", ("--listen", "tls/127.0.0.1:7447")),
        ("listen-unicode", ("--listen", "tcp/ħøšt:7447")),
        ("external-unknown-der", ("--external", "der:Nope")),
        ("external-garbage", ("--external", ",,,")),
        ("routers-open-profile", ("--routers", "site")),
        ("certs-missing", ("--certs", "nocerts")),
        ("certs-empty-dir", ("--certs", "d")),
        ("summary-json-directory", ("--summary-json", "d")),
        ("summary-json-read-only", ("--summary-json", "{ro}/s.json")),
        ("view-read-only", ("--view", "{ro}/v.rrd")),
        ("view-unknown", ("--view", "somewhere.xyz")),
]:
    case("cli", f"up-{name}", *UP, *args, files={"d": DIR} if "d" in args else {},
         codes=(0, 2) if name in ("listen-empty", "external-garbage") else (2,))
case("cli", "up-config-missing", "up", "nope.yaml")
case("cli", "up-config-directory", "up", "d", files={"d": DIR})
case("cli", "up-config-empty", "up", "e.yaml", files={"e.yaml": ""})
case("cli", "up-table-missing", "up", S, "--table", "nope.json")
case("cli", "up-table-garbage", "up", S, "--table", "g.json", files={"g.json": "{not json"})
case("cli", "up-table-fifo", "up", S, "--table", "f.json", files={"f.json": FIFO}, timeout=15)
case("cli", "up-table-dev-zero", "up", S, "--table", "/dev/zero", timeout=30, mem_mb=1500)

# margins
for name, args in [
        ("kp-nan", ("--kp", "nan", "--ki", "1.9e-7")), ("kp-inf", ("--kp", "inf", "--ki", "1.9e-7")),
        ("kp-negative", ("--kp", "-5e-8", "--ki", "1.9e-7")), ("kp-zero", ("--kp", "0", "--ki", "1.9e-7")),
        ("kp-text", ("--kp", "abc", "--ki", "1.9e-7")),
        ("ki-1e400", ("--kp", "5e-8", "--ki", "1e400")), ("ki-nan", ("--kp", "5e-8", "--ki", "nan")),
        ("ki-negative", ("--kp", "5e-8", "--ki", "-1")),
        ("ders-unknown", ("--kp", "5e-8", "--ki", "1.9e-7", "--ders", "Nope")),
        ("ders-empty", ("--kp", "5e-8", "--ki", "1.9e-7", "--ders", "")),
        ("ders-twice", ("--kp", "5e-8", "--ki", "1.9e-7", "--ders", "SGen1,SGen1")),
]:
    case("cli", f"margins-{name}", "margins", S, *args,
         codes=(0, 2) if name == "ders-twice" else (2,))
case("cli", "margins-kp-1e-300", "margins", S, "--kp", "1e-300", "--ki", "1e-300", codes=(0, 2),
     check=no_warning, note="0 only without warnings")
case("cli", "margins-config-missing", "margins", "nope.yaml", "--kp", "5e-8", "--ki", "1.9e-7")

# tune
for name, args, files in [
        ("out-directory", ("--out", "d"), {"d": DIR}),
        ("subsets-missing", ("--subsets", "nope.txt"), {}),
        ("subsets-directory", ("--subsets", "d"), {"d": DIR}),
        ("subsets-fifo", ("--subsets", "f.txt"), {"f.txt": FIFO}),
        ("subsets-dev-zero", ("--subsets", "/dev/zero"), {}),
        ("subsets-empty-file", ("--subsets", "e.txt"), {"e.txt": ""}),
        ("subsets-unknown-der", ("--subsets", "u.txt"), {"u.txt": "SGen1 Nope\n"}),
        ("subsets-random-0", ("--subsets", "random:0"), {}),
        ("subsets-random-negative", ("--subsets", "random:-1"), {}),
        ("subsets-random-1e9", ("--subsets", "random:1000000000"), {}),
        ("subsets-unknown", ("--subsets", "some"), {}),
        ("workers-zero", ("--workers", "0"), {}),
        ("workers-negative", ("--workers", "-1"), {}),
        ("workers-million", ("--workers", "1000000"), {}),
        ("disk-margin-nan", ("--disk-margin-min", "nan"), {}),
        ("disk-margin-2.5", ("--disk-margin-min", "2.5"), {}),
        ("overshoot-nan", ("--overshoot-max-pct", "nan"), {}),
        ("overshoot-negative", ("--overshoot-max-pct", "-1"), {}),
        ("overshoot-1e400", ("--overshoot-max-pct", "1e400"), {}),
        ("method-unknown", ("--method", "magic"), {}),
]:
    extra = () if "--out" in args else ("--out", "t.json")
    codes = (0, 2) if name in ("workers-million", "subsets-random-1e9") else (2,)
    case("cli", f"tune-{name}", "tune", S, *args, *extra, files=files, codes=codes, timeout=90,
         mem_mb=1500, max_children=12)
case("cli", "tune-resume-without-table", "tune", S, "--resume", "--out", "t.json", codes=(0, 2),
     timeout=90)

# analyze
A = ("analyze", S, "--only", "robustness")
for name, args, files in [
        ("table-missing", ("--table", "nope.json"), {}),
        ("table-garbage", ("--table", "g.json"), {"g.json": "[1, 2"}),
        ("table-nan-gains", ("--table", "n.json"), {"n.json": tbl(set_gains(kp=NAN))}),
        ("out-is-a-file", ("--table", T, "--out", "f"), {"f": "x"}),
        ("grid-zero", ("--table", T, "--grid", "0"), {}),
        ("grid-negative", ("--table", T, "--grid", "-5"), {}),
        ("grid-1e9", ("--table", T, "--grid", "1000000000", "--only", "solution-space",
                      "--solution-space", "SGen1"), {}),
        ("models-unknown", ("--table", T, "--models", "pt9"), {}),
        ("only-unknown", ("--table", T, "--only", "everything"), {}),
        ("solution-space-unknown", ("--table", T, "--solution-space", "Nope"), {}),
        ("solution-space-empty", ("--table", T, "--solution-space", ""), {}),
]:
    case("cli", f"analyze-{name}", *A, *args, files=files, timeout=90, mem_mb=2000,
         codes=(0, 2) if name == "solution-space-empty" else (2,))

# certs
for name, args, files in [
        ("dir-is-a-file", ("f",), {"f": "x"}), ("days-zero", ("c", "--days", "0"), {}),
        ("days-negative", ("c", "--days", "-1"), {}), ("days-1e9", ("c", "--days", "1000000000"), {}),
        ("days-text", ("c", "--days", "ever"), {}), ("host-empty", ("c", "--host", ""), {}),
        ("host-garbage", ("c", "--host", "bad host/name!"), {}),
        ("renew-unknown", ("c", "--renew", "der/Nope"), {}),
        ("config-missing", ("c", "--config", "nope.yaml"), {}),
        ("router-traversal", ("c", "--router", "../../x"), {}),
]:
    case("cli", f"certs-{name}", "certs", *args, files=files)

# agent
AG = ("--connect", "tcp/127.0.0.1:1", "--connect-timeout", "1")
for name, args in [
        ("kind-unknown", ("wizard", S, *AG)), ("connect-garbage", ("der", S, "--id", "SGen1",
                                                                    "--connect", "garbage")),
        ("der-without-id", ("der", S, *AG)), ("der-unknown-id", ("der", S, "--id", "Nope", *AG)),
        ("connect-timeout-negative", ("der", S, "--id", "SGen1", "--connect",
                                      "tcp/127.0.0.1:1", "--connect-timeout", "-1")),
        ("connect-timeout-nan", ("der", S, "--id", "SGen1", "--connect", "tcp/127.0.0.1:1",
                                 "--connect-timeout", "nan")),
        ("resume-at-ns-negative", ("der", S, "--id", "SGen1", *AG, "--resume-at-ns", "-1")),
        ("resume-at-ns-huge", ("der", S, "--id", "SGen1", *AG, "--resume-at-ns", str(10**30))),
        ("cpfc-table-garbage", ("cpfc", S, *AG, "--table", "g.json")),
        ("tls-without-certs", ("der", S, "--id", "SGen1", "--connect", "tls/127.0.0.1:1")),
        ("certs-missing", ("der", S, "--id", "SGen1", "--connect", "tls/127.0.0.1:1",
                           "--certs", "nocerts")),
        ("config-missing", ("der", "nope.yaml", "--id", "SGen1", *AG)),
]:
    case("cli", f"agent-{name}", "agent", *args, files={"g.json": "{"}, timeout=30)
case("cli", "agent-router-unreachable", "agent", "der", S, "--id", "SGen1", *AG, codes=(1,),
     timeout=30, note="docs: exit 1 when the router could not be reached")

# router
RT = ("router", S, "--name", "site")
for name, args in [
        ("listen-garbage", ("--connect", "tcp/127.0.0.1:1", "--listen", "garbage")),
        ("listen-port-99999", ("--connect", "tcp/127.0.0.1:1", "--listen", "tcp/127.0.0.1:99999")),
        ("connect-port-99999", ("--connect", "tcp/127.0.0.1:99999")),
        ("certs-missing", ("--connect", "tls/127.0.0.1:1", "--certs", "nocerts")),
        ("tls-without-certs", ("--connect", "tls/127.0.0.1:1")),
]:
    case("cli", f"router-{name}", *RT, *args, timeout=30)
case("cli", "router-name-traversal", "router", S, "--name", "../../x", "--connect",
     "tcp/127.0.0.1:1", timeout=30)
case("cli", "router-listen-busy-port", *RT, "--connect", "tcp/127.0.0.1:1", "--listen",
     "tcp/127.0.0.1:{busy_port}", codes=(1, 2), timeout=30,
     note="docs: exit 1 if the router cannot start")

# replay, plot, inspect: the recording's readers
for cmd, extra in (("replay", ()), ("plot", ()), ("inspect", ())):
    for name, arg, files in [
            ("missing", "nope.mcap", {}), ("directory", "d", {"d": DIR}),
            ("empty", "e.mcap", {"e.mcap": b""}), ("garbage", "g.mcap", {"g.mcap": b"\x89MCAP0\r\n" + bytes(range(256)) * 8}),
            ("fifo", "f.mcap", {"f.mcap": FIFO}), ("dev-zero", "/dev/zero", {})]:
        case("cli", f"{cmd}-{name}", cmd, arg, *extra, files=files,
             timeout=15 if name == "fifo" else 30, mem_mb=1500)
case("cli", "replay-rrd-directory", "replay", R, "--rrd", "d", files={"d": DIR})
case("cli", "replay-web-port-99999", "replay", R, "--web", "--web-port", "99999", timeout=30)
case("cli", "plot-out-directory", "plot", R, "-o", "d", files={"d": DIR})
case("cli", "plot-out-unknown-format", "plot", R, "-o", "p.nosuchformat")
case("cli", "inspect-recover-to-directory", "inspect", "{trunc}", "--recover-to", "d",
     files={"d": DIR})
case("cli", "inspect-truncated", "inspect", "{trunc}", "--recover-to", "r.mcap", codes=(0, 1),
     note="a killed run's file is recovered")
case("cli", "inspect-valid", "inspect", R, codes=(0,))

# fault, against a running up (the live fixture) and without one
F = ("fault", "{run}")
for name, args in [
        ("at-negative", ("ict_outage", "--at", "-5")), ("at-nan", ("ict_outage", "--at", "nan")),
        ("at-1e300", ("ict_outage", "--at", "1e300")),
        ("for-negative", ("ict_outage", "--for", "-1")),
        ("probability-1.5", ("link_loss", "cpfc_to_der", "--probability", "1.5")),
        ("probability-nan", ("link_loss", "cpfc_to_der", "--probability", "nan")),
        ("delay-negative", ("link_delay", "cpfc_to_der", "--delay", "-1")),
        ("delay-1e300", ("link_delay", "cpfc_to_der", "--delay", "1e300")),
        ("kind-unknown", ("meteor",)), ("kill-unknown-agent", ("kill", "nobody")),
        ("kill-without-target", ("kill",)), ("der-offline-unknown", ("der_offline", "Nope")),
        ("link-unknown", ("link_outage", "wormhole")),
        ("timeout-negative", ("ict_outage", "--timeout", "-1")),
        ("timeout-nan", ("ict_outage", "--timeout", "nan")),
        ("certs-missing", ("ict_outage", "--certs", "nocerts")),
]:
    case("cli", f"fault-{name}", *F, *args, timeout=30)
case("cli", "fault-unknown-run", "fault", "no-such-run-id", "ict_outage", codes=(1, 2), timeout=30)
case("cli", "fault-run-json-garbage", "fault", "g.run.json", "ict_outage", files={
    "g.run.json": "{"}, timeout=30)
case("cli", "fault-endpoint-nobody", "fault", "tcp/127.0.0.1:1", "ict_outage", "--timeout", "2",
     codes=(1, 2), timeout=30, note="docs: 1 without answer")

# ---- config: configs that pass validation but crash, stall or are refused late ---------------

TINY_RISE = cfg({"ders.0.t_rise_s": 1e-12})
LONG_DELAY = cfg({"ders.0.t_delay_s": 3600})
case("config", "t-rise-1e-12-up", "up", "c.yaml", files={"c.yaml": TINY_RISE}, codes=(0, 2),
     timeout=90, mem_mb=2000, quick=True)
case("config", "t-rise-1e-12-tune", "tune", "c.yaml", "--out", "t.json", files={"c.yaml": TINY_RISE},
     codes=(0, 2), timeout=90, mem_mb=2000, max_children=12, quick=True)
case("config", "t-rise-1e-12-margins", "margins", "c.yaml", "--kp", "5e-8", "--ki", "1.9e-7",
     files={"c.yaml": TINY_RISE}, codes=(0, 2), timeout=60, mem_mb=2000, quick=True)
case("config", "t-delay-3600-up", "up", "c.yaml", files={"c.yaml": LONG_DELAY}, codes=(0, 2),
     timeout=90, mem_mb=2000, quick=True)
case("config", "t-delay-3600-tune", "tune", "c.yaml", "--out", "t.json",
     files={"c.yaml": LONG_DELAY}, codes=(0, 2), timeout=60, mem_mb=2000, max_children=12,
     quick=True)
case("config", "t-delay-3600-margins", "margins", "c.yaml", "--kp", "5e-8", "--ki", "1.9e-7",
     files={"c.yaml": LONG_DELAY}, codes=(0, 2), timeout=60, mem_mb=2000)
case("config", "voltage-band-inverted", "check", "c.yaml", files={"c.yaml": cfg({
    **GRID, "grid_model.limits": {"v_min_pu": 1.1, "v_max_pu": 0.9}})}, timeout=90, quick=True)


def thousand_ders(fx: Fixtures) -> str:
    doc = fx.doc("small")
    der = doc["ders"][0]
    doc["ders"] = [{**der, "id": f"D{i:04d}", "sgen": f"sgen {i}"} for i in range(1000)]
    doc["scenario"]["availability"] = []
    return yaml.safe_dump(doc, sort_keys=False)


case("config", "1000-ders-check", "check", "c.yaml", files={"c.yaml": thousand_ders},
     codes=(0, 2), timeout=60, quick=True)
case("config", "1000-ders-up", "up", "c.yaml", files={"c.yaml": thousand_ders}, codes=(2,),
     timeout=60, max_children=30, stop_when=r"started \d+ agents", quick=True,
     check=answered_within(60),
     note="answered within 60 s: refused in one line, or the agents started (then ended by "
          "the probe)")

for name, edits in [
        ("sgen-not-in-net", {**GRID, "ders.0.sgen": "MV1.101 SGen 999"}),
        ("unknown-simbench-code", {**GRID, "simbench_code": "1-MV-nowhere--0-no_sw"}),
        ("unknown-study-case", {"grid_model": {"study_case": "zz"}}),
        ("load-name-as-sgen", {**GRID, "ders.0.sgen": "MV1.101 Load 2"}),
]:
    for cmd in ("check", "up"):
        case("config", f"{cmd}-{name}", cmd, "c.yaml", files={"c.yaml": cfg(edits)},
             timeout=150, quick=True, note="check refuses what up refuses")

# the YAML reader and the validator, hostile
BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [{', '.join(['*' + p] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi"))
for name, content in [
        ("alias-bomb", BOMB),
        ("nested-100000", "a: " + "[" * 100000 + "]" * 100000 + "\n"),
        ("nested-flow-maps", "a: " + "{b: " * 20000 + "1" + "}" * 20000 + "\n"),
        ("a-list", "- 1\n- 2\n"),
        ("20-mib-comment", lambda fx: cfg()(fx) + "#" * (20 * 2**20) + "\n"),
        ("non-utf8", b"grid: \xff\xfe\n"),
        ("nan-delay", cfg({"t_com_s": NAN})), ("inf-power", cfg({"ders.0.p_inst_w": INF})),
        ("1e400-delay", cfg(replace=(("t_com_s: 0.1", "t_com_s: 1e400"),))),
        ("seed-10**400", cfg(replace=(("seed: 7", "seed: 1" + "0" * 400),))),
        ("duplicate-key", cfg(replace=(("t_com_s: 0.1", "t_com_s: 0.1\nt_com_s: 0.2"),))),
        ("unknown-key", cfg({"t_comm_s": 0.1})),
        ("1001-ders", lambda fx: yaml.safe_dump({**fx.doc("small"), "ders": [
            {**fx.doc("small")["ders"][0], "id": f"D{i}", "sgen": f"s{i}"} for i in range(1001)]})),
        ("negative-power", cfg({"ders.0.p_inst_w": -2e6})),
        ("duration-1e7", cfg({"scenario.duration_s": 1e7})),
        ("step-after-end", cfg({"scenario.p_ref_steps": [{"t_s": 99, "delta_w": 1e6}]})),
        ("id-with-slash", cfg({"ders.0.id": "SGen/1"})),
        ("grid-with-wildcard", cfg({"grid": "adn/**"})),
        ("period-zero", cfg({"runtime.pi_period_s": 0})),
]:
    case("config", f"check-{name}", "check", "c.yaml", files={"c.yaml": content}, timeout=60,
         mem_mb=2000)
case("config", "up-pi-period-1e-6", "up", "c.yaml", files={"c.yaml": cfg({
    "runtime.pi_period_s": 1e-6})}, codes=(0, 2), timeout=120, mem_mb=2000,
    note="the documented minimum period: runs or is refused")
case("config", "margins-t-com-3600", "margins", "c.yaml", "--kp", "5e-8", "--ki", "1.9e-7",
     files={"c.yaml": cfg({"t_com_s": 3600})}, codes=(0, 2), timeout=60, mem_mb=2000)


def grid_cache_tampered(ctx: Ctx) -> str | None:
    """A grid-cache .npz with the line ratings divided by 10: the run must not take it (the
    loading it reports stays what the untampered cache gives, or it refuses in one line)."""
    import numpy as np

    cache = ctx.dir / "cache"
    cache.mkdir()
    env = {"ADNMESH_CACHE_DIR": str(cache)}
    config = ctx.dir / "g.yaml"
    config.write_text(cfg({**GRID, "scenario.duration_s": 4, "scenario.p_ref_steps": [
        {"t_s": 1, "delta_w": 5e5}], "scenario.availability": []})(ctx.fx))
    target = ctx.fx.target
    saved = target.env
    target.env = {**saved, **env}
    try:
        first = ctx.run("up", config, "--out", "a.mcap", "--summary-json", "a.json", timeout=240)
        files = sorted(cache.glob("*.npz"))
        if not files:
            raise Skip("the build did not use ADNMESH_CACHE_DIR (the shared cache is left alone)")
        if first.rc != 0 or ctx.json("a.json") is None:
            return f"the untampered run failed: exit {first.rc}: {first_line(first.err)}"
        before = ctx.json("a.json")["grid"]["line_loading_max_pct"]
        for path in files:
            with np.load(path, allow_pickle=False) as npz:
                arrays = {k: npz[k] for k in npz.files}
            keys = [k for k in arrays if "line" in k and ("max" in k or "rating" in k)]
            if not keys:
                raise Skip(f"no line-rating array in {path.name}: {sorted(arrays)}")
            for k in keys:
                arrays[k] = arrays[k] / 10
            with open(path, "wb") as fh:
                np.savez(fh, **arrays)
        second = ctx.run("up", config, "--out", "b.mcap", "--summary-json", "b.json", timeout=240)
    finally:
        target.env = saved
    if second.rc == 2:
        return stderr_problem(second.err, 2)
    if second.rc != 0 or ctx.json("b.json") is None:
        return f"the run on the tampered cache: exit {second.rc}: {first_line(second.err)}"
    after = ctx.json("b.json")["grid"]["line_loading_max_pct"]
    if not math.isclose(after, before, rel_tol=0.01):
        return f"tampered cache taken: line loading {after:.1f} % instead of {before:.1f} %"
    return None


runner_case("config", "grid-cache-ratings-divided-by-10", grid_cache_tampered, timeout=600)

# ---- table: tables that pass the loader but crash or stall ------------------------------------

UPT = ("up", S, "--table", "t.json", "--out", "r.mcap", "--stall-timeout", "20")


def tcase(name: str, edit_or_text, quick=False, codes=(2,), **kw) -> None:
    content = edit_or_text if isinstance(edit_or_text, (str, bytes)) else tbl(edit_or_text)
    case("table", name, *UPT, files={"t.json": content}, codes=codes, timeout=90, quick=quick,
         **kw)


def _unknown_der(t):
    entry = all_ders(t)
    entry["ders"] = [*entry["ders"], "SGenX"]
    entry["w"]["SGenX"] = 1.0


def _weight(value):
    def edit(t):
        entry = all_ders(t)
        entry["w"][entry["ders"][0]] = value
    return edit


def _scaled(factor):
    def edit(t):
        entry = all_ders(t)
        entry["kp"] *= factor
        entry["ki"] *= factor
    return edit


tcase("kp-nan", set_gains(kp=NAN), quick=True)
tcase("kp-negative", set_gains(kp=-5e-8), quick=True)
tcase("ki-zero", set_gains(ki=0.0), quick=True)
tcase("unknown-der-id", _unknown_der, quick=True)
tcase("nested-100000", "[" * 100000 + "]" * 100000, quick=True)
tcase("kp-ki-1e300", set_gains(kp=1e300, ki=1e300), quick=True)
tcase("negative-weight", _weight(-0.5), quick=True)
tcase("unstable-gains-x12", _scaled(12), quick=True, note="issue: unstable gains used silently")
tcase("kp-infinity", set_gains(kp=INF))
tcase("weight-5", _weight(5.0))
tcase("weight-zero", _weight(0.0), codes=(0,),
      note="accepted: Find W gives 0 to a DER whose single loop violates at every weight "
           "(docs/method.md#find-w); the rule is [0, 1], not all 0 in a feasible entry")
tcase("weights-all-zero", lambda t: all_ders(t).update(w=dict.fromkeys(all_ders(t)["ders"], 0.0)))
tcase("entries-missing", lambda t: t.pop("entries"))
tcase("entries-empty", lambda t: t.update(entries=[]), codes=(0, 2),
      note="an empty table: tuned on demand or refused")
tcase("entry-empty-subset", lambda t: t["entries"].append({**t["entries"][0], "ders": [], "w": {}}))
tcase("entry-weights-of-other-ders", lambda t: all_ders(t).update(w={"SGen1": 1.0}))
def _other_design(t):
    """A table tuned for another config: another design where the table keeps one (a build
    that binds tables to the design), else another file's sha256 (one that binds to the file)."""
    if "design" not in t:
        t.update(config_sha256="0" * 64)
        return
    t["design"]["ders"][0]["t_delay_s"] = 5.0
    text = json.dumps(t["design"], sort_keys=True, separators=(",", ":"), allow_nan=False)
    t["design_sha256"] = hashlib.sha256(text.encode()).hexdigest()


tcase("other-config", _other_design)
tcase("format-99", lambda t: t.update(format=99))
tcase("static-kp-nan", lambda t: t["static"] and t["static"].update(kp=NAN))
tcase("empty-file", "")
tcase("not-json", "{entries: [")
tcase("huge-number", lambda t: all_ders(t).update(kp=10**400))
tcase("duplicate-entry", lambda t: t["entries"].append(copy.deepcopy(all_ders(t))), codes=(0, 2))
tcase("10-mib", lambda t: t.update(pad="x" * (10 * 2**20)), codes=(0, 2))
case("table", "analyze-kp-nan", "analyze", S, "--table", "t.json", "--only", "robustness",
     files={"t.json": tbl(set_gains(kp=NAN))}, timeout=90)
case("table", "agent-cpfc-kp-nan", "agent", "cpfc", S, "--table", "t.json", "--connect",
     "tcp/127.0.0.1:1", "--connect-timeout", "1", files={"t.json": tbl(set_gains(kp=NAN))},
     timeout=30, note="the CPFC refuses the table before it connects (else exit 1)")

# ---- bus: junk and forged messages against a running up ---------------------------------------


def envelope(type_: str, src: str, seq: int, t_ns: int, **body) -> bytes:
    """A message as docs/runtime.md describes the envelope."""
    return json.dumps({"v": 1, "type": type_, "src": src, "seq": seq, "t_send_ns": t_ns,
                       "t_deliver_ns": t_ns, **body}).encode()


def zenoh_session(endpoint: str, certs: Path | None = None, identity: str | None = None):
    try:
        import zenoh
    except ImportError:
        raise Skip("no zenoh in the probe's interpreter") from None
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    if certs is not None:
        config.insert_json5("transport/link/tls", json.dumps({
            "root_ca_certificate": str(certs / "ca.pem"), "enable_mtls": True,
            "connect_certificate": str(certs / f"{identity}.pem"),
            "connect_private_key": str(certs / f"{identity}.key"),
            "verify_name_on_connect": True}))
        config.insert_json5("transport/link/protocols", json.dumps(["tls"]))
    return zenoh.open(config)


def put_all(endpoint: str, messages, certs=None, identity=None) -> int:
    import zenoh
    with zenoh_session(endpoint, certs, identity) as session:
        for key, payload in messages:
            session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
    return len(messages)


BUS = {"scenario": {"duration_s": 200, "p_ref_steps": [{"t_s": 40, "delta_w": 1.0e6}],
                    "availability": [{"t_s": 90, "available": False, "ders": ["SGen2"]}]}}
AT_NS = 150 * 10**9


def _endpoint(proc: Proc) -> str:
    line = proc.wait_line(r"router on \S+", 5) or ""
    found = re.search(r"router on ((?:tcp|tls)/[^\s;]+)", line)
    if not found:
        raise RuntimeError(f"no router endpoint in up's output: {line!r}")
    return found.group(1)


def bus_run(ctx: Ctx, attack: Callable[[str, str], object] | None, *extra, changes=BUS,
            name="run", timeout=240) -> tuple[Result, dict | None, Path]:
    """``up`` of the small case with ``changes``; once every agent is ready,
    ``attack(endpoint, grid)``; return (result, summary JSON, recording)."""
    config = ctx.dir / f"{name}.yaml"
    doc = ctx.fx.doc("small")
    for section, values in changes.items():
        doc.setdefault(section, {}).update(values)
    config.write_text(yaml.safe_dump(doc, sort_keys=False))
    out = ctx.dir / f"{name}.mcap"
    with ctx.fx.up_lock:
        stall = () if "--stall-timeout" in map(str, extra) else ("--stall-timeout", "20")
        proc = ctx.proc("up", config, "--out", out, "--summary-json", f"{name}.json", *stall,
                        *extra, timeout=timeout).start()
        try:
            if attack is not None:
                if proc.wait_line(r"agents ready", 120) is None:
                    proc.kill("")
                    res = proc.wait()
                    raise RuntimeError(f"up did not get ready: exit {res.rc}: {first_line(res.err)}")
                proc.notes["attack"] = attack(_endpoint(proc), doc["grid"])
        except BaseException:
            proc.kill("")
            proc.wait()
            raise
        res = proc.wait()
    return res, ctx.json(f"{name}.json"), out


def _ended(summary: dict | None) -> str:
    return (summary or {}).get("extra", {}).get("ended", "?")


def run_problem(res: Result, summary, codes=(0,)) -> str | None:
    """Why a run that should survive did not (None: it did)."""
    if res.killed:
        return res.killed
    problem = stderr_problem(res.err, 0)
    if problem:
        return problem
    if res.rc not in codes:
        return f"exit {res.rc}: {first_line(res.err)}"
    if summary is None:
        return "no summary JSON"
    if res.leftover:
        return f"{len(res.leftover)} process(es) left running after up"
    return None


def _baseline(ctx: Ctx) -> dict:
    """The undisturbed bus run (same config and seed), once."""
    if "bus_baseline" not in ctx.fx._values:
        with ctx.fx._lock:
            if "bus_baseline" not in ctx.fx._values:
                folder = ctx.fx.root / "bus-baseline"
                folder.mkdir(exist_ok=True)
                res, summary, out = bus_run(Ctx(folder, ctx.fx, ctx.case), None, name="base")
                if run_problem(res, summary):
                    raise Skip(f"the undisturbed run failed: {run_problem(res, summary)}")
                ctx.fx._values["bus_baseline"] = {"summary": summary, "size": out.stat().st_size}
    return ctx.fx._values["bus_baseline"]


def _steps(summary) -> list:
    return [(s["t_s"], round(s["figures"].get("rise_time_s") or -1, 6),
             round(s["figures"].get("overshoot_pct") or 0, 6)) for s in summary.get("steps", [])]


def junk_payloads(grid: str) -> list[tuple[str, bytes]]:
    root = f"adn/{grid}/"
    keys = ["cpfc/p_y", "scenario/p_ref", "der/SGen1/state", "der/SGen1/heartbeat",
            "measurement/p_ip", "measurement/grid", "availability/si", "faults", "control/fault",
            "event/up", "clock/report/cpfc", "clock/grant/cpfc", "clock/start", "clock/stop",
            "clock/bye/cpfc", "clock/kill/cpfc", "der/Nope/state", "der/SGen1/state/extra"]
    bodies = [b"", b"\xff\xfe\x00junk", b"{", b"null", b"[]", b'{"v":1}', b'{"v":1,"type":"p_y"}',
              envelope("p_y", "cpfc", 1, 10**9, p_y=NAN, p_ref_w=1e6, kp=5e-8, ki=2e-7,
                       entry=1).replace(b"NaN", b"1e999"),
              envelope("p_ip", "cpfc", 1, 10**9, p_ip_w=1),                    # wrong sender
              envelope("p_ip", "measurement", 10**40, 10**9, p_ip_w=1),       # 40-digit seq
              envelope("p_ip", "measurement", 1, -5, p_ip_w=1),               # negative time
              envelope("clock_stop", "rogue", 1, 10**9, reason="junk"),       # wrong sender
              envelope("der_state", "der/Nope", 1, 10**9, p_w=1, setpoint_w=1, mode="control"),
              b"[" * 50000 + b"]" * 50000, b"\n" * 1000, b"x" * (1 << 20)]
    return [(root + k, b) for k in keys for b in bodies]


def bus_junk(ctx: Ctx) -> str | None:
    base = _baseline(ctx)
    res, summary, _ = bus_run(ctx, lambda ep, grid: put_all(ep, junk_payloads(grid)))
    problem = run_problem(res, summary)
    if problem:
        return problem
    if _ended(summary) != "finished":
        return f"ended {_ended(summary)!r}"
    if summary["extra"].get("rejected_by_recorder", 0) == 0:
        return "the recorder rejected none of the junk"
    if _steps(summary) != _steps(base["summary"]):
        return f"step figures changed: {_steps(summary)} vs {_steps(base['summary'])}"
    return None


def forged_data(ep: str, grid: str) -> int:
    root = f"adn/{grid}/"
    seq = 10**9
    return put_all(ep, [
        (root + "cpfc/p_y", envelope("p_y", "cpfc", seq, AT_NS, p_y=1.0, p_ref_w=1e6, kp=5e-8,
                                     ki=2e-7, entry=1)),
        (root + "der/SGen2/state", envelope("der_state", "der/SGen2", seq, AT_NS, p_w=1e7,
                                            setpoint_w=1e7, mode="control")),
        (root + "measurement/p_ip", envelope("p_ip", "measurement", seq, AT_NS, p_ip_w=5e7)),
        (root + "availability/si", envelope("si", "availability", seq, AT_NS,
                                            si={"SGen1": False, "SGen2": False})),
        (root + "faults", envelope("fault", "up", seq, AT_NS, fault_id=1, kind="ict_outage",
                                   start_ns=AT_NS, end_ns=AT_NS + 10**10)),
        (root + "control/fault", envelope("fault_request", "operator", seq, AT_NS,
                                          request_id="rogue", kind="ict_outage", at_ns=None,
                                          for_ns=None))])


def bus_forged(ctx: Ctx) -> str | None:
    """Open profile: valid forged messages with the right sender ids (docs/deployment.md: the
    recorder rejects those ahead of the clock; the run completes)."""
    res, summary, _ = bus_run(ctx, forged_data)
    problem = run_problem(res, summary)
    if problem:
        return problem
    if _ended(summary) != "finished":
        return f"ended {_ended(summary)!r}"
    if summary["extra"].get("rejected_by_recorder", 0) < 3:
        return (f"the recorder took forged messages as genuine (rejected "
                f"{summary['extra'].get('rejected_by_recorder', 0)} of 6)")
    return None


def bus_forged_stop(ctx: Ctx) -> str | None:
    """Open profile: a forged clock/stop ends the run; it must never say 'finished'."""
    stop = lambda ep, grid: put_all(ep, [(f"adn/{grid}/clock/stop", envelope(  # noqa: E731
        "clock_stop", "up", 10**9, AT_NS, reason="rogue"))])
    res, summary, _ = bus_run(ctx, stop)
    if res.killed:
        return res.killed
    problem = stderr_problem(res.err, 0)
    if problem:
        return problem
    if summary is None:
        return f"no summary JSON (exit {res.rc})"
    ended = _ended(summary)
    if ended == "finished" or res.rc == 0:
        return f"exit {res.rc}, ended {ended!r} after a forged stop"
    return None


def bus_forged_grant(ctx: Ctx) -> str | None:
    """Open profile: a grant to 10^15 ns for the CPFC; docs: the clock stalls and the run is
    stopped (here after --stall-timeout 10) - cleanly, never 'finished' short of the end."""
    grant = lambda ep, grid: put_all(ep, [(f"adn/{grid}/clock/grant/cpfc", envelope(  # noqa: E731
        "clock_grant", "up", 10**9, 10**9, until_ns=10**15, expect=0))])
    res, summary, _ = bus_run(ctx, grant, "--stall-timeout", "10")
    if res.killed:
        return res.killed
    problem = stderr_problem(res.err, 0)
    if problem:
        return problem
    if summary is None:
        return f"no summary JSON (exit {res.rc})"
    if _ended(summary) == "finished" and summary.get("sim_time_s", 0) < 200 - 1e-6:
        return f"ended 'finished' at {summary.get('sim_time_s')} s of 200 s"
    return None


def bus_newlines(ctx: Ctx) -> str | None:
    """One 512 KiB payload of newlines on a DER's own key: counted as one message, the
    recording does not grow by megabytes."""
    base = _baseline(ctx)
    res, summary, out = bus_run(ctx, lambda ep, grid: put_all(
        ep, [(f"adn/{grid}/der/SGen1/state", b"\n" * (512 * 1024))]))
    problem = run_problem(res, summary)
    if problem:
        return problem
    extra = summary["extra"]
    rejects = extra.get("rejected_by_recorder", 0) + extra.get("rejected_by_agents", 0)
    growth = (out.stat().st_size - base["size"]) / 2**20
    if rejects > 10 or growth > 1.0:
        return f"{rejects} rejects counted, recording {growth:+.1f} MiB"
    return None


class PYFollower:
    """A Zenoh callback on ``cpfc/p_y``: the latest send time seen (``seen_ns``), and
    ``reached`` set once it is at least ``at_ns``."""

    def __init__(self, at_ns: float) -> None:
        self.at_ns, self.seen_ns, self.reached = at_ns, 0, threading.Event()

    def __call__(self, sample) -> None:
        try:
            t = json.loads(sample.payload.to_bytes().split(b"\n")[-1])["t_send_ns"]
        except (ValueError, KeyError):
            return
        self.seen_ns = max(self.seen_ns, t)
        if self.seen_ns >= self.at_ns:
            self.reached.set()


def stolen_key(ep: str, grid: str, certs: Path, proc_notes: dict) -> int:
    """With der/SGen2's certificate: from 20 s on, 16 states of 10 MW and 16 heartbeats
    on SGen2's own keys (seq from 10^9, sent 5 s ahead), two forged clock reports."""
    import zenoh
    root = f"adn/{grid}/"
    p_y = PYFollower(20 * 10**9)
    sent = 0
    with zenoh_session(ep, certs, "der/SGen2") as session:
        subscriber = session.declare_subscriber(root + "cpfc/p_y", p_y)
        if not p_y.reached.wait(90):
            raise RuntimeError("the run did not reach 20 s (as seen by der/SGen2)")
        at = p_y.seen_ns + 5 * 10**9
        for i in range(16):
            for key, body in ((root + "der/SGen2/state", envelope(
                    "der_state", "der/SGen2", 10**9 + i, at + i, p_w=1e7, setpoint_w=1e7,
                    mode="control")), (root + "der/SGen2/heartbeat", envelope(
                    "heartbeat", "der/SGen2", 10**9 + i, at + i, available=True, mode="control"))):
                session.put(key, body, congestion_control=zenoh.CongestionControl.BLOCK)
                sent += 1
        for i, claimed in enumerate(({root + "der/SGen2/state": [1000, at]}, {})):
            session.put(root + "clock/report/der/SGen2", envelope(
                "clock_report", "der/SGen2", 10**9 + i, p_y.seen_ns, next_ns=None, granted_ns=at,
                received=0, sent=claimed), congestion_control=zenoh.CongestionControl.BLOCK)
            sent += 1
        subscriber.undeclare()
    return sent


def bus_stolen_key(ctx: Ctx) -> str | None:
    """Secure profile, der/SGen2's key stolen: the run completes, SGen2 is isolated, the step
    after it is followed by SGen1 alone (issue 39, deliverable 1)."""
    changes = {"scenario": {"duration_s": 300, "p_ref_steps": [{"t_s": 200, "delta_w": 5e5}],
                            "availability": []}}
    config = ctx.dir / "run.yaml"
    doc = ctx.fx.doc("small")
    for section, values in changes.items():
        doc.setdefault(section, {}).update(values)
    config.write_text(yaml.safe_dump(doc, sort_keys=False))
    certs = ctx.dir / "certs"
    made = ctx.run("certs", certs, "--config", config, timeout=60)
    if made.rc != 0:
        raise Skip(f"adnmesh certs failed: {first_line(made.err)}")
    if not (certs / "der" / "SGen2.pem").exists():
        raise Skip("no der/SGen2.pem in the certificate folder (another layout)")
    res, summary, _ = bus_run(ctx, lambda ep, grid: stolen_key(ep, grid, certs, {}), "--secure",
                              "--certs", certs, changes=changes, timeout=300)
    problem = run_problem(res, summary)
    if problem:
        return f"{problem} (ended {_ended(summary)!r})"
    if _ended(summary) != "finished":
        return f"ended {_ended(summary)!r}"
    said = "quarantin" in res.err or any("SGen2" in str(f) for f in summary.get("faults", []))
    if not said:
        return "SGen2 not isolated: no quarantine said, no fault of SGen2"
    steps = [s for s in summary.get("steps", []) if abs(s["t_s"] - 200) < 1e-6]
    if not steps:
        return "the 200 s step is missing from the summary"
    fig = steps[0]["figures"]
    if fig.get("settling_time_s") is None or (fig.get("overshoot_pct") or 0) >= 5:
        return f"the 200 s step degraded: {fig}"
    return None


runner_case("bus", "junk", bus_junk, note="~300 invalid payloads on 18 keys; figures unchanged")
runner_case("bus", "forged-valid-messages-open", bus_forged)
runner_case("bus", "forged-stop-open", bus_forged_stop, quick=True)
runner_case("bus", "forged-grant-open", bus_forged_grant)
runner_case("bus", "512-kib-newlines", bus_newlines, quick=True)
runner_case("bus", "stolen-der-key-secure", bus_stolen_key, quick=True)

# ---- process: SIGKILL of agents by PID mid-run ------------------------------------------------


def sim_time_watch(ep: str, grid: str, at_s: float, on_time: Callable[[], None],
                   stop: threading.Event) -> float:
    """Follow the run's P_Y on the bus; call ``on_time`` once its send time reaches ``at_s``;
    return the sim time it was called at."""
    root = f"adn/{grid}/"
    p_y = PYFollower(at_s * 1e9)
    with zenoh_session(ep) as session:
        subscriber = session.declare_subscriber(root + "cpfc/p_y", p_y)
        while not p_y.reached.wait(0.05):
            if stop.is_set():
                raise RuntimeError(f"the run ended before {at_s} s")
        on_time()
        subscriber.undeclare()
    return p_y.seen_ns / 1e9


def kill_at(ctx: Ctx, agent: str, at_s: float, base: str = "ref", changes=None,
            timeout: float = 420) -> tuple[Result, dict | None, float]:
    """``up`` of the reference case (or the small one); SIGKILL ``agent``'s process by PID
    once the run's sim time reaches ``at_s``; return (result, summary, when)."""
    config = ctx.dir / "run.yaml"
    doc = ctx.fx.doc(base)
    for path, value in (changes or {}).items():
        set_path(doc, path, value)
    config.write_text(yaml.safe_dump(doc, sort_keys=False))
    when = [math.nan]
    ctx.detail = f"{agent} SIGKILLed at ~{at_s:g} s"
    with ctx.fx.up_lock:
        proc = ctx.proc("up", config, "--out", "run.mcap", "--summary-json", "s.json",
                        timeout=timeout).start()
        try:
            if proc.wait_line(r"agents ready", 240) is None:
                proc.kill("")
                res = proc.wait()
                raise RuntimeError(f"up did not get ready: exit {res.rc}: {first_line(res.err)}")
            pid = proc.agents().get(agent)
            if pid is None:
                raise RuntimeError(f"no process of {agent} among up's children: {proc.agents()}")
            ended = threading.Event()
            threading.Thread(target=lambda: (proc.proc.wait(), ended.set()), daemon=True).start()
            when[0] = sim_time_watch(_endpoint(proc), doc["grid"], at_s,
                                     lambda: os.kill(pid, signal.SIGKILL), ended)
        except BaseException:
            proc.kill("")
            proc.wait()
            raise
        res = proc.wait()
    ctx.detail = f"{agent} SIGKILLed at {when[0]:.1f} s; exit {res.rc}"
    return res, ctx.json("s.json"), when[0]


def lost_fault(summary: dict, agent: str) -> dict | None:
    """The summary's fault naming ``agent`` exactly (as a value), if any."""
    for fault in summary.get("faults", []):
        if f'"{agent}"' in json.dumps(fault):
            return fault
    return None


def step_at(summary: dict, t: float) -> dict | None:
    return next((s for s in summary.get("steps", []) if abs(s["t_s"] - t) < 1e-6), None)


def process_availability(ctx: Ctx) -> str | None:
    """SIGKILL of the availability monitor at ~60 s of the reference run: said as a fault,
    and the 200 s step (after the six WTs left) as undisturbed (1.99 %; 8.1 % when the CPFC
    kept the gains of all 11 DERs)."""
    res, summary, when = kill_at(ctx, "availability", 60)
    problem = run_problem(res, summary, codes=(0, 1))
    if problem:
        return problem
    reasons = []
    if lost_fault(summary, "availability") is None:
        reasons.append("the monitor's death is not in the summary's faults")
    step = step_at(summary, 200)
    if step is None:
        reasons.append("no 200 s step")
    elif (step["figures"].get("overshoot_pct") or 0) > 3:
        reasons.append(f"200 s step overshoots {step['figures']['overshoot_pct']:.1f} %")
    return "; ".join(reasons) + f" (killed at {when:.1f} s)" if reasons else None


def process_cpfc(ctx: Ctx) -> str | None:
    """SIGKILL of the CPFC at ~150 s: the 200 s and 420 s steps must be accounted for (not
    executed, and why), the death a fault of the summary."""
    res, summary, when = kill_at(ctx, "cpfc", 150)
    problem = run_problem(res, summary, codes=(0, 1))
    if problem:
        return problem
    reasons = []
    if lost_fault(summary, "cpfc") is None:
        reasons.append("the CPFC's death is not in the summary's faults")
    listed = {round(s["t_s"]): s for s in summary.get("scenario_steps", [])}
    for t in (200, 420):
        said = listed.get(t)
        if step_at(summary, t) is None and (said is None or not said.get("reason")):
            reasons.append(f"the {t} s step vanished without a word")
    return "; ".join(reasons) + f" (killed at {when:.1f} s)" if reasons else None


def process_der(ctx: Ctx) -> str | None:
    """SIGKILL of SGen1 at ~60 s: said as a fault; the 200 s and 420 s steps as undisturbed
    (before: 16.1 % overshoot; 420 s not settled, -165 kW)."""
    res, summary, when = kill_at(ctx, "der/SGen1", 60)
    problem = run_problem(res, summary, codes=(0, 1))
    if problem:
        return problem
    reasons = []
    if lost_fault(summary, "der/SGen1") is None:
        reasons.append("SGen1's death is not in the summary's faults")
    for t in (200, 420):
        step = step_at(summary, t)
        if step is None:
            reasons.append(f"no {t} s step")
            continue
        fig = step["figures"]
        if fig.get("settling_time_s") is None or (fig.get("overshoot_pct") or 0) > 3 \
                or abs(step.get("steady_error_w") or 0) > 1e4:
            reasons.append(f"{t} s step: overshoot {fig.get('overshoot_pct') or 0:.1f} %, "
                           f"settling {fig.get('settling_time_s')}, steady error "
                           f"{(step.get('steady_error_w') or 0) / 1e3:.0f} kW")
    return "; ".join(reasons) + f" (killed at {when:.1f} s)" if reasons else None


def process_measurement_small(ctx: Ctx) -> str | None:
    """SIGKILL of the measurement at ~30 s of a 60 s small run: the run goes on to the end,
    the death said."""
    res, summary, when = kill_at(ctx, "measurement", 30, base="small",
                                 changes={"scenario.duration_s": 60}, timeout=180)
    problem = run_problem(res, summary, codes=(0, 1))
    if problem:
        return problem
    if summary.get("sim_time_s", 0) < 60 - 1e-6:
        return f"the run stopped at {summary.get('sim_time_s')} s of 60 s"
    if lost_fault(summary, "measurement") is None:
        return "the measurement's death is not in the summary's faults"
    return None


def signal_up(ctx: Ctx, sig: int, codes: tuple, want_summary: bool) -> str | None:
    config = ctx.dir / "run.yaml"
    config.write_text(cfg({"scenario.duration_s": 3600})(ctx.fx))
    with ctx.fx.up_lock:
        proc = ctx.proc("up", config, "--out", "run.mcap", "--summary-json", "s.json",
                        timeout=120).start()
        if proc.wait_line(r"agents ready", 120) is None:
            proc.kill("")
            res = proc.wait()
            return f"up did not get ready: exit {res.rc}: {first_line(res.err)}"
        agents = dict(proc.agents())
        time.sleep(3)
        proc.signal(sig)
        res = proc.wait()
    if res.killed:
        return res.killed
    alive = [a for a, pid in agents.items() if _alive(pid)]
    if alive or res.leftover:
        return f"left running after up: {alive or res.leftover}"
    if sig == signal.SIGKILL:
        return None
    problem = stderr_problem(res.err, 0)
    if problem:
        return problem
    if res.rc not in codes:
        return f"exit {res.rc}, expected {sorted(codes)}"
    if want_summary and ctx.json("s.json") is None:
        return "no summary JSON after the signal"
    return None


runner_case("process", "sigkill-availability-at-60s", process_availability, timeout=900)
runner_case("process", "sigkill-cpfc-at-150s", process_cpfc, timeout=900)
runner_case("process", "sigkill-der-at-60s", process_der, timeout=900)
runner_case("process", "sigkill-measurement-small", process_measurement_small)
runner_case("process", "sigterm-up", lambda ctx: signal_up(ctx, signal.SIGTERM, (143,), True),
            note="docs: exit 143, summary of the time reached")
runner_case("process", "sigint-up", lambda ctx: signal_up(ctx, signal.SIGINT, (130,), True),
            note="docs: exit 130")
runner_case("process", "sigkill-up", lambda ctx: signal_up(ctx, signal.SIGKILL, (), False),
            note="docs: every agent goes with it")

# ---- resources: a full disk, up's memory over a long run --------------------------------------


def disk_full(ctx: Ctx) -> str | None:
    """--out on a 1 MiB file system (the recording needs ~2.5 MB): one line, the run goes on
    or stops by rule, the summary and its JSON written, the partial file readable."""
    full = ctx.fx["full"]
    config = ctx.dir / "run.yaml"
    config.write_text(cfg({"scenario.duration_s": 120})(ctx.fx))
    out = Path(full) / "run.mcap"
    res = ctx.run("up", config, "--out", out, "--summary-json", "s.json", timeout=240)
    if res.killed:
        return res.killed
    problem = stderr_problem(res.err, 0)
    if problem:
        return problem
    if res.rc not in (0, 1, 2):
        return f"exit {res.rc}"
    if res.rc == 2:          # refused before it started: the file system was full from the start
        return None
    if ctx.json("s.json") is None:
        return f"no summary JSON (exit {res.rc}: {first_line(res.err)})"
    if not re.search(r"space|disk|full", res.err, re.I):
        return "the full disk is not said"
    if out.exists():
        read = ctx.run("inspect", out, "--recover-to", ctx.dir / "recovered.mcap", timeout=120)
        if read.killed or stderr_problem(read.err, read.rc) or read.rc not in (0, 1):
            return f"the partial recording is not readable: exit {read.rc}: {first_line(read.err)}"
    return None


def memory_growth(ctx: Ctx) -> str | None:
    """up's RSS over a 3,600 s run of the small case: at the end within 10 % of its RSS
    after start-up (issue 39: 317 -> 653 MB over the reference run)."""
    duration = ctx.fx.soak_s
    config = ctx.dir / "run.yaml"
    config.write_text(cfg({"scenario.duration_s": duration})(ctx.fx))
    with ctx.fx.up_lock:
        proc = ctx.proc("up", config, "--out", "run.mcap", timeout=1200, sample_rss=True,
                        mem_mb=4000).start()
        ready = proc.wait_line(r"agents ready", 120)
        t_ready = time.monotonic() - proc.t0
        res = proc.wait()
    problem = run_problem(res, {}, codes=(0,))
    if problem:
        return problem
    if ready is None:
        return "never ready"
    after = [mb for t, mb in res.rss if t >= t_ready + 3]
    if len(after) < 4:
        return f"too short to measure ({len(after)} samples)"
    start, end = after[0], max(after[-3:])
    ctx.detail = f"up's RSS {start:.0f} -> {end:.0f} MB over {duration} s of sim time"
    if end > 1.10 * start:
        return f"up grew {start:.0f} -> {end:.0f} MB over {duration} s ({(end / start - 1) * 100:.0f} %)"
    return None


runner_case("resources", "disk-full-recording", disk_full, quick=True, timeout=300)
runner_case("resources", "memory-over-long-run", memory_growth, timeout=1200)


# ---------------------------------------------------------------------------------------------
# running the cases

@dataclass
class Outcome:
    name: str
    cls: str
    status: str           # pass, fail, skip
    reason: str = ""
    rc: int | None = None
    elapsed: float = 0.0
    detail: str = ""


def prepare(case_: Case, ctx: Ctx) -> list[str]:
    for name, content in case_.files.items():
        path = ctx.dir / name
        if content is FIFO:
            os.mkfifo(path)
        elif content is DIR:
            path.mkdir()
        else:
            value = content(ctx.fx) if callable(content) else content
            if isinstance(value, bytes):
                path.write_bytes(value)
            else:
                path.write_text(value)
        if name == "u.yaml":
            path.chmod(0)
    return [re.sub(r"\{(\w+)\}", lambda m: str(ctx.fx[m.group(1)]), a) for a in case_.argv]


def evaluate(case_: Case, res: Result, ctx: Ctx) -> str | None:
    if res.stopped:                  # the answer the case waited for came: the probe ended it
        return case_.check(res, ctx) if case_.check else None
    if res.killed:
        return res.killed
    if traceback_in(res.err):
        return f"exit {res.rc}, " + traceback_in(res.err)
    if res.rc not in case_.codes:
        what = first_line(res.err) if res.rc != 0 else "accepted (exit 0)"
        return f"exit {res.rc} (expected {'/'.join(map(str, sorted(case_.codes)))}): {what}"
    problem = stderr_problem(res.err, res.rc, res.out)
    if problem:
        return problem
    if case_.argv and case_.argv[0] == "up" and res.rc == 2 and re.search(
            r"started \d+ agents", res.err):
        return "refused only after the agents started"
    if res.leftover:
        return f"{len(res.leftover)} process(es) left running"
    if case_.check:
        return case_.check(res, ctx)
    return None


def run_case(case_: Case, fx: Fixtures, root: Path) -> Outcome:
    folder = root / "cases" / case_.name.replace("/", "__")
    folder.mkdir(parents=True)
    ctx = Ctx(folder, fx, case_)
    t0 = time.monotonic()
    try:
        if case_.skip and case_.skip():
            raise Skip(case_.skip())
        if case_.runner is not None:
            reason = case_.runner(ctx)
            return Outcome(case_.name, case_.cls, "fail" if reason else "pass", reason or "",
                           None, time.monotonic() - t0, ctx.detail)
        argv = prepare(case_, ctx)
        env = {**fx.target.env, **case_.env}
        proc = Proc(fx.target.argv(*argv), folder, env, case_.timeout, case_.mem_mb,
                    case_.max_children, case_.stop_when)
        if case_.runs_up and not case_.needs_live_run:
            with fx.up_lock:
                res = proc.start().wait()
        else:
            res = proc.start().wait()
        (folder / "probe.stdout").write_text(res.out)
        (folder / "probe.stderr").write_text(res.err)
        reason = evaluate(case_, res, ctx)
        return Outcome(case_.name, case_.cls, "fail" if reason else "pass", reason or "",
                       res.rc, res.elapsed)
    except Skip as exc:
        return Outcome(case_.name, case_.cls, "skip", str(exc), None, time.monotonic() - t0)
    except Exception as exc:         # noqa: BLE001 - the probe's own trouble with a case
        return Outcome(case_.name, case_.cls, "fail", f"probe: {type(exc).__name__}: {exc}",
                       None, time.monotonic() - t0)
    finally:
        for path in folder.rglob("*"):       # the case's FIFOs and locked files go too
            try:
                if path.is_dir():
                    path.chmod(0o755)
            except OSError:
                pass


def select(classes: list[str], quick: bool, only: str | None) -> list[Case]:
    chosen = [c for c in CASES if c.cls in classes and (not quick or c.quick)]
    if only:
        chosen = [c for c in chosen if re.search(only, c.name)]
    return chosen


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--adnmesh", default=None, help="the build's command prefix, e.g. "
                        "'adnmesh' or '/path/python -m adnmesh' (default: this interpreter "
                        "-m adnmesh)")
    parser.add_argument("--tree", type=Path, default=None,
                        help="the build's source tree: its configs are used and it goes on "
                        "PYTHONPATH (default: this script's repository, no PYTHONPATH)")
    parser.add_argument("--pythonpath", default=None, help="PYTHONPATH for the build "
                        "(default: --tree if given)")
    parser.add_argument("--classes", default=",".join(CLASSES),
                        help=f"comma-separated, of {','.join(CLASSES)} (default: all)")
    parser.add_argument("--quick", action="store_true",
                        help="only the issue's own cases, no long runs (~3 min)")
    parser.add_argument("--only", default=None, help="regex on case names")
    parser.add_argument("--jobs", type=int, default=2,
                        help="cases run at once that start no adnmesh up (default 2)")
    parser.add_argument("--soak-s", type=int, default=SOAK_S,
                        help=f"scenario of the memory case, s (default {SOAK_S})")
    parser.add_argument("--json", type=Path, default=None, help="also write the report here")
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder")
    parser.add_argument("--list", action="store_true", help="list the cases and exit")
    args = parser.parse_args(argv)

    classes = [c.strip() for c in args.classes.split(",") if c.strip()]
    unknown = sorted(set(classes) - set(CLASSES))
    if unknown:
        parser.error(f"unknown class(es) {unknown}; known: {','.join(CLASSES)}")
    cases = select(classes, args.quick, args.only)
    if args.list:
        for c in cases:
            what = (" ".join(c.argv) or "(no arguments)") if c.runner is None else (
                c.runner.__doc__ or c.note or c.runner.__name__).strip().split("\n")[0]
            print(f"{c.name:52s} {'Q' if c.quick else ' '} {what[:110]}")
        print(f"{len(cases)} cases")
        return 0

    tree = (args.tree or REPO).resolve()
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    pythonpath = args.pythonpath or (str(tree) if args.tree else None)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    prefix = shlex.split(args.adnmesh) if args.adnmesh else [sys.executable, "-m", "adnmesh"]
    target = Target(prefix, env, tree)

    root = Path(tempfile.mkdtemp(prefix="adnmesh-probe-"))
    # the grid cache: the probe's own (a copy of the user's, read only), so that no case
    # writes into the shared one
    cache = root / "grid-cache"
    cache.mkdir()
    shared = Path(os.environ.get("ADNMESH_CACHE_DIR") or Path(
        os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "adnmesh")
    for path in (shared.glob("grid-*") if shared.is_dir() else ()):
        shutil.copy2(path, cache / path.name)
    env["ADNMESH_CACHE_DIR"] = str(cache)
    lock = threading.Lock()

    def log(text: str) -> None:
        with lock:
            print(text, flush=True)

    fx = Fixtures(target, root, log)
    fx.soak_s = args.soak_s
    log(f"adnmesh probe: {len(cases)} cases of {','.join(classes)}"
        f"{' (quick)' if args.quick else ''} against {target.describe()}; configs from {tree}")
    outcomes: list[Outcome] = []
    t_start = time.monotonic()

    def one(c: Case) -> None:
        o = run_case(c, fx, root)
        outcomes.append(o)
        tag = {"pass": "pass", "fail": "FAIL", "skip": "skip"}[o.status]
        said = "; ".join(x for x in (o.reason, o.detail) if x)
        log(f"  {tag}  {o.name} ({o.elapsed:.1f} s){': ' + said if said else ''}")

    try:
        light = [c for c in cases if not c.runs_up and not c.needs_live_run]
        heavy = [c for c in cases if c.runs_up and not c.needs_live_run]
        live = [c for c in cases if c.needs_live_run]
        with ThreadPoolExecutor(max(1, args.jobs)) as pool:
            list(pool.map(one, light))
        for c in heavy:
            one(c)
        for c in live:
            one(c)
    except KeyboardInterrupt:
        log("interrupted: reporting what ran")
    finally:
        fx.teardown()
        if args.keep:
            log(f"kept {root}")
        else:
            for path in root.rglob("*"):
                try:
                    if path.is_dir() and not path.is_symlink():
                        path.chmod(0o755)
                except OSError:
                    pass
            shutil.rmtree(root, ignore_errors=True)

    report(outcomes, classes, target, args, time.monotonic() - t_start)
    return 0


def report(outcomes: list[Outcome], classes, target: Target, args, wall: float) -> None:
    order = {c.name: i for i, c in enumerate(CASES)}
    outcomes.sort(key=lambda o: order.get(o.name, 0))
    print()
    print(f"{'class':10s} {'ran':>5s} {'passed':>7s} {'failed':>7s} {'skipped':>8s}")
    counts = {}
    for cls in classes:
        mine = [o for o in outcomes if o.cls == cls]
        ran = [o for o in mine if o.status != "skip"]
        counts[cls] = {"ran": len(ran), "passed": sum(o.status == "pass" for o in ran),
                       "failed": sum(o.status == "fail" for o in ran),
                       "skipped": len(mine) - len(ran)}
        k = counts[cls]
        print(f"{cls:10s} {k['ran']:5d} {k['passed']:7d} {k['failed']:7d} {k['skipped']:8d}")
    total = {key: sum(k[key] for k in counts.values()) for key in ("ran", "passed", "failed",
                                                                   "skipped")}
    print(f"{'total':10s} {total['ran']:5d} {total['passed']:7d} {total['failed']:7d} "
          f"{total['skipped']:8d}   ({wall / 60:.1f} min)")
    failed = [o for o in outcomes if o.status == "fail"]
    if failed:
        print("\nfailed:")
        for o in failed:
            print(f"  {o.name}: {o.reason}")
    skipped = [o for o in outcomes if o.status == "skip"]
    if skipped:
        print("\nskipped:")
        for o in skipped:
            print(f"  {o.name}: {o.reason}")
    if args.json:
        args.json.write_text(json.dumps({
            "target": target.describe(), "tree": str(target.tree), "quick": args.quick,
            "wall_s": round(wall, 1), "classes": counts, "total": total,
            "cases": [{"name": o.name, "class": o.cls, "status": o.status, "reason": o.reason,
                       "rc": o.rc, "elapsed_s": round(o.elapsed, 2), "detail": o.detail}
                      for o in outcomes]},
            indent=1))
        print(f"\nreport: {args.json}")


if __name__ == "__main__":
    sys.exit(main())
