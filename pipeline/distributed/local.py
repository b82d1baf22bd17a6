"""Stage items side by side on one machine: what `mapex repro --jobs N` runs.

`dvc repro` runs one stage at a time. After the specialists most of the quickstart's stages use
one core (an extraction's children are trained one after another), so on a 2-core machine one
core sat idle for about 200 of its 756 seconds (docs/benchmarks.md, "End to end"). DVC itself
allows more: it releases its repository lock while a stage's command runs and guards the
stage's own deps and outs with read/write locks (dvc/stage/run.py, dvc/stage/decorators.py), so
several `dvc --wait-for-lock repro --single-item ITEM` processes may run in one workspace at
once, each bookkeeping (dvc.lock, run-cache) under the repository lock in turn.

This module orders the workspace's stage items by DVC's own DAG (the same items and upstream as
`mapex repro --ray`'s tasks, pipeline.distributed.workspace.stage_items) and starts each item's
`dvc repro --single-item` once every item upstream of it has finished, at most `jobs` at a time.
Each item decides for itself, as in `dvc repro`, whether it runs, is restored from the
run-cache or is skipped as unchanged; its outputs are the same bytes as under `dvc repro`
(every stage is a pure command of its deps and params; one torch thread a process). On a
failure nothing new starts, the items running finish, and the failed item's log is shown.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Callable, Mapping, Protocol, Sequence

from pipeline.distributed.workspace import StageItem, _dvc_bin

# What `dvc repro` prints for an item it did not run (its wording in DVC 3.x), for the summary.
_UNCHANGED = re.compile(r"didn't change, skipping")
_RESTORED = re.compile(r"is cached - skipping run, checking out outputs")


class Terminated(Exception):
    """SIGTERM reached `mapex repro` (repro_parallel turns it into this)."""


class Process(Protocol):
    def poll(self) -> int | None: ...

    def send_signal(self, sig: int) -> None: ...

    def wait(self, timeout: float | None = None) -> int: ...


@dataclass
class ItemResult:
    """One stage item's run: its exit code, wall seconds and what DVC did with it."""

    name: str
    returncode: int
    seconds: float
    outcome: str  # "ran", "unchanged", "restored" or "failed"
    log: Path | None = None


@dataclass
class ReproResult:
    results: list[ItemResult] = field(default_factory=list)
    not_started: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def failed(self) -> list[ItemResult]:
        return [r for r in self.results if r.returncode != 0]


def outcome_of(log_text: str, returncode: int) -> str:
    """What DVC did with an item, from its output: failed, unchanged, restored or ran."""
    if returncode != 0:
        return "failed"
    if _UNCHANGED.search(log_text):
        return "unchanged"
    if _RESTORED.search(log_text):
        return "restored"
    return "ran"


