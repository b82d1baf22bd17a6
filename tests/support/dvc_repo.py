"""Helpers of the tests that run the real DVC pipeline in a temporary git + DVC copy of the
repository: `make_repo` builds it from a params dict, `run` runs a command there (failing the
test with its output), `ran` reads which stages `dvc repro` executed."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.params.plan import write_plan
from pipeline.params.planned import with_tracked_env
from support.tiny_params import save_params

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
DVC = str(BIN / "dvc")


def run(cmd: list[str], cwd: Path) -> str:
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "PYTHONPATH": str(ROOT)}
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    assert r.returncode == 0, f"{' '.join(cmd)} failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r.stdout + r.stderr


def ran(output: str) -> set[str]:
    """Names of the stages `dvc repro` actually executed."""
    return {m.split("@")[0] for m in re.findall(r"Running stage '([^']+)'", output)}


def make_repo(root: Path, params: dict) -> Path:
    """`root` as a git + DVC repository holding pipeline/, stages/, presets/envs.yaml, `params`
    and the dvc.yaml planned for them."""
    if shutil.which("dvc", path=str(BIN)) is None:
        pytest.fail(f"dvc is not installed next to {sys.executable}")
    for name in ("pipeline", "stages"):
        shutil.copytree(ROOT / name, root / name, ignore=shutil.ignore_patterns("__pycache__"))
    (root / "presets").mkdir()  # the score stage's table of reference points (a DVC dep)
    shutil.copy(ROOT / "presets" / "envs.yaml", root / "presets" / "envs.yaml")
    save_params(root / "params.yaml", with_tracked_env(params))  # env.reward_terms: every stage lists it
    # the plan for these params, as `mapex plan` writes it: from the copied catalogue, code deps of the copy
    write_plan(params, root / "params.yaml", root)
    (root / ".gitignore").write_text("/data/\n__pycache__/\nMUJOCO_LOG.TXT\n")
    for cmd in (
        ["git", "init", "-q"],
        ["git", "config", "user.email", "test@example.com"],
        ["git", "config", "user.name", "test"],
        [DVC, "init", "-q"],
        ["git", "add", "-A"],
        ["git", "commit", "-qm", "tiny pipeline"],
    ):
        run(cmd, root)
    return root
