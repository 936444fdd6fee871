"""Atomic file writes (adnmesh.files): whole file or nothing, permissions, no leftovers."""
from __future__ import annotations

import os
import stat

import pytest

from adnmesh.files import write_atomic


def _mode(path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_bytes_text_and_a_writer_make_the_file_in_new_folders(tmp_path) -> None:
    target = tmp_path / "a" / "b" / "out.bin"
    assert write_atomic(target, b"\x00\x01") == target
    assert target.read_bytes() == b"\x00\x01"
    write_atomic(str(target), "zwölf\r\n")                  # UTF-8, newlines as they are
    assert target.read_bytes() == "zwölf\r\n".encode()
    write_atomic(target, lambda fh: fh.write(b"written"))
    assert target.read_bytes() == b"written"
    assert sorted(p.name for p in target.parent.iterdir()) == ["out.bin"]


def test_a_failing_writer_leaves_the_old_file_and_no_temporary(tmp_path) -> None:
    target = tmp_path / "table.json"
    write_atomic(target, "old")

    def half(fh) -> None:
        fh.write(b"new, but only ha")
        raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError, match="interrupted"):
        write_atomic(target, half)
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["table.json"]


def test_permissions_are_those_of_open_unless_kept_to_the_owner(tmp_path) -> None:
    umask = os.umask(0o022)
    try:
        write_atomic(tmp_path / "shared", "x")
        write_atomic(tmp_path / "private", "x", mode=0o600)
    finally:
        os.umask(umask)
    assert _mode(tmp_path / "shared") == 0o644
    assert _mode(tmp_path / "private") == 0o600
