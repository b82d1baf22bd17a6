"""Side-by-side worker processes inside one stage.

A stage that splits its work into independent parts (the specialists of a seed, say) can run
each part in its own process: on a CPU with cores to spare and small networks, two processes
of one job each beat one process that does both (PyTorch's per-op overhead, not arithmetic,
bounds a small update, and a second thread does not halve that overhead, a second process
does).

`run_side_by_side(fn, parts, on_message)` starts one process per part (spawned; or forked,
`start="fork"`, where the caller knows that safe), calls
`fn(*part, send=send)` in it, relays what the part `send`s to `on_message` in this process,
and returns when every part has finished. The first part that fails stops the others and
raises `WorkerError` here. A worker whose parent has gone (the stage was killed) is killed by
the kernel at once on Linux (PR_SET_PDEATHSIG), elsewhere it stops at its next `send`; the
work of a part must therefore be safe to kill, which is what the stages' atomic writes and
resumable checkpoints are for.

A SIGTERM to the stage is passed on to every worker still running (pipeline.core.signals): a
part that stops at a safe point on it (raises `Stopped` after writing its checkpoint) counts
as stopped, not failed, and once every part has finished or stopped `run_side_by_side`
raises `Stopped` with one line per stopped part.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import signal
import sys
import time
import traceback
from typing import Any, Callable, Sequence

from pipeline.core.signals import Stopped, reset_in_forked_child, sigterm_deferred, stop_requested

START_METHODS = ("spawn", "fork")


def split_evenly(items: Sequence[Any], n: int) -> list[list[Any]]:
    """items in min(n, len(items)) contiguous parts whose sizes differ by one at most."""
    n = max(1, min(n, len(items)))
    size, extra = divmod(len(items), n)
    parts, start = [], 0
    for i in range(n):
        stop = start + size + (i < extra)
        parts.append(list(items[start:stop]))
        start = stop
    return parts


def oversubscribed(processes: int, threads: int) -> str | None:
    """A warning when `processes` workers of `threads` torch threads each want more cores than
    this machine has (OpenMP threads then wait on each other: measured several times slower)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if processes * threads <= cores:
        return None
    return (
        f"warning: {processes} processes x {threads} torch threads on {cores} cores: oversubscribed, "
        f"expect it to be slow; lower MAPEX_TORCH_THREADS or processes"
    )


class WorkerError(RuntimeError):
    """A worker process failed: `part` is its index; `detail` its traceback, or "" when the
    failure was one of the caller's `expected` exception types (its message says it all;
    `kind` is then its type) or the process died without a word (the message gives its exit
    code)."""

    def __init__(
        self, part: int, message: str, detail: str = "", expected: bool = False, kind: type | None = None
    ) -> None:
        super().__init__(message)
        self.part, self.detail, self.expected, self.kind = part, detail, expected, kind


class ParentGone(SystemExit):
    """Raised in a worker whose parent process has exited."""


