"""The one resume path of every long stage: a fingerprint rule, a checkpoint, resume-or-start-over.

Every run the stages drive (TD3 specialists, PDERL, MOPDERL, MORL/D, MAPEX extraction) is a
library object with `state_dict()` and `load_state_dict(state)`. A stage checkpoints it with
a `Checkpoint` under `run_fingerprint(...)`, the one rule for what a run depends on: its
params, its input files, every code file the stage imports (`closure_files`, the same list
DVC's deps hold, so no hand-kept list can miss one), the device, the torch thread count and
the versions of the numeric libraries (`provenance.NUMERIC_LIBRARIES`: torch, numpy, mujoco,
gymnasium, ...), each of which can change the last bits of results. A rerun resumes (`resume`) only if the
fingerprint matches and the state fits the run; anything else starts over, saying why.

A checkpoint file holds {"format": "mapex.checkpoint", "format_version", "fingerprint",
"state", "n_items"}, written atomically and streamed (no in-memory copy of big buffers). A
state may hold a "log": a list that only grows (the members of an extraction or MOPDERL run).
Its entries are written once each, to files of their own beside the checkpoint
(`<stem>.item_00000.pt`, ...), before the checkpoint that counts them, so the cost of a
checkpoint stays constant (rewriting every policy at every iteration would grow
quadratically: hundreds of GB over a paper-scale run) and a checkpoint never names a missing
entry.

A SIGTERM inside pipeline.core.signals.sigterm_deferred makes the run's next
`Checkpoint.safe_point` write the checkpoint at once and raise `Stopped`.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Callable, Sequence, TypeVar

from pipeline.core.artifacts import TMP_SUFFIX, ArtifactError, atomic_path, torch_load_checked, torch_save_atomic
from pipeline.core.codedeps import closure_files
from pipeline.core.provenance import library_versions
from pipeline.core.signals import Stopped, stop_requested

# Where progress goes when a sweep asks for shared storage: `mapex repro --ray --resume-root` sets it
# to one directory per stage item, so a retry on another node resumes where a dead one stopped.
RESUME_ROOT_ENV = "MAPEX_RESUME_ROOT"

FORMAT = "mapex.checkpoint"
ITEM_FORMAT = "mapex.checkpoint_item"
FORMAT_VERSION = 3

R = TypeVar("R")


def fingerprint(config: dict[str, Any], files: Sequence[str | Path]) -> str:
    """sha256 over a canonical JSON of `config` and the bytes of each file, in order."""
    h = hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode())
    for f in files:
        h.update(str(Path(f).name).encode())
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def run_fingerprint(
    stage: str, config: dict[str, Any], device, inputs: Sequence[str | Path] = (), precision: str = "fp32"
) -> str:
    """The fingerprint of a run of stage `stage` (its module stages/<stage>.py): `config` (the
    params it reads and its seed and objectives; not settings that change nothing saved, such
    as checkpoint_every), the device and the precision it resolved to (pipeline.core.precision:
    `auto` is bf16 on one machine and fp32 on another), the torch thread count, the versions of
    the numeric libraries (a checkpoint of another torch or mujoco is not resumed: its run
    would not continue bit for bit), the bytes of its input files and of every code file the
    stage imports."""
    import torch

    full = {
        **config,
        "device": str(device),
        "precision": precision,
        "threads": torch.get_num_threads(),
        "libraries": library_versions(),
    }
    return fingerprint(full, [*inputs, *closure_files(f"stages.{stage}")])


class Checkpoint:
    """The checkpoint of one run at `path` under fingerprint `fp`; `say` tells the user why a
    checkpoint is not resumed."""

    def __init__(self, path: str | Path, fp: str, say: Callable[[str], None]) -> None:
        self.path, self.fp, self.say = Path(path), fp, say
        self.written = 0  # log entries on disk that the checkpoint of this fingerprint counts
        self.good = False  # the file holds a state of this run: resumed from, or saved here

    def _item(self, i: int) -> Path:
        return self.path.with_name(f"{self.path.stem}.item_{i:05d}.pt")

    def _items(self) -> list[Path]:
        return sorted(self.path.parent.glob(f"{self.path.stem}.item_*.pt"))

    def load(self) -> dict[str, Any] | None:
        """The state saved under this fingerprint (its log restored), else None: a missing,
        unreadable, foreign or stale checkpoint is never trusted. Memory-mapped: buffer rows
        are read from the file as they are copied into the run, not held twice."""
        if not self.path.exists():
            return None
        try:
            import torch

            obj = torch.load(self.path, map_location="cpu", weights_only=True, mmap=True)
        except Exception as exc:  # truncated, corrupt, not a torch file
            self.say(f"{self.path}: ignored, starting over (cannot be read: {type(exc).__name__}: {exc})")
            return None
        if not isinstance(obj, dict) or obj.get("format") != FORMAT or obj.get("format_version") != FORMAT_VERSION:
            self.say(f"{self.path}: ignored, starting over (not a {FORMAT} v{FORMAT_VERSION} file)")
            return None
        if obj.get("fingerprint") != self.fp:
            self.say(
                f"{self.path}: params, inputs, code, device, threads or libraries changed since it was written; starting over"
            )
            return None
        state, n = obj.get("state"), obj.get("n_items", 0)
        if n:
            try:
                state = {
                    **state,
                    "log": [torch_load_checked(self._item(i), ITEM_FORMAT, FORMAT_VERSION)["item"] for i in range(n)],
                }
            except (ArtifactError, KeyError) as exc:
                self.say(f"{self.path}: ignored, starting over (an entry it counts cannot be read: {exc})")
                return None
        self.written = n
        self.good = True
        return state

    def save(self, state: dict[str, Any]) -> None:
        """Write `state` atomically: its log entries not yet on disk first (each once), then
        the checkpoint that counts them."""
        import torch

        log = state.get("log")
        rest = {k: v for k, v in state.items() if k != "log"}
        if log is not None:
            if self.written == 0:
                for old in self._items():  # entries of an earlier run must not linger
                    old.unlink(missing_ok=True)
            for i in range(self.written, len(log)):
                torch_save_atomic(
                    {"format": ITEM_FORMAT, "format_version": FORMAT_VERSION, "item": log[i]}, self._item(i)
                )
        obj = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "fingerprint": self.fp,
            "state": rest,
            "n_items": 0 if log is None else len(log),
        }
        with atomic_path(self.path) as tmp, open(tmp, "wb") as f:
            torch.save(obj, f)  # through a Python file, so a full disk surfaces as its OSError (DiskFull)
        self.written = obj["n_items"]
        self.good = True

    def safe_point(self, run, who: str, where: str, due: bool = False) -> None:
        """A point between two steps of `run` where its state is whole: save `run.state_dict()`
        if `due` (a periodic checkpoint) or if SIGTERM asked the run to stop (inside
        pipeline.core.signals.sigterm_deferred); then, on SIGTERM, raise Stopped saying
        `who` stopped at `where` and that a rerun resumes."""
        stop = stop_requested()
        if due or stop:
            self.save(run.state_dict())
        if stop:
            raise Stopped(f"{who}: SIGTERM: checkpoint written at {where} ({self.path}); rerun to resume")

    def clear(self) -> None:
        """Remove the checkpoint, its log entries, what a kill left half-written and its directory if that is now empty."""
        for path in (self.path, self.path.with_name(self.path.name + TMP_SUFFIX), *self._items()):
            path.unlink(missing_ok=True)
        self.written = 0
        self.good = False
        try:
            self.path.parent.rmdir()  # a progress directory of its own goes too; one holding outputs stays
        except OSError:
            pass


def resume(ckpt: Checkpoint, fresh: Callable[[], R]) -> tuple[R, bool]:
    """A run made by `fresh()`, restored from `ckpt` if it holds a state of this fingerprint
    that the run accepts; else (the message says why) a fresh run. Returns (run, resumed).
    A run whose restore failed half-way is thrown away (closed if it has `close`)."""
    run = fresh()
    state = ckpt.load()
    if state is None:
        return run, False
    try:
        run.load_state_dict(state)
    except (
        ValueError,
        KeyError,
        RuntimeError,
        TypeError,
        ArtifactError,
    ) as exc:  # right fingerprint, yet it does not fit
        ckpt.say(f"{ckpt.path}: cannot be resumed ({exc}); starting over")
        if hasattr(run, "close"):
            run.close()
        ckpt.written, ckpt.good = 0, False
        return fresh(), False
    return run, True


def resume_root(default: str | Path) -> Path:
    """The root a stage keeps its resume progress under: $MAPEX_RESUME_ROOT when set, else `default`."""
    root = os.environ.get(RESUME_ROOT_ENV)
    return Path(root) if root else Path(default)


def checkpoint_dir(out: str | Path, inside: bool = True) -> Path:
    """Where a stage that checkpoints beside its outputs keeps its checkpoint: OUT itself
    (`inside`, for a stage whose DVC outs are files in OUT), else the hidden sibling
    .<OUT's name>.resume (for a stage whose DVC out is the directory OUT, which DVC deletes
    before the stage runs); or $MAPEX_RESUME_ROOT/<OUT's name> when set (a sweep's shared
    storage, one directory per stage item)."""
    out = Path(out)
    root = os.environ.get(RESUME_ROOT_ENV)
    if root:
        return Path(root) / out.name
    return out if inside else out.parent / f".{out.name}.resume"
