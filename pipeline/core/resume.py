"""Resumable runs: a fingerprint of everything a run depends on, and its saved progress.

A stage that checkpoints after each unit of work stores the fingerprint with its progress; a
rerun resumes only if the fingerprint matches, so a changed param, input, code file, device
or thread count starts over instead of continuing stale state. The code files are every
in-project file the stage imports (`pipeline.core.codedeps.closure_files`), the same list DVC's
deps hold, so no hand-kept list can miss one.

Layout of a progress directory: one file per finished item (`item_00000.pt`, ...), each
written once, and `state.pt` (fingerprint, item count, small extra state) rewritten after
each item. Writing items separately keeps the cost of a checkpoint constant: rewriting every
policy at every iteration would grow quadratically (hundreds of GB over a paper-scale run).
`state.pt` is replaced only after the item it counts is on disk, so it never names a
missing item.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any, Callable

from pipeline.core.artifacts import ArtifactError, atomic_path, torch_load_checked, torch_save_atomic

# Where progress goes when a sweep asks for shared storage: `mapex sweep --resume-root` sets it
# to one directory per stage item, so a retry on another node resumes where a dead one stopped.
RESUME_ROOT_ENV = "MAPEX_RESUME_ROOT"

FORMAT = "mapex.resume"
ITEM_FORMAT = "mapex.resume_item"
FORMAT_VERSION = 2


def fingerprint(config: dict[str, Any], files: list[str | Path]) -> str:
    """sha256 over a canonical JSON of `config` and the bytes of each file, in order."""
    h = hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode())
    for f in files:
        h.update(str(Path(f).name).encode())
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def _item_path(directory: Path, i: int) -> Path:
    return directory / f"item_{i:05d}.pt"


def load_progress(directory: str | Path, expected: str) -> tuple[list[dict[str, Any]], dict[str, Any]] | None:
    """(items, extra state) saved in `directory` under fingerprint `expected`, else None.

    Unreadable or mismatched progress is discarded, never trusted.
    """
    directory = Path(directory)
    try:
        obj = torch_load_checked(directory / "state.pt", FORMAT, FORMAT_VERSION)
        if obj.get("fingerprint") != expected:
            return None
        items = [torch_load_checked(_item_path(directory, i), ITEM_FORMAT, FORMAT_VERSION)["item"] for i in range(obj["n_items"])]
    except (ArtifactError, KeyError):
        return None
    return items, obj["state"]


def save_progress(directory: str | Path, fp: str, new_items: list[dict[str, Any]], start: int, state: dict[str, Any]) -> int:
    """Write `new_items` as items start, start+1, ... (each once), then the state that counts
    them; returns the new item count. start = 0 begins a fresh progress directory."""
    directory = Path(directory)
    if start == 0:
        clear_progress(directory)  # stale items of another fingerprint must not linger
    for i, item in enumerate(new_items, start=start):
        torch_save_atomic({"format": ITEM_FORMAT, "format_version": FORMAT_VERSION, "item": item}, _item_path(directory, i))
    n = start + len(new_items)
    torch_save_atomic(
        {"format": FORMAT, "format_version": FORMAT_VERSION, "fingerprint": fp, "n_items": n, "state": state},
        directory / "state.pt",
    )
    return n


def clear_progress(directory: str | Path) -> None:
    shutil.rmtree(directory, ignore_errors=True)


def resume_root(default: str | Path) -> Path:
    """The root a stage keeps its resume progress under: $MAPEX_RESUME_ROOT when set, else `default`."""
    root = os.environ.get(RESUME_ROOT_ENV)
    return Path(root) if root else Path(default)


def checkpoint_dir(out: str | Path) -> Path:
    """Where a stage that checkpoints beside its outputs (OUT/<name>_state.pt) keeps that file:
    OUT itself, or $MAPEX_RESUME_ROOT/<OUT's name> when set (shared storage)."""
    root = os.environ.get(RESUME_ROOT_ENV)
    return Path(root) / Path(out).name if root else Path(out)


# One-file checkpoints of a whole run (training stages: TD3 and PDERL specialists, MORL/D):
# {"format", "format_version", "fingerprint", "state"}, written streamed and atomically.


def load_run_checkpoint(path: str | Path, fmt: str, version: int, fp: str, log: Callable[[str], None]) -> dict[str, Any] | None:
    """The run state saved at `path` under fingerprint `fp`, else None: a missing, unreadable,
    foreign or stale checkpoint is never trusted (`log` says why it is ignored). Memory-mapped:
    buffer rows are read from the file as they are copied into the run, not held twice."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        import torch

        obj = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as exc:  # truncated, corrupt, not a torch file
        log(f"{path}: ignored, starting over (cannot be read: {type(exc).__name__}: {exc})")
        return None
    if not isinstance(obj, dict) or obj.get("format") != fmt or obj.get("format_version") != version:
        log(f"{path}: ignored, starting over (not a {fmt} v{version} file)")
        return None
    if obj.get("fingerprint") != fp:
        log(f"{path}: params, code, device, threads or libraries changed since it was written; starting over")
        return None
    return obj.get("state")


def save_run_checkpoint(path: str | Path, fmt: str, version: int, fp: str, state: dict[str, Any]) -> None:
    """Write a run checkpoint atomically, streamed to the file (no in-memory copy of its buffers)."""
    import torch

    obj = {"format": fmt, "format_version": version, "fingerprint": fp, "state": state}
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)

