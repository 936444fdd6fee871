"""A program for the fork server's tests (``tests/test_forkserver.py``): forked as an agent
would be, ``main(argv)`` does what ``argv`` says and says what it found in a JSON file. Run as
``python -m fork_probe CONFIG REPLY_FD`` it is a fork server that refuses every fork (as one
whose ``fork()`` fails for want of memory or processes)."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path


def main(argv: list[str]) -> int:
    action, *rest = argv
    if action == "exit":
        return int(rest[0])
    if action == "raise":
        raise RuntimeError("the probe raises")
    if action == "wait":                # until killed (bounded: a test that forgets it)
        time.sleep(60)
        return 0
    if action == "pool":                # pool OUT: a spawned worker, as the CPFC's retune
        from concurrent.futures import ProcessPoolExecutor
        from multiprocessing import get_context
        with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
            Path(rest[0]).write_text(str(pool.submit(pow, 2, 10).result(timeout=60)))
        return 0
    if action == "tell":                # tell OUT CONFIG: what the child looks like
        out, config = rest
        from adnmesh.runtime.process import _PRELOADED, load_config_or_exit
        preloaded = _PRELOADED.get(os.path.abspath(config))
        Path(out).write_text(json.dumps({
            "pid": os.getpid(), "ppid": os.getppid(), "sid": os.getsid(0),
            "argv": sys.argv, "env": dict(os.environ),
            "comm": Path("/proc/self/comm").read_text().strip(),
            "stdin": os.readlink("/proc/self/fd/0"),
            "config_preloaded": preloaded is not None
            and load_config_or_exit(config) is preloaded[1]}))
        return 0
    raise SystemExit(f"fork_probe: unknown action {action!r}")


if __name__ == "__main__":
    reply = int(sys.argv[2])
    os.write(reply, b"ready\n")
    for _ in sys.stdin:
        os.write(reply, b"refused OSError: [Errno 11] Resource temporarily unavailable\n")
