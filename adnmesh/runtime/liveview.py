"""Where ``adnmesh up --view`` sends the run: a native viewer, the web viewer or a file.

:func:`open_view` starts, for a viewer, the ``rerun`` program shipped with rerun-sdk, bound to
127.0.0.1 (its gRPC server and, with ``web``, its web viewer's HTTP server), as its own process
group so that it stays open after the run; ``FILE.rrd`` needs no viewer and no display
(headless). The work of the view (decoding the messages by ``replay``'s rules, sending them to
Rerun: :class:`~adnmesh.results.live.LiveView`) runs in a child process of ``up``
(:class:`ViewProcess`), so that it never holds the interpreter lock of the process whose
router and recorder drive the clock: ``up`` only queues what it records and hands it over
through a pipe every :data:`~adnmesh.results.live.VIEW_PERIOD_S`.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import subprocess
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from adnmesh.errors import UsageError
from adnmesh.results.live import VIEW_PERIOD_S, LiveView, RecordQueue
from adnmesh.results.rerun_export import (APPLICATION_ID, grpc_url, rerun_executable,
                                          web_viewer_url)
from adnmesh.runtime.bus import DEFAULT_HOST, free_port

VIEW_NICE = 10
"""How much lower the view's process runs than the run's own (``os.nice`` increment)."""

__all__ = ["ViewProcess", "ViewTarget", "open_view", "parse_view", "viewer_argv"]


@dataclass(frozen=True)
class ViewTarget:
    """What ``--view`` asked for: ``kind`` is ``native``, ``web`` or ``file`` (``path``)."""

    kind: str
    path: Path | None = None


def parse_view(text: str | None) -> ViewTarget | None:
    """``--view`` (``native``), ``--view web`` or ``--view FILE.rrd``; None without it."""
    if text is None:
        return None
    if text in ("native", "web"):
        return ViewTarget(text)
    if text.endswith(".rrd"):
        return ViewTarget("file", Path(text))
    raise UsageError(f"--view: expected 'web', 'native' or FILE.rrd, got {text!r}")


def viewer_argv(web: bool, grpc_port: int, web_port: int) -> list[str]:
    """The command of a viewer bound to 127.0.0.1: native (gRPC server on ``grpc_port``) or
    web (``--serve-web``: gRPC proxy on ``grpc_port``, web viewer on ``web_port``)."""
    argv = [*rerun_executable(), "--bind", DEFAULT_HOST, "--port", str(grpc_port)]
    if web:
        argv += ["--serve-web", "--web-viewer-port", str(web_port)]
    return argv


def _has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class ViewProcess(RecordQueue):
    """The live view in a child process; :meth:`take` queues as :class:`LiveView` does
    (:class:`~adnmesh.results.live.RecordQueue`, thread-safe).

    Parameters
    ----------
    sink : tuple
        ``("file", path)``, ``("grpc", url)`` or ``("none", None)`` (events only).
    run_id : str
        The Rerun recording id and name.
    on_events : callable, optional
        Gets the new events (a list of :class:`~adnmesh.results.rules.Event`), on a thread
        of this process.
    viewer_pid : int, optional
        The viewer process the stream goes to (it outlives the run).
    limits : adnmesh.config.GridLimits, optional
        The run's grid band, drawn beside the grid's extremes.
    """

    def __init__(self, sink: tuple, run_id: str, on_events=None,
                 viewer_pid: int | None = None, period_s: float = VIEW_PERIOD_S,
                 limits=None) -> None:
        super().__init__()
        self.viewer_pid, self.on_events, self.period_s = viewer_pid, on_events, period_s
        self.error: str | None = None
        self.cpu_s = 0.0            # CPU time of the view's process, s (once closed)
        self._stop = threading.Event()
        context = multiprocessing.get_context("spawn")
        self._conn, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(child, sink, run_id,
                                                             on_events is not None, limits),
                                        name="adnmesh-live-view", daemon=True)
        self._process.start()
        child.close()
        self._sender = threading.Thread(target=self._send_loop, daemon=True)
        self._receiver = threading.Thread(target=self._receive_loop, daemon=True)
        self._sender.start()
        self._receiver.start()

    def close(self, timeout_s: float = 120.0) -> None:
        """Hand over what is left, let the child send it and end; wait for it (bounded)."""
        self._stop.set()
        self._sender.join()
        self._hand_over()
        self._send(None)
        self._receiver.join(timeout_s)
        self._process.join(timeout_s if not self._receiver.is_alive() else 1.0)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
            self.error = self.error or "live view: its process did not finish; killed"
        self._conn.close()

    def _hand_over(self) -> None:
        pending = self.taken()
        if pending:
            self._send(pending)

    def _send(self, item) -> None:
        try:
            self._conn.send(item)
        except (BrokenPipeError, OSError):
            self.error = self.error or "live view: its process ended early"

    def _send_loop(self) -> None:
        while not self._stop.wait(self.period_s):
            self._hand_over()

    def _receive_loop(self) -> None:
        while True:
            try:
                kind, value = self._conn.recv()
            except (EOFError, OSError):
                self.error = self.error or "live view: its process ended early"
                return
            if kind == "events" and self.on_events is not None:
                self.on_events(value)
            elif kind == "done":
                error, self.cpu_s = value
                self.error = error or self.error
                return


def _serve(conn, sink: tuple, run_id: str, events: bool, limits=None) -> None:
    """The child process: messages from ``conn`` into a :class:`LiveView`, until None."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)     # up ends it, after the run
    try:
        os.nice(VIEW_NICE)   # the view is best effort: the agents and the clock come first
    except OSError:
        pass
    rec = None
    if sink[0] != "none":
        import rerun as rr

        rec = rr.RecordingStream(APPLICATION_ID, recording_id=run_id)
        if sink[0] == "file":
            rec.save(sink[1])
        else:
            rec.connect_grpc(sink[1])
        rec.send_recording_name(run_id)
    view = LiveView(rec, on_events=(lambda found: conn.send(("events", found)))
                    if events else None, limits=limits)
    try:
        while (pending := conn.recv()) is not None:
            for topic, schema_name, records in pending:
                view.take(topic, schema_name, records)
            view.send_pending()
    finally:
        view.close()
        times = os.times()
        conn.send(("done", (view.error, times.user + times.system)))


