"""Files written atomically: a reader sees the old file or the new one, never half of one.

:func:`write_atomic` writes to a temporary file beside the target (a hidden name of its own,
so two writers never share one), flushes it to disk (``fsync``) and renames it into place
(``os.replace``); if anything fails on the way, the temporary file is removed and the target
is untouched. The gain tables and their CSV, the grid cache and recordings are written so.

Foundation module: the standard library only.
"""
from __future__ import annotations

import os
import secrets
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

__all__ = ["write_atomic"]

#: file mode of a new file before the umask (as :func:`open` creates one)
DEFAULT_MODE = 0o666


def write_atomic(path: str | Path, content: bytes | str | Callable[[BinaryIO], object],
                 mode: int = DEFAULT_MODE) -> Path:
    """Write ``path`` atomically and durably; return it as a :class:`~pathlib.Path`.

    Parameters
    ----------
    path : str or Path
        The target; missing parent folders are created.
    content : bytes, str or callable
        The file's bytes, a text (written as UTF-8, newlines as they are), or a function
        that writes them to the binary file object it is given.
    mode : int
        Permissions of the new file before the umask: the default is that of :func:`open`
        (0o666, so 0o644 with the usual umask); 0o600 keeps it to the owner (as
        :func:`tempfile.mkstemp` does).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _new_temporary(path, mode)
    try:
        with os.fdopen(fd, "wb") as fh:
            if callable(content):
                content(fh)
            else:
                fh.write(content.encode("utf-8") if isinstance(content, str) else content)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _new_temporary(path: Path, mode: int) -> tuple[int, Path]:
    """A new file ``.<name>.<random>.tmp`` beside ``path``, opened for writing: (fd, path)."""
    flags = (os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
             | getattr(os, "O_CLOEXEC", 0))
    for _ in range(100):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
        try:
            return os.open(tmp, flags, mode), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary file name beside {path}")
