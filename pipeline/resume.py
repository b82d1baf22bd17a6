"""Resumable runs: a fingerprint of everything a run depends on, and its saved progress.

A stage that checkpoints after each unit of work stores the fingerprint with its state; a
rerun resumes only if the fingerprint matches, so a changed param or input starts over
instead of continuing stale state.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from pipeline.artifacts import ArtifactError, torch_load_checked, torch_save_atomic

FORMAT = "mapex.resume"
FORMAT_VERSION = 1


def fingerprint(config: dict[str, Any], files: list[str | Path]) -> str:
    """sha256 over a canonical JSON of `config` and the bytes of each input file, in order."""
    h = hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode())
    for f in files:
        h.update(str(Path(f).name).encode())
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def load_resume(path: str | Path, expected: str) -> dict[str, Any] | None:
    """The saved state at `path` if it exists, is readable and carries fingerprint `expected`."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        obj = torch_load_checked(path, FORMAT, FORMAT_VERSION)
    except ArtifactError:
        return None  # unreadable progress is discarded, never trusted
    return obj["state"] if obj.get("fingerprint") == expected else None


def save_resume(path: str | Path, fp: str, state: dict[str, Any]) -> None:
    torch_save_atomic({"format": FORMAT, "format_version": FORMAT_VERSION, "fingerprint": fp, "state": state}, path)
