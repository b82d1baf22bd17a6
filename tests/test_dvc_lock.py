"""Two `dvc repro` in one workspace at once: DVC's lock refuses the second, with its message
(docs/manual.md, "Faults a long run meets")."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

# Two `dvc repro` at once: `make test-fast` leaves this file out.
pytestmark = pytest.mark.integration

BIN = Path(sys.executable).parent

DVC_YAML = """stages:
  slow:
    cmd: touch started && sleep 5 && echo done > out.txt
    outs:
      - out.txt
"""


def test_a_second_repro_in_the_same_workspace_is_refused_by_dvcs_lock(tmp_path):
    dvc = shutil.which("dvc", path=str(BIN))
    if dvc is None:
        pytest.fail(f"dvc is not installed next to {sys.executable}")
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}

    def run(*cmd: str) -> subprocess.CompletedProcess:
        return subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)

    (tmp_path / "dvc.yaml").write_text(DVC_YAML)
    for cmd in (
        ["git", "init", "-q"],
        ["git", "config", "user.email", "test@example.com"],
        ["git", "config", "user.name", "test"],
        [dvc, "init", "-q"],
        ["git", "add", "-A"],
        ["git", "commit", "-qm", "one slow stage"],
    ):
        assert run(*cmd).returncode == 0, cmd
    first = subprocess.Popen(
        [dvc, "repro"], cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    deadline = time.time() + 60
    while not (tmp_path / "started").exists() and first.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    assert (tmp_path / "started").exists(), "the first repro never started its stage"
    second = run(dvc, "repro")
    assert first.poll() is None, "the first repro ended before the second was refused"
    said = second.stdout + second.stderr
    assert second.returncode != 0, said
    assert "ERROR" in said and "lock" in said.lower(), said  # "... is busy ... remove '.dvc/tmp/rwlock'" or
    # "Unable to acquire lock", whichever of DVC's locks the first repro holds at that moment
    assert "Running stage" not in said
    output, _ = first.communicate(timeout=120)
    assert first.returncode == 0, output  # the first is not disturbed
    assert (tmp_path / "out.txt").read_text() == "done\n"
