"""Files written atomically, and input files read within bounds.

Written atomically: a reader sees the old file or the new one, never half of one.

:func:`write_atomic` writes to a temporary file beside the target (a hidden name of its own,
so two writers never share one), flushes it to disk (``fsync``) and renames it into place
(``os.replace``); if anything fails on the way, the temporary file is removed and the target
is untouched. The gain tables and their CSV, the grid cache and recordings are written so.

Read within bounds: :func:`read_regular` reads a regular file only (a FIFO would block the
reader until something writes to it, a device such as ``/dev/zero`` never ends) and at most a
given number of bytes, so that a config, a table or a subset list named by mistake is one
error line, not a hang or a reader that fills memory. :func:`check_writable` says before any
work whether an output can be written where the user asks.

Foundation module: the standard library only.
"""
from __future__ import annotations

import errno
import os
import secrets
import stat
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

__all__ = ["FileRefused", "check_writable", "read_regular", "unreadable", "write_atomic"]

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


def unreadable(path: str | Path, exc: OSError, what: str) -> str:
    """Why ``path``, a ``what`` (``"config file"``, ``"recording"``), could not be read, as one
    line: ``PATH: no such file``, ``PATH: is a directory, not a WHAT``, the refusal of
    :func:`read_regular` in words, or ``PATH: cannot read: REASON``."""
    if isinstance(exc, FileNotFoundError):
        return f"{path}: no such file"
    if isinstance(exc, IsADirectoryError):
        return f"{path}: is a directory, not a {what}"
    if isinstance(exc, FileRefused):
        return f"{path}: {exc.strerror}"
    return f"{path}: cannot read: {exc.strerror or exc}"


class FileRefused(OSError):
    """An input that is not a regular file or is larger than its reader takes; ``strerror``
    says which in words (e.g. ``not a regular file (a FIFO)``), ``filename`` names it."""


_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def _mib(n: int) -> str:
    return f"{n / 2**20:g} MiB" if n >= 2**20 else f"{n:,} bytes"


def read_regular(path: str | Path, max_bytes: int) -> bytes:
    """The bytes of the regular file ``path``, which must not exceed ``max_bytes``.

    Opened without blocking (a FIFO is refused before anything waits for a writer) and read
    to at most ``max_bytes + 1`` bytes whatever its size says (``/proc`` files say 0).

    Raises
    ------
    FileRefused
        Not a regular file, or larger than ``max_bytes``.
    OSError
        As :func:`os.open` raises it (FileNotFoundError, PermissionError, ...);
        IsADirectoryError for a directory.
    """
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
                 | getattr(os, "O_BINARY", 0))
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(path))
        if not stat.S_ISREG(mode):
            kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
            raise FileRefused(errno.EINVAL, f"not a regular file ({kind})", str(path))
        chunks, size = [], 0
        while size <= max_bytes:
            chunk = os.read(fd, min(1 << 20, max_bytes + 1 - size))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
        if size > max_bytes:
            raise FileRefused(errno.EFBIG, f"larger than {_mib(max_bytes)}",
                              str(path))
        return b"".join(chunks)
    finally:
        os.close(fd)


def check_writable(path: str | Path, directory: bool = False) -> Path:
    """Make sure that ``path`` can be written (its parent folders are created); return it.

    A file (``directory`` False) must not be a directory; a folder (``directory`` True) is
    created and must not be a file. The test writes and removes a hidden empty file where the
    output goes, so it holds for root as well (for whom permission bits do not stop writes) and
    on read-only file systems.

    Raises
    ------
    OSError
        What creating the folder or the test file raised, with ``filename`` set;
        IsADirectoryError (``directory`` False) or NotADirectoryError (True) for the wrong
        kind of thing at ``path``.
    """
    path = Path(path)
    folder = path if directory else path.parent
    if not directory and path.is_dir():
        raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(path))
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:   # a file in the way (mkdir's exist_ok accepts only a folder)
        raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(folder)) \
            from None
    except OSError as exc:
        if exc.filename is None:
            exc.filename = str(folder)
        raise
    try:
        fd, tmp = _new_temporary(folder / (path.name or "out"), 0o600)
    except OSError as exc:
        raise type(exc)(exc.errno, exc.strerror, str(folder)) from None
    os.close(fd)
    tmp.unlink()
    return path
