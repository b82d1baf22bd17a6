"""Atomic writing of artifacts and the error raised for a bad one.

Every artifact is written under a temporary name beside its destination, fsynced, and
renamed into place only when complete, so a killed stage never leaves a half-written file
that a later stage would accept. A directory that already exists (a Zarr buffer, say) is
swapped with its replacement in one atomic exchange (Linux renameat2 RENAME_EXCHANGE), so a
kill at any point leaves either the old directory or the new one, whole, at the destination.
Where the exchange is unavailable (another OS, a file system without it) the old directory
is first renamed aside to DEST.old and the next write, or `recover`, puts it back if the
process died between the two renames.

A write that fails because the disk is full or a quota or file-size limit is reached
(ENOSPC, EDQUOT, EFBIG, also when a library wraps the OSError, as torch's zip writer does)
raises `DiskFull`: one line naming the file, the temporary removed, the old artifact intact.
"""

from __future__ import annotations

import csv
import ctypes
import ctypes.util
import errno
import io
import json
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

import torch

TMP_SUFFIX = ".partial"


class ArtifactError(ValueError):
    """An input artifact is missing, truncated, of the wrong format, or does not match."""


class DiskFull(ArtifactError):
    """An artifact could not be written: the disk, a quota or the file-size limit is full."""


# errnos that mean "no room to write": ENOSPC (disk full), EDQUOT (quota), EFBIG (file-size limit)
DISK_FULL_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (at most 160 characters), or its type's name: what a
    one-line refusal quotes of an error raised while reading a file from elsewhere."""
    try:
        text = str(exc).strip()
    except Exception:  # the str of an exception carrying a hostile value may itself fail
        text = ""
    return text.splitlines()[0][:160] if text else type(exc).__name__


def disk_full_error(exc: BaseException) -> OSError | None:
    """The OSError of a full disk, quota or file-size limit behind `exc` (itself, or what it was
    raised from or while handling, as torch's RuntimeError wraps a file object's OSError), else None."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS:
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # e.g. a platform where directories cannot be opened
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def fsync_tree(path: Path) -> None:
    """fsync every file under `path` (or `path` itself), then the directories, deepest first."""
    if path.is_file():
        with open(path, "rb") as f:
            os.fsync(f.fileno())
        return
    dirs = []
    for root, _, files in os.walk(path):
        dirs.append(Path(root))
        for name in files:
            with open(Path(root) / name, "rb") as f:
                os.fsync(f.fileno())
    for d in reversed(dirs):
        _fsync_dir(d)


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap paths a and b (Linux renameat2). False where unsupported."""
    libc_name = ctypes.util.find_library("c")
    if libc_name is None:
        return False
    libc = ctypes.CDLL(libc_name, use_errno=True)
    fn = getattr(libc, "renameat2", None)
    if fn is None:
        return False
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def recover(dest: str | Path) -> None:
    """Undo a directory swap a kill interrupted: DEST missing but DEST.old whole -> put it back."""
    dest = Path(dest)
    old = dest.with_name(dest.name + ".old")
    if old.exists() and not dest.exists():
        os.replace(old, dest)
    elif old.exists():
        _remove(old)


def replace_path(tmp: Path, dest: Path) -> None:
    """Move the complete `tmp` (file or directory) to `dest`, replacing what is there atomically."""
    fsync_tree(tmp)
    if dest.is_dir() and not dest.is_symlink():
        if _exchange(tmp, dest):
            _fsync_dir(dest.parent)
            _remove(tmp)  # the old directory, now at tmp
        else:
            old = dest.with_name(dest.name + ".old")
            _remove(old)
            os.replace(dest, old)
            os.replace(tmp, dest)  # a kill before this line: `recover` restores DEST.old
            _fsync_dir(dest.parent)
            shutil.rmtree(old)
    else:
        os.replace(tmp, dest)
        _fsync_dir(dest.parent)


@contextmanager
def atomic_path(dest: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write `dest` at (a file or a directory); replace `dest` on success.

    On an exception the temporary is removed and `dest` is left as it was; a full disk, quota or
    file-size limit raises `DiskFull` naming `dest`. The temporary is fsynced before it
    replaces `dest`, and the replacement is atomic (see the module doc).
    """
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    recover(dest)
    tmp = dest.with_name(dest.name + TMP_SUFFIX)
    _remove(tmp)
    try:
        yield tmp
        replace_path(tmp, dest)
    except BaseException as exc:
        _remove(tmp)
        full = disk_full_error(exc)
        if full is None:
            raise
        recover(dest)  # a fallback swap that failed between its renames: the old directory back
        kept = f"the previous {dest.name} is left intact" if dest.exists() else "nothing was left behind"
        raise DiskFull(
            f"{dest}: cannot be written: the disk is full or a quota or file-size limit was reached "
            f"({full.strerror or full}); {kept}; free some space and rerun"
        ) from None


def write_bytes_atomic(dest: str | Path, data: bytes) -> None:
    with atomic_path(dest) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())


def write_text_atomic(dest: str | Path, text: str) -> None:
    write_bytes_atomic(dest, text.encode())


def csv_text(header: Sequence[str], rows: Iterable[Sequence | Mapping[str, Any]]) -> str:
    """The text of a CSV artifact: the header line, then one line per row, each ended by "\n".

    A row is a sequence of values in header order, or a mapping with exactly the header's keys.
    Values are written as the csv module writes them (str of each, None empty, a field holding a
    comma, quote or line break quoted); callers format floats themselves where they want fewer digits.
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for row in rows:
        if isinstance(row, Mapping):
            if set(row) != set(header):
                raise ValueError(f"CSV row keys {sorted(row)} differ from the header {list(header)}")
            row = [row[h] for h in header]
        w.writerow(row)
    return buf.getvalue()


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


def read_json(path: str | Path, keys: tuple[str, ...] = ()) -> dict[str, Any]:
    """A JSON object holding every key in `keys`; ArtifactError naming the file (and the key)
    if it is missing, unreadable, not an object or lacks a key."""
    path = Path(path)
    if not path.is_file():
        raise ArtifactError(f"{path}: file not found")
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ArtifactError(f"{path}: cannot be read as JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ArtifactError(f"{path}: expected a JSON object, got {type(data).__name__}")
    missing = [k for k in keys if k not in data]
    if missing:
        raise ArtifactError(f"{path}: no {', '.join(map(repr, missing))} key")
    return data