def run_items(
    items: Sequence[StageItem],
    jobs: int,
    launch: Callable[[StageItem], Process],
    finished: Callable[[StageItem, int, float], None] = lambda item, rc, s: None,
    started: Callable[[StageItem], None] = lambda item: None,
    stop: Callable[[Process, int], None] = lambda p, sig: p.send_signal(sig),
    again: Callable[[Process, int], None] | None = None,
    again_after: float = 5.0,
    poll_seconds: float = 0.2,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> tuple[list[tuple[StageItem, int, float]], list[str]]:
    """Start each item once every upstream item (of those given) has finished with exit code 0,
    at most `jobs` at a time, in the order given among those ready (stage_items' order: the
    longest chain of dependents first). After a failure nothing new starts and the running items
    finish. Returns (item, exit code, seconds) in the order they finished, and the names of the
    items never started. On KeyboardInterrupt every running item gets SIGINT, on Terminated
    SIGTERM, through `stop` (DVC and the stages stop cleanly on either: nothing half-written),
    and is waited for; then it re-raises. A SIGINT can be lost by a stage's command (a shell
    whose child got it between fork and exec goes on with its script), so an item still running
    `again_after` seconds later gets it again through `again` (default `stop`), and so on until it
    ends; a second Ctrl-C while waiting does the same at once instead of abandoning the items."""
    if jobs < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    names = {i.name for i in items}
    pending = list(items)
    running: dict[str, tuple[StageItem, Process, float]] = {}
    done: set[str] = set()
    out: list[tuple[StageItem, int, float]] = []
    failed = False
    try:
        while pending or running:
            if not failed:
                for item in list(pending):
                    if len(running) >= jobs:
                        break
                    if all(u in done or u not in names for u in item.upstream):
                        pending.remove(item)
                        started(item)
                        running[item.name] = (item, launch(item), clock())
            if not running:
                break  # what is left waits on a failed item
            ended = [(n, rc) for n, (_, p, _) in running.items() if (rc := p.poll()) is not None]
            if not ended:
                sleep(poll_seconds)
                continue
            for name, rc in ended:
                item, _, t0 = running.pop(name)
                seconds = clock() - t0
                out.append((item, rc, seconds))
                finished(item, rc, seconds)
                if rc == 0:
                    done.add(name)
                else:
                    failed = True
    except (KeyboardInterrupt, Terminated) as exc:
        sig = signal.SIGINT if isinstance(exc, KeyboardInterrupt) else signal.SIGTERM
        _stop_and_wait(
            [p for _, p, _ in running.values()], sig, stop, again or stop, again_after, poll_seconds, clock, sleep
        )
        raise
    return out, [i.name for i in pending]


def _stop_and_wait(
    procs: list[Process],
    sig: int,
    stop: Callable[[Process, int], None],
    again: Callable[[Process, int], None],
    again_after: float,
    poll_seconds: float,
    clock: Callable[[], float],
    sleep: Callable[[float], None],
) -> None:
    """`stop` each process with `sig`, then wait for all of them; SIGINT again (through `again`) to
    those still running every `again_after` seconds, and at once on another Ctrl-C. SIGTERM is
    sent once: a stage stops on it at its next safe point, however long that takes."""

    def send(fn: Callable[[Process, int], None], ps: list[Process]) -> None:
        for p in ps:
            try:
                fn(p, sig)
            except ProcessLookupError:
                pass

    send(stop, procs)
    last = clock()
    while procs := [p for p in procs if p.poll() is None]:
        try:
            sleep(poll_seconds)
        except KeyboardInterrupt:
            last = float("-inf")  # a second Ctrl-C: pass it on now
        if sig == signal.SIGINT and clock() - last >= again_after:
            send(again, [p for p in procs if p.poll() is None])
            last = clock()


def group_members(pgid: int) -> list[int] | None:
    """The processes of process group `pgid`, from /proc (None where there is no /proc)."""
    proc = Path("/proc")
    if not proc.is_dir():
        return None
    out = []
    for entry in proc.iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue  # gone meanwhile
        # fields after the command (in parentheses, which may hold spaces): state, ppid, pgrp
        fields = stat[stat.rfind(")") + 2 :].split()
        if len(fields) > 2 and int(fields[2]) == pgid:
            out.append(int(entry.name))
    return out


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.@-]+", "_", name)


