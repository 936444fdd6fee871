"""Test helper: retune jobs a realtime CPFC's retune process can run (picklable)."""

from __future__ import annotations

import os
import time
from pathlib import Path


def when_told(go: str, entry, words: str = "words") -> tuple:
    """``(entry, words)`` once the file ``go`` exists (at most 60 s), so that a test decides
    when the job is done."""
    deadline = time.monotonic() + 60
    while not Path(go).exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    return entry, words


def dies() -> tuple:
    """A retune process that ends without an answer."""
    os._exit(3)
