"""Fixtures shared by the whole test suite.

- `write_params(directory, overrides)`: writes a params.yaml built from the toy preset TINY
  (tests/support/tiny_params.py: a specialist trains in a few seconds) with `overrides` merged in.
- `tiny_params`: that file, unmodified, in the test's tmp_path.
- `mapex(*args, cwd=...)`: runs the real `mapex` console command in a subprocess and returns
  the CompletedProcess (returncode, stdout, stderr as text).
- `cli(*args)`: invokes the same typer app in this process (no interpreter start-up, which
  costs seconds here); returns a click Result (exit_code, stdout, stderr). Good for checks of
  argument and params handling; use `mapex` where a separate process matters.
- hypothesis runs without its per-example deadline (profile "mapex"); torch runs one thread.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any, Callable

import pytest
import torch
from hypothesis import settings
from support.tiny_params import TINY, merge, save_params

# No per-example deadline: this machine is shared, and a loaded moment would fail an example
# that is merely slow, not wrong.
settings.register_profile("mapex", deadline=None)
settings.load_profile("mapex")

# One torch thread in every test process, as `mapex` runs its stages by default (stages/cli.py,
# MAPEX_TORCH_THREADS=1). Tests that invoke a stage function in process bypass that, and ran on
# torch's default (one thread per core) until an earlier test in the same process happened to
# call the CLI: their thread count depended on the order of files, and on a busy 2-core machine
# the tiny nets run 5-10 times slower on two threads (two of test_pderl.py's tests: 25 s vs 5 s).
torch.set_num_threads(1)

REPO = Path(__file__).resolve().parents[1]


def _write_params(directory: Path, overrides: dict[str, Any] | None = None, name: str = "params.yaml") -> Path:
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / name
    save_params(path, merge(TINY, overrides), sort_keys=False)  # without derived lists
    return path


@pytest.fixture(scope="session")
def write_params() -> Callable[..., Path]:
    """Factory: write_params(directory, overrides=None, name="params.yaml") -> path of the file."""
    return _write_params


@pytest.fixture
def tiny_params(tmp_path: Path) -> Path:
    """A params.yaml holding the tiny preset, in this test's tmp_path."""
    return _write_params(tmp_path)


def _mapex_command() -> list[str]:
    # The console script installed beside this interpreter; `python -m stages.cli` if absent.
    script = Path(sys.executable).with_name("mapex")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "stages.cli"]


def _run_mapex(*args: str | Path, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    env = os.environ.copy()
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    # One torch thread unless the caller chose otherwise: the test machine is small and
    # shared, and runs compared for bitwise equality must use the same thread count.
    env.setdefault("OMP_NUM_THREADS", "1")
    return subprocess.run(
        [*_mapex_command(), *map(str, args)],
        cwd=cwd,  # MuJoCo writes MUJOCO_LOG.TXT into the working directory
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _invoke_cli(*args: str | Path):
    from typer.testing import CliRunner

    from stages.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="session")
def cli() -> Callable[..., Any]:
    """In-process runner: cli("train-specialist", "--objective", 0, ...) -> click Result."""
    return _invoke_cli


@pytest.fixture(scope="session")
def mapex() -> Callable[..., subprocess.CompletedProcess]:
    """Runner: mapex("train-specialist", "--objective", 0, ..., cwd=dir) -> CompletedProcess."""
    return _run_mapex


# The test files that take longest (about 40 s to 3 min each on the 2-core machine), longest
# first, then the longest of the fast tier. `make test` and `make test-fast` run the suite in two
# pytest-xdist workers, each file whole in one worker (--dist loadfile), handed out in collection
# order; starting with these keeps one worker from being left with a long file at the end while
# the other idles.
SLOWEST_FILES = (
    "test_sweep.py",
    "test_dvc_methods.py",
    "test_nobj_pipeline.py",
    "test_import_export.py",
    "test_dvc_pipeline.py",
    "test_train_specialist.py",
    "test_extract_stage.py",
    "test_extract_policy_sets.py",
    "test_extract_inputs.py",
    # the slowest of the fast tier (`make test-fast`, about 10 to 25 s each on one core)
    "test_presets.py",
    "test_morld.py",
    "test_pderl.py",
    "test_batched_specialists.py",
)


def pytest_collection_modifyitems(session, config, items):
    """Run the slowest files first (a stable sort: the order within a file and among the rest is kept)."""
    rank = {name: i for i, name in enumerate(SLOWEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(SLOWEST_FILES)))
