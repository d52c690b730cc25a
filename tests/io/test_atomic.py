"""Atomic writes: the whole file or nothing, and no temporary left behind."""

from __future__ import annotations

import pytest

from pelvicnav.io.atomic import write_bytes


def test_write_bytes_replaces_whole_and_leaves_nothing_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "out.bin"
    write_bytes(target, b"first")
    write_bytes(target, b"second")
    assert target.read_bytes() == b"second"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bin"]

    def fail(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr("pelvicnav.io.atomic.os.replace", fail)
    with pytest.raises(OSError, match="disk full"):
        write_bytes(target, b"third")
    assert target.read_bytes() == b"second"  # the old file stands, no temporary is left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bin"]
