"""pipeline.core.workers: parts in side-by-side processes, their messages relayed in order, the
first failure stopping the rest, SIGTERM passed on to the workers, and workers that stop once
their stage process is gone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.core.signals import Stopped, sigterm_deferred, stop_requested
from pipeline.core.workers import WorkerError, run_side_by_side

# The part functions below run in spawned processes, which import them from this module.


def count_part(name: str, n: int, *, send) -> None:
    for i in range(n):
        send(name, i)


def failing_part(delay_s: float, *, send) -> None:
    time.sleep(delay_s)
    raise ValueError("objective 7 is out of range")


def slow_part(marker: str, *, send) -> None:
    send("started", os.getpid())
    time.sleep(30)
    Path(marker).write_text("finished")


def slow_or_failing_part(kind: str, marker: str, *, send) -> None:
    if kind == "slow":
        slow_part(marker, send=send)
    else:
        failing_part(1.0, send=send)


def dying_part(*, send) -> None:
    os._exit(3)


def write_pid(pid_file: str) -> None:
    tmp = Path(pid_file + ".tmp")
    tmp.write_text(str(os.getpid()))
    tmp.replace(pid_file)  # whole or absent


def forever_part(pid_file: str, *, send) -> None:
    write_pid(pid_file)
    while True:
        send("tick")
        time.sleep(0.05)


def silent_part(pid_file: str, *, send) -> None:
    """Works without a word (as a worker saving its artifacts does)."""
    write_pid(pid_file)
    time.sleep(60)


def chatty_or_dying_part(kind: str, *, send) -> None:
    if kind == "chatty":
        for _ in range(2000):
            send("tick")
            time.sleep(0.01)
    else:
        time.sleep(0.5)
        os._exit(3)


def stoppable_or_quick_part(kind: str, name: str, marker: str, *, send) -> None:
    """'quick': returns at once (leaving `marker`); else, once the quick part has finished,
    steps until SIGTERM asks it to stop, then stops at its next safe point as a stage's run does."""
    if kind == "quick":
        Path(marker).write_text("done")
        return
    deadline = time.monotonic() + 60
    while not Path(marker).exists() and time.monotonic() < deadline:  # spawned workers start in any order
        time.sleep(0.02)
    time.sleep(1.0)  # and let the quick worker report and exit before the SIGTERM
    with sigterm_deferred():
        send("started")  # only now would a SIGTERM be deferred
        while not stop_requested():
            time.sleep(0.02)
        raise Stopped(f"{name}: SIGTERM: checkpoint written at step 7")


class BadInput(ValueError):
    pass


def bad_input_part(*, send) -> None:
    raise BadInput("params.yaml: train_specialist.processes must be >= 1, got 0")


def test_messages_arrive_in_order_per_part():
    got: dict[int, list] = {0: [], 1: []}
    run_side_by_side(count_part, [("a", 50), ("b", 30)], lambda i, m: got[i].append(m))
    assert got[0] == [("a", i) for i in range(50)]
    assert got[1] == [("b", i) for i in range(30)]


def test_a_failing_part_stops_the_others_and_names_itself(tmp_path):
    marker = tmp_path / "finished"
    started = time.monotonic()
    with pytest.raises(WorkerError) as info:
        run_side_by_side(slow_or_failing_part, [("slow", str(marker)), ("fail", "")])
    assert info.value.part == 1
    assert "ValueError: objective 7 is out of range" in str(info.value)
    assert "Traceback" in info.value.detail and "failing_part" in info.value.detail
    assert time.monotonic() - started < 25  # the slow part was stopped, not waited for
    assert not marker.exists()


def test_a_part_that_dies_without_a_word_is_a_failure():
    with pytest.raises(WorkerError, match="exited with code 3") as info:
        run_side_by_side(dying_part, [()], None)
    assert info.value.part == 0


def test_a_dead_worker_is_noticed_while_another_keeps_talking():
    started = time.monotonic()
    with pytest.raises(WorkerError, match="exited with code 3") as info:
        run_side_by_side(chatty_or_dying_part, [("chatty",), ("dying",)])
    assert info.value.part == 1
    assert time.monotonic() - started < 15  # not after the chatty part's 20 s


def test_an_expected_error_comes_without_a_traceback():
    with pytest.raises(WorkerError) as info:
        run_side_by_side(bad_input_part, [()], expected=(BadInput,))
    assert info.value.expected and info.value.detail == ""
    assert str(info.value) == "params.yaml: train_specialist.processes must be >= 1, got 0"