def repro_parallel(
    root: Path,
    items: Sequence[StageItem],
    jobs: int,
    echo: Callable[[str], None],
    log_dir: Path | None = None,
    places: Mapping[str, tuple[Path, str]] | None = None,
) -> ReproResult:
    """Run `items` of the DVC workspace at `root` with run_items, each as `dvc --wait-for-lock
    repro --single-item ITEM`, its output to LOG_DIR/ITEM.log (default: .dvc/tmp/mapex-repro, DVC's
    scratch folder, never tracked); `echo` gets a line as each starts and ends.

    `places` (item name -> (workspace, DVC's item name)) runs items in other workspaces instead,
    the cells of a grid (pipeline.distributed.onebox): each in its workspace with that
    workspace's code first on PYTHONPATH (a cell is a clone of a commit), its log in that
    workspace's .dvc/tmp/mapex-repro/."""
    log_dir = log_dir or root / ".dvc" / "tmp" / "mapex-repro"
    log_dir.mkdir(parents=True, exist_ok=True)
    files: dict[str, tuple[Path, IO[bytes]]] = {}
    total = len(items)
    count = {"ended": 0}
    result = ReproResult()
    env = {k: v for k, v in os.environ.items() if k != "DVC_STAGE"}

    def launch(item: StageItem) -> Process:
        cwd, dvc_name, item_env, where = root, item.name, env, log_dir
        if places is not None:
            cwd, dvc_name = places[item.name]
            where = cwd / ".dvc" / "tmp" / "mapex-repro"
            where.mkdir(parents=True, exist_ok=True)
            item_env = {
                **env,
                "PATH": f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}",
                "PYTHONPATH": os.pathsep.join(p for p in (str(cwd), env.get("PYTHONPATH", "")) if p),
            }
        path = where / f"{_safe_name(dvc_name)}.log"
        fh = open(path, "wb")  # noqa: SIM115 (closed when the item ends)
        files[item.name] = (path, fh)
        return subprocess.Popen(
            [_dvc_bin(), "--wait-for-lock", "repro", "--single-item", dvc_name],
            cwd=cwd,
            stdout=fh,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=item_env,
            # a process group of its own, so that Ctrl-C reaches each item once, from here: DVC
            # ignores SIGINT while its stage's command runs and counts on the command getting it,
            # as a terminal's Ctrl-C does to a whole group (stop_group below)
            start_new_session=True,
        )

    def started(item: StageItem) -> None:
        echo(f"start  {item.name}")

    def finished(item: StageItem, rc: int, seconds: float) -> None:
        path, fh = files.pop(item.name)
        fh.close()
        text = path.read_text(errors="replace")
        outcome = outcome_of(text, rc)
        result.results.append(ItemResult(item.name, rc, seconds, outcome, path))
        count["ended"] += 1
        echo(f"[{count['ended']}/{total}] {outcome:<9} {item.name} ({seconds:.1f} s)")
        if rc != 0:
            tail = "\n".join(text.rstrip().splitlines()[-30:])
            echo(f"{item.name} exited with {rc}; the end of its output ({path}):\n{tail}")

    def stop_command(p: Process, sig: int) -> None:
        # the signal to the stage's command only, not to DVC (the group's leader): DVC killed, or
        # interrupted while it releases its locks, would leave them behind
        pgid = p.pid  # type: ignore[attr-defined]  (a Popen in a session of its own: its group is its pid)
        for pid in group_members(pgid) or ():
            if pid != pgid:
                try:
                    os.kill(pid, sig)
                except ProcessLookupError:
                    pass

    def stop_group(p: Process, sig: int) -> None:
        pgid = p.pid  # type: ignore[attr-defined]
        if sig == signal.SIGINT or group_members(pgid) is None:
            # SIGINT as a terminal's Ctrl-C (DVC ignores it while the command runs); without /proc
            # the whole group is all there is to signal
            os.killpg(pgid, sig)
            return
        # SIGTERM: the command stops at a safe point, keeping its checkpoint, and exits 143
        stop_command(p, sig)

    def on_term(signum, frame):
        raise Terminated

    t0 = time.monotonic()
    old_term = signal.signal(signal.SIGTERM, on_term)
    try:
        _, result.not_started = run_items(
            items, jobs, launch, finished=finished, started=started, stop=stop_group, again=stop_command
        )
    finally:
        signal.signal(signal.SIGTERM, old_term)
        for _, fh in files.values():
            fh.close()
        result.seconds = time.monotonic() - t0
    return result


def summary_table(result: ReproResult) -> str:
    """The items as they ended: outcome and wall seconds each, then the whole run's wall time."""
    width = max([len("stage item"), *(len(r.name) for r in result.results)])
    lines = [f"{'stage item':<{width}}  {'outcome':<9}  {'s':>7}"]
    lines += [f"{r.name:<{width}}  {r.outcome:<9}  {r.seconds:>7.1f}" for r in result.results]
    busy = sum(r.seconds for r in result.results)
    lines.append(f"{len(result.results)} items in {result.seconds:.1f} s wall ({busy:.1f} s of items side by side)")
    return "\n".join(lines)
