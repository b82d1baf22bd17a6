"""What produced a stage's outputs: code version, library versions, device and thread count.

Recorded beside the artifacts, never inside them. A stage run with `--provenance PATH` writes
its record there as JSON (`write_provenance`); dvc.yaml declares that file as an out of its own
under data/provenance/, at the path of the stage's out below data/ plus .json (the record of
data/fronts/mapex_td3/seed0/population.pt is data/provenance/fronts/mapex_td3/seed0.json). An
artifact a later stage reads holds only what its inputs and params determine, so a rerun that
changes no number (a refactor, a comment, a new commit) rewrites its bytes unchanged and DVC
reruns nothing downstream; only the record, which no stage but the report reads, changes.
Without --provenance (a stage command run by hand) no record is written.

The report's provenance table reads the records (pipeline.reporting.runs), so a reader can
tell whether two results are comparable. Bitwise reproducibility holds only between runs whose
records agree on everything here except `git_dirty` noise (same machine type, thread count,
library versions and device); see the README, "Reproducibility".
"""

from __future__ import annotations

import functools
import json
import platform
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

import torch

from pipeline.core.artifacts import write_text_atomic
from pipeline.core.cost import process_cost

ROOT = Path(__file__).resolve().parents[2]
LIBRARIES = ("mapex", "torch", "numpy", "mujoco", "gymnasium", "mo-gymnasium", "zarr")
# The third-party libraries whose versions can change a run's numbers (or its saved state's
# layout); a checkpoint written under other versions is not resumed (pipeline.core.resume).
# mapex itself is not among them: its code is fingerprinted file by file.
NUMERIC_LIBRARIES = tuple(lib for lib in LIBRARIES if lib != "mapex")


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def library_versions(libs: tuple[str, ...] = NUMERIC_LIBRARIES) -> dict[str, str | None]:
    """The installed version of each of `libs` (None where one is not installed)."""
    return {lib: _version(lib) for lib in libs}


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
    """A JSON-able record of what is running now (code, libraries, device, threads)."""
    return {
        **_git(),
        "versions": {lib: _version(lib) for lib in LIBRARIES},
        "python": platform.python_version(),
        "device": device_name(device),
        "torch_threads": torch.get_num_threads(),
    }


def write_provenance(
    path: Path | None,
    stage: str,
    device: torch.device | str = "cpu",
    precision: str | None = None,
    cost: dict[str, Any] | None = None,
) -> None:
    """Write the record of this run of `stage` to `path` (JSON, atomically): {"stage": ...,
    and `provenance(device)`'s keys}, "precision": what the stage computed in ("fp32" or
    "bf16", its `precision` param resolved: pipeline.core.precision) for a stage that has one,
    and "cost": this process's core-seconds and wall seconds (pipeline.core.cost.process_cost;
    a stage resumed from a checkpoint: its last process only) updated with `cost`, what the
    stage adds (extraction and interpolation: "iterations", their per-iteration rows, which
    survive a resume). Nothing when `path` is None (no --provenance given). Stages call it
    after their outputs are written: a record stands for a finished run."""
    if path is None:
        return
    record = {"stage": stage, **provenance(device)}
    if precision is not None:
        record["precision"] = precision
    record["cost"] = {**process_cost(), **(cost or {})}
    write_text_atomic(path, json.dumps(record, indent=2) + "\n")