def _die_with_parent(parent: int) -> None:
    """On Linux, have the kernel SIGKILL this process as soon as its parent dies, whatever it is
    doing (saving artifacts, say); elsewhere `send` notices at the next message."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            import signal

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent:  # it died before the flag was set
        os._exit(1)


def _entry(
    fn: Callable[..., Any], index: int, args: tuple, channel, parent: int, expected: tuple[type, ...], forked: bool
) -> None:
    if forked:  # started inside the parent's sigterm_deferred block: leave it, as a spawned worker starts
        reset_in_forked_child()
    _die_with_parent(parent)

    def send(*message: Any) -> None:
        if os.getppid() != parent:
            channel.cancel_join_thread()  # exit without flushing messages nobody will read
            raise ParentGone(f"worker {index}: the stage process has gone; stopping")
        channel.put((index, "message", message))

    try:
        fn(*args, send=send)
    except ParentGone:
        raise
    except Stopped as exc:  # on SIGTERM, at a safe point, its checkpoint written
        channel.put((index, "stopped", str(exc)))
        return
    except BaseException as exc:  # noqa: BLE001 - every failure must reach the parent
        known = isinstance(exc, expected)
        detail = "" if known else traceback.format_exc()
        message = str(exc) if known else f"{type(exc).__name__}: {exc}"
        # an expected type is one of the caller's (importable, so it pickles by name)
        channel.put((index, "error", (message, detail, known, type(exc) if known else None)))
        raise SystemExit(1) from None
    channel.put((index, "done", None))


def run_side_by_side(
    fn: Callable[..., Any],
    parts: Sequence[tuple],
    on_message: Callable[[int, tuple], None] | None = None,
    expected: tuple[type, ...] = (),
    poll_s: float = 0.2,
    start: str = "spawn",
) -> None:
    """Run fn(*parts[i], send=...) for every i, each in its own spawned process, at once.

    fn must be importable (a module-level function) and its arguments picklable. start="fork"
    forks the workers instead: no interpreter start-up and no imports (about 2 s of a core per
    worker for torch and MuJoCo, which a few seconds of work cannot pay back), the arguments
    inherited, not pickled; only for a caller whose process holds no CUDA state and no OpenMP
    thread pool (one torch thread), which a fork would copy broken. What a part
    passes to `send(*message)` reaches `on_message(i, message)` here, in order per part.
    Raises WorkerError for the first part that fails (the others are killed first); for an
    exception of a type in `expected` (bad input, say) without the worker's traceback. A
    SIGTERM here is sent on to each running worker; Stopped (its lines those of the parts
    that stopped) once all have ended.
    """
    if start not in START_METHODS:
        raise ValueError(f"start={start!r}: expected one of {list(START_METHODS)}")
    # spawn by default, not fork: the parent may hold OpenMP or CUDA state
    ctx = mp.get_context(start)
    channel = ctx.Queue()
    forked = start == "fork"
    procs = [
        ctx.Process(
            target=_entry, args=(fn, i, tuple(args), channel, os.getpid(), tuple(expected), forked), daemon=True
        )
        for i, args in enumerate(parts)
    ]
    done: set[int] = set()
    stopped: dict[int, str] = {}
    forwarded = False

    def handle(item) -> None:
        index, kind, payload = item
        if kind == "message":
            if on_message is not None:
                on_message(index, payload)
        elif kind == "done":
            done.add(index)
        elif kind == "stopped":
            stopped[index] = payload
            done.add(index)
        else:
            message, detail, known, exc_type = payload
            raise WorkerError(index, f"part {index}: {message}" if not known else message, detail, known, exc_type)

    try:
        with sigterm_deferred():
            for p in procs:
                p.start()
            checked = time.monotonic()
            while len(done) < len(procs):
                if stop_requested() and not forwarded:
                    forwarded = True
                    for i, p in enumerate(procs):
                        if i not in done and p.is_alive():
                            p.terminate()  # SIGTERM: the part checkpoints at its next safe point
                try:
                    handle(channel.get(timeout=poll_s))
                except queue.Empty:
                    pass
                if time.monotonic() - checked < poll_s:
                    continue
                # liveness on a clock, not only when the queue is quiet: busy siblings must not
                # hide a worker that died (killed for memory, say)
                checked = time.monotonic()
                dead = [i for i, p in enumerate(procs) if i not in done and not p.is_alive()]
                if dead:
                    # a process that exited normally flushed its last messages first: read them
                    until = time.monotonic() + 2.0
                    while time.monotonic() < until and any(i not in done for i in dead):
                        try:
                            handle(channel.get(timeout=0.1))
                        except queue.Empty:
                            pass
                    for i in dead:
                        if i in done:
                            continue
                        if forwarded and procs[i].exitcode == -signal.SIGTERM:  # before it could defer it
                            stopped[i] = f"part {i}: SIGTERM before its first safe point; nothing saved"
                            done.add(i)
                            continue
                        raise WorkerError(i, f"part {i}: its process exited with code {procs[i].exitcode}")
        if stopped:
            raise Stopped("\n".join(stopped[i] for i in sorted(stopped)))
    finally:
        for p in procs:
            if p.is_alive():
                p.kill()  # a sibling failed: stop the others now, not at their next safe point
        for p in procs:
            p.join()
        channel.close()
