"""What produced an artifact: code version, library versions, device and thread count.

Recorded in every artifact's metadata and shown in the report, so a reader can tell whether
two results are comparable. Bitwise reproducibility holds only between runs whose provenance
agrees on everything here except `git_dirty` noise (same machine type, thread count, library
versions and device); see the README, "Reproducibility".
"""

from __future__ import annotations

import functools
import platform
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[2]
LIBRARIES = ("mapex", "torch", "numpy", "mujoco", "gymnasium", "mo-gymnasium", "zarr")


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


@functools.lru_cache(maxsize=None)
def _git() -> dict[str, Any]:
    """Commit of the project checkout and whether tracked files differ from it (None outside git).

    dvc.lock is left out: `dvc repro` rewrites it after every stage, so it would mark every
    later stage of a clean checkout dirty. Params are recorded in the artifacts themselves.
    """
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        dirty = (
            subprocess.run(
                ["git", "status", "--porcelain", "--untracked-files=no", "--", ".", ":!dvc.lock"],
                cwd=ROOT,
                capture_output=True,
                text=True,
                timeout=10,
                check=True,
            ).stdout.strip()
            != ""
        )
    except (OSError, subprocess.SubprocessError):
        return {"git_commit": None, "git_dirty": None}
    return {"git_commit": commit, "git_dirty": dirty}


@functools.lru_cache(maxsize=None)
def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo on Linux), else platform.processor()."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def device_name(device: torch.device | str) -> str:
    """'cpu: <model>' or 'cuda: <GPU name>'."""
    device = torch.device(device)
    if device.type == "cuda":
        return f"cuda: {torch.cuda.get_device_name(device)}"
    return f"cpu: {cpu_model()}"


def provenance(device: torch.device | str = "cpu") -> dict[str, Any]:
    """A JSON-able record of what is producing an artifact now."""
    return {
        **_git(),
        "versions": {lib: _version(lib) for lib in LIBRARIES},
        "python": platform.python_version(),
        "device": device_name(device),
        "torch_threads": torch.get_num_threads(),
    }
