"""What a stage's compute cost: CPU (core-) seconds and wall seconds, for its provenance record.

Core-seconds are CPU seconds, user plus system, of every thread of the process and of the child
processes it has waited for (a stage's worker processes; `resource.getrusage`): on a CPU the
compute a run took whatever its thread count, comparable across machines of one kind. A GPU's
own time is not in them (the record's wall seconds and device say what ran there).

Timings are never in an artifact: they differ from run to run, and an artifact holds only what
its inputs and params fix (docs/developing.md, "Provenance"). They go to the stage's provenance
record (`pipeline.core.provenance.write_provenance`, key "cost"), which only the report reads.
"""

from __future__ import annotations

import os
import resource
import time
from dataclasses import dataclass


def _process_start() -> float:
    """When this process started, on the time.monotonic clock (Linux: from /proc, whose uptime is
    that clock's; elsewhere: when this module was loaded, after the interpreter's start-up)."""
    try:
        with open("/proc/self/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22, starttime, after the name
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return time.monotonic() - max(uptime - ticks / os.sysconf("SC_CLK_TCK"), 0.0)
    except (OSError, ValueError, IndexError):
        return time.monotonic()


STARTED = _process_start()  # the start of a process's wall seconds, as of its CPU seconds


def cpu_seconds() -> float:
    """CPU seconds (user + system) of this process's threads and of its waited-for children."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def process_cost() -> dict[str, float]:
    """This process's cost so far: {"cpu_seconds", "wall_seconds"}, both since it started."""
    return {"cpu_seconds": round(cpu_seconds(), 3), "wall_seconds": round(time.monotonic() - STARTED, 3)}


@dataclass
class Stopwatch:
    """Wall and CPU seconds spent inside a `with` block (`wall`, `cpu` once it has ended)."""

    wall: float = 0.0
    cpu: float = 0.0

    def __enter__(self) -> "Stopwatch":
        self._wall, self._cpu = time.perf_counter(), cpu_seconds()
        return self

    def __exit__(self, *exc) -> None:
        self.wall = time.perf_counter() - self._wall
        self.cpu = cpu_seconds() - self._cpu


# The columns of one row of a run's per-iteration cost (provenance record "cost" -> "iterations").
COST_FIELDS = ("iteration", "phase", "policies", "train_wall_s", "train_cpu_s", "eval_wall_s", "eval_cpu_s")


def cost_row(
    iteration: int, phase: str, policies: int, train: Stopwatch | None, evaluate: Stopwatch | None
) -> dict[str, float | int | str]:
    """One row of COST_FIELDS: what iteration `iteration`'s `phase` ("start": the starting
    policies evaluated; "seeds": interpolated policies mixed and evaluated; "children": children
    trained and evaluated) cost for its `policies` policies (None: nothing of that part)."""
    return {
        "iteration": iteration,
        "phase": phase,
        "policies": policies,
        "train_wall_s": round(train.wall, 4) if train else 0.0,
        "train_cpu_s": round(train.cpu, 4) if train else 0.0,
        "eval_wall_s": round(evaluate.wall, 4) if evaluate else 0.0,
        "eval_cpu_s": round(evaluate.cpu, 4) if evaluate else 0.0,
    }
