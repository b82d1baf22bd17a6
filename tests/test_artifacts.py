"""Atomic artifact writes: a failure or a kill at any point leaves the old or the new one whole."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import pipeline.core.artifacts as art
from pipeline.core.artifacts import atomic_path, recover, write_text_atomic


def write_dir(path: Path, tag: str) -> None:
    path.mkdir()
    (path / "a.txt").write_text(f"{tag}-a")
    (path / "sub").mkdir()
    (path / "sub" / "b.txt").write_text(f"{tag}-b")


def read_dir(path: Path) -> tuple[str, str]:
    return (path / "a.txt").read_text(), (path / "sub" / "b.txt").read_text()


def test_file_replaced_whole_and_failure_keeps_the_old(tmp_path):
    dest = tmp_path / "x" / "f.txt"
    write_text_atomic(dest, "one")
    write_text_atomic(dest, "two")
    assert dest.read_text() == "two"
    with pytest.raises(RuntimeError):
        with atomic_path(dest) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert dest.read_text() == "two" and sorted(p.name for p in dest.parent.iterdir()) == ["f.txt"]


def test_directory_replaced_whole_and_failure_keeps_the_old(tmp_path):
    dest = tmp_path / "buf.zarr"
    with atomic_path(dest) as tmp:
        write_dir(tmp, "old")
    with atomic_path(dest) as tmp:
        write_dir(tmp, "new")
    assert read_dir(dest) == ("new-a", "new-b")
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(dest) as tmp:
            write_dir(tmp, "half")
            raise KeyboardInterrupt
    assert read_dir(dest) == ("new-a", "new-b")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["buf.zarr"]


def test_directory_swap_is_one_exchange_where_linux_has_it(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    write_dir(a, "A")
    write_dir(b, "B")
    if not art._exchange(a, b):
        pytest.skip("renameat2 RENAME_EXCHANGE unsupported here (the fallback is tested below)")
    assert read_dir(a) == ("B-a", "B-b") and read_dir(b) == ("A-a", "A-b")


def test_fallback_killed_between_renames_is_recovered(tmp_path, monkeypatch):
    """Without the exchange, a kill after moving the old directory aside and before moving the
    new one in leaves DEST.old whole; the next write (or `recover`) puts it back first."""
    dest = tmp_path / "buf.zarr"
    with atomic_path(dest) as tmp:
        write_dir(tmp, "old")
    monkeypatch.setattr(art, "_exchange", lambda a, b: False)
    real_replace, calls = os.replace, []

    def dying_replace(src, dst):
        calls.append(Path(dst).name)
        if len(calls) == 2:
            raise SystemExit("killed between the renames")
        real_replace(src, dst)

    monkeypatch.setattr(art.os, "replace", dying_replace)
    with pytest.raises(SystemExit):
        with atomic_path(dest) as tmp:
            write_dir(tmp, "new")
    monkeypatch.setattr(art.os, "replace", real_replace)
    assert not dest.exists() and read_dir(tmp_path / "buf.zarr.old") == ("old-a", "old-b")
    recover(dest)
    assert read_dir(dest) == ("old-a", "old-b") and not (tmp_path / "buf.zarr.old").exists()
    with atomic_path(dest) as tmp:  # and the fallback completes when not killed
        write_dir(tmp, "new")
    assert read_dir(dest) == ("new-a", "new-b")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["buf.zarr"]


def test_everything_written_is_fsynced_before_the_rename(tmp_path, monkeypatch):
    synced: list[str] = []
    real = os.fsync
    monkeypatch.setattr(art.os, "fsync", lambda fd: (synced.append(os.readlink(f"/proc/self/fd/{fd}")), real(fd)))
    dest = tmp_path / "d"
    with atomic_path(dest) as tmp:
        write_dir(tmp, "x")
    partial = str(tmp_path / ("d" + art.TMP_SUFFIX))
    assert {partial + "/a.txt", partial + "/sub/b.txt"} <= set(synced)
