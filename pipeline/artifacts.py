"""Atomic writing of artifacts and the error raised for a bad one.

Every artifact is written under a temporary name beside its destination and renamed into
place only when complete, so a killed stage never leaves a half-written file that a later
stage would accept.
"""

from __future__ import annotations

import io
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import torch

TMP_SUFFIX = ".partial"


class ArtifactError(ValueError):
    """An input artifact is missing, truncated, of the wrong format, or does not match."""


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


@contextmanager
def atomic_path(dest: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write `dest` at (a file or a directory); rename on success.

    On an exception the temporary is removed and `dest` is left as it was.
    """
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(dest.name + TMP_SUFFIX)
    _remove(tmp)
    try:
        yield tmp
    except BaseException:
        _remove(tmp)
        raise
    if dest.is_dir() and not dest.is_symlink():
        old = dest.with_name(dest.name + ".old")
        _remove(old)
        os.replace(dest, old)
        os.replace(tmp, dest)
        shutil.rmtree(old)
    else:
        os.replace(tmp, dest)


def write_bytes_atomic(dest: str | Path, data: bytes) -> None:
    with atomic_path(dest) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())


def write_text_atomic(dest: str | Path, text: str) -> None:
    write_bytes_atomic(dest, text.encode())


def torch_save_atomic(obj: Any, dest: str | Path) -> None:
    buf = io.BytesIO()
    torch.save(obj, buf)
    write_bytes_atomic(dest, buf.getvalue())


def torch_load_checked(path: str | Path, fmt: str, version: int) -> dict[str, Any]:
    """Load a torch artifact with weights_only=True and check its format tag and version."""
    path = Path(path)
    if not path.is_file():
        raise ArtifactError(f"{path}: file not found (expected a {fmt} artifact)")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # truncated or corrupt zip, or not a torch file at all
        raise ArtifactError(f"{path}: cannot be read as a torch checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(obj, dict) or obj.get("format") != fmt:
        got = obj.get("format") if isinstance(obj, dict) else type(obj).__name__
        raise ArtifactError(f"{path}: format is {got!r}, expected {fmt!r}")
    if obj.get("format_version") != version:
        raise ArtifactError(f"{path}: format_version {obj.get('format_version')!r}, expected {version}")
    return obj
