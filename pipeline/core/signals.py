"""SIGTERM (what a cluster scheduler sends before it kills a job) as a request to stop at a safe point.

Inside a `sigterm_deferred()` block a SIGTERM does not end the process: it sets a flag that
`stop_requested()` reads. A long run checks it at its safe points, between two steps,
generations, iterations or exchanges, never inside an update (`Checkpoint.safe_point` in
pipeline/core/resume.py), writes its checkpoint there and raises `Stopped`; the stage prints
the one line and exits with EXIT_CODE, and a rerun resumes bitwise. Outside such a block
SIGTERM keeps its default action: the process ends at once, and the atomic writes leave no
partial artifact.

The flag is process-wide, as a signal's disposition is; only the main thread can install the
handler, so in any other thread the block changes nothing. A SIGTERM still pending when the
block ends came after the run's last safe point: the run is complete and the stage goes on
to write its outputs.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator

# 128 + 15: what a shell reports for a process that SIGTERM ended, so a scheduler or a script
# reads a stop on request as what it is.
EXIT_CODE = 128 + signal.SIGTERM

_received: list[int] = []  # SIGTERMs received since the outermost active block began
_depth = 0  # nesting of active blocks in this process


class Stopped(Exception):
    """A run stopped on SIGTERM at a safe point; the message says where and what it saved."""


def _on_sigterm(signum: int, frame) -> None:
    _received.append(signum)


@contextmanager
def sigterm_deferred() -> Iterator[None]:
    """While active (in the main thread), SIGTERM sets the flag `stop_requested()` reads
    instead of ending the process; the previous handler is restored on exit."""
    global _depth
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGTERM)
    if _depth == 0:
        _received.clear()
        signal.signal(signal.SIGTERM, _on_sigterm)
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if _depth == 0:
            signal.signal(signal.SIGTERM, previous)
            _received.clear()


def reset_in_forked_child() -> None:
    """In a process forked from inside a `sigterm_deferred()` block: SIGTERM back to its default
    action and no block active, as in a freshly started process (a block the child opens then
    installs the handler again)."""
    global _depth
    _depth = 0
    _received.clear()
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def stop_requested() -> bool:
    """Whether a SIGTERM arrived inside the active `sigterm_deferred()` block."""
    return bool(_received)
