"""Provenance: the git state it records ignores dvc.lock (rewritten by `dvc repro` mid-run)."""

from __future__ import annotations

import subprocess

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
