"""Provenance: the git state it records ignores dvc.lock (rewritten by `dvc repro` mid-run); a
stage writes its record to the --provenance file only."""

from __future__ import annotations

import json
import subprocess

import torch

import pipeline.core.provenance as prov


def git(cwd, *args):
    subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True)


def test_git_dirty_ignores_dvc_lock_but_not_code(tmp_path, monkeypatch):
    git(tmp_path, "init", "-q")
    git(tmp_path, "config", "user.email", "t@example.com")
    git(tmp_path, "config", "user.name", "t")
    (tmp_path / "dvc.lock").write_text("a\n")
    (tmp_path / "code.py").write_text("x = 1\n")
    git(tmp_path, "add", "-A")
    git(tmp_path, "commit", "-qm", "init")
    monkeypatch.setattr(prov, "ROOT", tmp_path)

    def state():
        prov._git.cache_clear()
        return prov._git()

    try:
        clean = state()
        assert clean["git_dirty"] is False and len(clean["git_commit"]) == 40
        (tmp_path / "dvc.lock").write_text("b\n")
        assert state()["git_dirty"] is False
        (tmp_path / "code.py").write_text("x = 2\n")
        assert state()["git_dirty"] is True
    finally:
        prov._git.cache_clear()


def test_write_provenance_writes_a_record_only_where_asked(tmp_path):
    prov.write_provenance(None, "score")  # no --provenance: nothing anywhere
    assert list(tmp_path.iterdir()) == []
    path = tmp_path / "provenance" / "score" / "mapex_td3" / "seed0.json"
    prov.write_provenance(path, "score", "cpu")
    record = json.loads(path.read_text())
    assert record["stage"] == "score" and record["device"].startswith("cpu: ")
    assert {"git_commit", "git_dirty", "versions", "python", "torch_threads"} <= set(record)
    assert record["versions"]["torch"] == torch.__version__
    assert [p.name for p in path.parent.iterdir()] == ["seed0.json"]  # written atomically, no .partial left


def test_torch_floor_refuses_the_weights_only_bypass_and_admits_the_makefile_pin():
    """pyproject's torch range starts at 2.6 (CVE-2025-32434: weights_only=True bypassable
    below it) and still admits the build the Makefile installs, so pip installs nothing more."""
    import re
    import tomllib
    from pathlib import Path

    from packaging.requirements import Requirement

    root = Path(__file__).resolve().parents[1]
    deps = tomllib.loads((root / "pyproject.toml").read_text())["project"]["dependencies"]
    (torch_req,) = [Requirement(d) for d in deps if Requirement(d).name == "torch"]
    pin = re.search(r"^TORCH_SPEC \?= torch==(\S+)$", (root / "Makefile").read_text(), re.M).group(1)
    assert torch_req.specifier.contains(pin) and torch_req.specifier.contains(f"{pin}+cpu")
    for old in ("2.3.0", "2.5.1"):
        assert not torch_req.specifier.contains(old), old


def test_every_record_says_what_its_process_cost_and_a_stopwatch_measures_a_block(tmp_path):
    from pipeline.core.cost import Stopwatch, cost_row, cpu_seconds

    before = cpu_seconds()
    with Stopwatch() as sw:
        x = 0
        for i in range(300_000):  # some CPU work
            x += i * i
    assert sw.cpu > 0 and sw.wall > 0 and cpu_seconds() - before >= sw.cpu
    row = cost_row(3, "children", 2, sw, None)
    assert row["iteration"] == 3 and row["eval_cpu_s"] == 0.0 and row["train_cpu_s"] == round(sw.cpu, 4)
    path = tmp_path / "record.json"
    prov.write_provenance(path, "extract", "cpu", "fp32", {"iterations": [row]})
    cost = json.loads(path.read_text())["cost"]
    # the process's seconds since it started: this test process has run a while, imports included
    assert cost["cpu_seconds"] >= sw.cpu and cost["wall_seconds"] > sw.wall
    assert cost["iterations"] == [row]
