"""Atomic artifact writes: a failure, a kill or a full disk at any point leaves the old or the new one whole."""

from __future__ import annotations

import csv
import errno
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import pipeline.core.artifacts as art
from pipeline.core.artifacts import atomic_path, csv_text, disk_full_error, recover, write_text_atomic
from pipeline.core.buffer import load_buffer


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


# --- a full disk --------------------------------------------------------------------------
#
# A child process writes each kind of artifact once, then lowers its file-size limit
# (RLIMIT_FSIZE, with SIGXFSZ ignored so write() fails with EFBIG, as it fails with ENOSPC on a
# full disk or EDQUOT over a quota) and writes each again, bigger than the limit.

DISK_FULL_CHILD = """
import json, resource, signal, sys
import numpy as np, torch
from pipeline.core.artifacts import DiskFull, torch_save_atomic, write_text_atomic
from pipeline.core.buffer import save_buffer
from pipeline.core.resume import Checkpoint

def rows(n, fill):
    return {"obs": np.full((n, 3), fill, np.float32), "action": np.full((n, 2), fill, np.float32),
            "reward": np.full((n, 2), fill, np.float32), "next_obs": np.full((n, 3), fill, np.float32),
            "terminated": np.zeros(n, bool), "truncated": np.zeros(n, bool),
            "episode": np.zeros(n, np.int64), "episode_step": np.zeros(n, np.int32)}

d = sys.argv[1]
attrs = {"obs_dim": 3, "act_dim": 2, "n_objectives": 2}
torch_save_atomic({"x": torch.arange(10)}, f"{d}/a.pt")
write_text_atomic(f"{d}/a.txt", "old")
save_buffer(f"{d}/b.zarr", rows(5, 1.0), attrs)
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (65536, 65536))
noise = np.random.default_rng(0).random((40_000, 3)).astype(np.float32)  # incompressible
writes = {
    "a.pt": lambda: torch_save_atomic({"x": torch.zeros(40_000)}, f"{d}/a.pt"),
    "a.txt": lambda: write_text_atomic(f"{d}/a.txt", "x" * 100_000),
    "b.zarr": lambda: save_buffer(f"{d}/b.zarr", {**rows(40_000, 2.0), "obs": noise}, attrs),
    "new.pt": lambda: Checkpoint(f"{d}/new.pt", "fp", print).save({"x": torch.zeros(40_000)}),
}
said = {}
for name, write in writes.items():
    try:
        write()
        said[name] = None
    except DiskFull as exc:
        said[name] = str(exc)
print(json.dumps(said))
"""


def test_a_full_disk_is_one_line_and_leaves_the_old_artifact_and_no_partial(tmp_path):
    root = Path(__file__).resolve().parents[1]
    r = subprocess.run(
        [sys.executable, "-c", DISK_FULL_CHILD, str(tmp_path)],
        env={**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    said = json.loads(r.stdout.splitlines()[-1])
    for name in ("a.pt", "a.txt", "b.zarr", "new.pt"):
        line = said[name]
        assert line is not None, f"{name}: written past the file-size limit"
        assert line.startswith(f"{tmp_path / name}: cannot be written: the disk is full or a quota")
        assert "\n" not in line and "File too large" in line
    assert said["a.pt"].endswith("the previous a.pt is left intact; free some space and rerun")
    assert said["new.pt"].endswith("nothing was left behind; free some space and rerun")
    # the old artifacts whole, no temporary left
    assert torch.equal(torch.load(tmp_path / "a.pt", weights_only=True)["x"], torch.arange(10))
    assert (tmp_path / "a.txt").read_text() == "old"
    data, _ = load_buffer(tmp_path / "b.zarr")
    assert len(data["obs"]) == 5 and np.all(data["obs"] == 1.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pt", "a.txt", "b.zarr"]


def test_disk_full_is_found_behind_a_wrapping_error():
    full = OSError(errno.ENOSPC, "No space left on device")
    try:
        try:
            raise full
        except OSError:
            raise RuntimeError("PytorchStreamWriter failed writing file data/0")  # as torch does
    except RuntimeError as exc:
        assert disk_full_error(exc) is full
    assert disk_full_error(OSError(errno.EDQUOT, "Disk quota exceeded")) is not None
    assert disk_full_error(OSError(errno.EACCES, "Permission denied")) is None
    assert disk_full_error(RuntimeError("other")) is None


def test_csv_text_header_rows_quoting_and_newline_line_ends():
    text = csv_text(["id", "name", "x"], [[0, "a,b", 1.5], (1, 'say "hi"', None), {"x": "0.25", "id": 2, "name": "c"}])
    assert text == 'id,name,x\n0,"a,b",1.5\n1,"say ""hi""",\n2,c,0.25\n'
    assert "\r" not in text
    assert list(csv.reader(io.StringIO(text))) == [
        ["id", "name", "x"],
        ["0", "a,b", "1.5"],
        ["1", 'say "hi"', ""],
        ["2", "c", "0.25"],
    ]
    assert csv_text(("a", "b"), []) == "a,b\n"


def test_csv_text_refuses_a_mapping_row_whose_keys_differ_from_the_header():
    with pytest.raises(ValueError, match=r"keys \['a', 'c'\] differ from the header \['a', 'b'\]"):
        csv_text(["a", "b"], [{"a": 1, "c": 2}])
    with pytest.raises(ValueError, match="differ from the header"):
        csv_text(["a", "b"], [{"a": 1}])