def open_view(target: ViewTarget | None, run_id: str, log: Callable[[str], None],
              on_events=None, limits=None) -> ViewProcess | None:
    """Open the view of ``target`` (None: events only, for ``on_events``) and return it
    started (None: a native viewer without a display, said in one line through ``log``).
    ``limits`` (the config's ``grid_model.limits``) is drawn beside the grid's extremes."""
    if target is None:
        return ViewProcess(("none", None), run_id, on_events)
    if target.kind == "native" and not _has_display():
        log("--view: no display for the native Rerun viewer (DISPLAY/WAYLAND_DISPLAY unset); "
            "use --view web or --view FILE.rrd")
        return None
    if target.kind == "file":
        target.path.parent.mkdir(parents=True, exist_ok=True)
        log(f"live view: streaming to {target.path}")
        return ViewProcess(("file", str(target.path)), run_id, on_events, limits=limits)
    grpc_port, web_port = free_port(), free_port()
    viewer = subprocess.Popen(viewer_argv(target.kind == "web", grpc_port, web_port),
                              stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, start_new_session=True)
    where = "native Rerun viewer"
    if target.kind == "web":
        where = f"web viewer: open {web_viewer_url(web_port, grpc_port, DEFAULT_HOST)}"
    log(f"live view: {where} (pid {viewer.pid}; it stays open after the run: "
        f"kill {viewer.pid} to close it)")
    return ViewProcess(("grpc", grpc_url(grpc_port, DEFAULT_HOST)), run_id, on_events,
                       viewer.pid, limits=limits)