def test_sigterm_is_passed_on_and_each_part_stops_at_its_safe_point(tmp_path):
    """SIGTERM to the process running run_side_by_side (here this one, while it waits): each
    running worker gets it and stops at its next safe point; a part that had finished counts
    as done; then Stopped, one line per stopped part. This process's handler is restored."""
    before = signal.getsignal(signal.SIGTERM)
    started: set[int] = set()

    def on_message(i: int, message: tuple) -> None:
        started.add(i)
        if started == {0, 2}:
            os.kill(os.getpid(), signal.SIGTERM)  # deferred: run_side_by_side is waiting

    with pytest.raises(Stopped) as info:
        marker = str(tmp_path / "quick_done")
        run_side_by_side(
            stoppable_or_quick_part, [("run", "a", marker), ("quick", "b", marker), ("run", "c", marker)], on_message
        )
    assert str(info.value) == "a: SIGTERM: checkpoint written at step 7\nc: SIGTERM: checkpoint written at step 7"
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.parametrize("part", ["forever_part", "silent_part"], ids=["talking", "silent"])
def test_workers_stop_when_the_stage_process_is_killed(part, tmp_path):
    """SIGKILL the process running run_side_by_side: its worker stops too, at once on Linux
    (the kernel kills it), else at its next send (only the talking one then)."""
    if part == "silent_part" and not sys.platform.startswith("linux"):
        pytest.skip("a silent worker is stopped by PR_SET_PDEATHSIG, Linux only")
    pid_file = tmp_path / "worker.pid"
    script = (
        "import sys; sys.path.insert(0, sys.argv[1]); import test_workers as t; "
        "from pipeline.core.workers import run_side_by_side; "
        f"run_side_by_side(t.{part}, [(sys.argv[2],)])"
    )
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}
    stage = subprocess.Popen([sys.executable, "-c", script, str(Path(__file__).parent), str(pid_file)], env=env)
    deadline = time.time() + 60
    while not pid_file.exists() and time.time() < deadline:
        time.sleep(0.05)
    assert pid_file.exists(), "the worker never started"
    worker = int(pid_file.read_text())
    stage.send_signal(signal.SIGKILL)
    stage.wait()
    deadline = time.time() + 10
    while time.time() < deadline and _alive(worker):
        time.sleep(0.05)
    assert not _alive(worker), "the worker outlived its stage process"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (exited, not yet reaped by init) counts as gone
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_oversubscription_is_named():
    from pipeline.core.workers import oversubscribed

    cores = len(os.sched_getaffinity(0))
    assert oversubscribed(1, 1) is None
    assert oversubscribed(cores, 1) is None
    warning = oversubscribed(cores, 2)
    assert warning is not None and f"{cores} processes x 2 torch threads on {cores} cores" in warning


# ---------------------------------------------------------------- start="fork"

INHERITED = {"value": "set before the fork"}  # a forked worker sees this module's state as it was


def inherited_part(key: str, *, send) -> None:
    send(INHERITED[key], os.getpid())


def sigterm_disposition_part(*, send) -> None:
    send(signal.getsignal(signal.SIGTERM) == signal.SIG_DFL, stop_requested())


def test_forked_parts_inherit_the_parent_and_relay_in_order(monkeypatch):
    """start="fork": the workers are copies of this process (a value set after import is seen,
    which a spawned worker would not see), and messages arrive as from spawned ones."""
    monkeypatch.setitem(INHERITED, "value", "changed after import")
    got: dict[int, list] = {0: [], 1: []}
    run_side_by_side(inherited_part, [("value",), ("value",)], lambda i, m: got[i].append(m), start="fork")
    assert [m[0] for m in got[0] + got[1]] == ["changed after import"] * 2
    assert len({m[1] for m in got[0] + got[1]} | {os.getpid()}) == 3  # two other processes
    got = {0: [], 1: []}
    run_side_by_side(count_part, [("a", 50), ("b", 30)], lambda i, m: got[i].append(m), start="fork")
    assert got[0] == [("a", i) for i in range(50)] and got[1] == [("b", i) for i in range(30)]


def test_a_forked_worker_leaves_the_parents_deferred_sigterm():
    """Forked inside run_side_by_side's sigterm_deferred block, a worker starts with SIGTERM's
    default action and no block active, as a spawned one does (so a SIGTERM passed on stops a
    worker that has no safe points of its own)."""
    got: list = []
    run_side_by_side(sigterm_disposition_part, [()], lambda i, m: got.append(m), start="fork")
    assert got == [(True, False)]


def test_a_failing_forked_part_is_reported_and_an_unknown_start_refused():
    with pytest.raises(WorkerError, match="objective 7 is out of range") as info:
        run_side_by_side(failing_part, [(0.0,)], start="fork")
    assert info.value.part == 0
    with pytest.raises(ValueError, match="start='forkserver': expected one of"):
        run_side_by_side(count_part, [("a", 1)], start="forkserver")
