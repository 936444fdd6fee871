"""Where ``adnmesh up --view`` sends the run: a native viewer, the web viewer or a file.

:func:`open_view` makes the Rerun recording stream and, for a viewer, starts the ``rerun``
program shipped with rerun-sdk, bound to 127.0.0.1 (its gRPC server and, with ``web``, its web
viewer's HTTP server), as its own process group so that it stays open after the run; the
stream connects to it over gRPC. ``FILE.rrd`` needs no viewer and no display (headless).
"""

from __future__ import annotations

import os
import subprocess
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from adnmesh.errors import UsageError
from adnmesh.recording.live import LiveView
from adnmesh.recording.rerun_export import APPLICATION_ID, rerun_executable
from adnmesh.runtime.bus import DEFAULT_HOST, free_port

__all__ = ["ViewTarget", "open_view", "parse_view", "viewer_argv"]


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


def _grpc_url(port: int) -> str:
    return f"rerun+http://{DEFAULT_HOST}:{port}/proxy"


def _has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def open_view(target: ViewTarget, run_id: str, log: Callable[[str], None],
              on_events=None) -> LiveView | None:
    """Open the stream of ``target`` and return its started :class:`LiveView` (None: a
    native viewer without a display, said in one line through ``log``)."""
    import rerun as rr

    if target.kind == "native" and not _has_display():
        log("--view: no display for the native Rerun viewer (DISPLAY/WAYLAND_DISPLAY unset); "
            "use --view web or --view FILE.rrd")
        return None
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=run_id)
    viewer = None
    if target.kind == "file":
        target.path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(target.path)
        log(f"live view: streaming to {target.path}")
    else:
        grpc_port, web_port = free_port(), free_port()
        viewer = subprocess.Popen(viewer_argv(target.kind == "web", grpc_port, web_port),
                                  stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL, start_new_session=True)
        rec.connect_grpc(_grpc_url(grpc_port))
        where = "native Rerun viewer"
        if target.kind == "web":
            query = urllib.parse.urlencode({"url": _grpc_url(grpc_port)})
            where = f"web viewer at http://{DEFAULT_HOST}:{web_port}/?{query}"
        log(f"live view: {where} (pid {viewer.pid}; it stays open after the run: "
            f"kill {viewer.pid} to close it)")
    rec.send_recording_name(run_id)
    return LiveView(rec, on_events=on_events,
                    viewer_pid=viewer.pid if viewer is not None else None).start()
