"""`mapex repro --jobs N`: stage items side by side in one DVC workspace.

The scheduler (pipeline.distributed.local.run_items) on fake processes: it never runs more than
N items, never starts an item before its upstream has finished, starts nothing new after a
failure, and interrupts the running items on Ctrl-C. Then the command on a toy DVC project whose
two first items can only both succeed when they run at the same time (each waits for the
other's flag file), so the test shows they did, without timing anything.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import textwrap
import time
from pathlib import Path

import pytest
import yaml
from support.dvc_repo import BIN, DVC, ROOT

from pipeline.distributed.local import ItemResult, ReproResult, outcome_of, run_items, summary_table
from pipeline.distributed.workspace import StageItem


def item(name: str, *upstream: str) -> StageItem:
    return StageItem(name, name.split("@")[0], tuple(upstream), (), "")


class FakeProcess:
    """Ends with `rc` after `polls` polls, or once it has had `ends_on` signals; records them."""

    def __init__(self, rc: int = 0, polls: int = 2, ends_on: int | None = None):
        self.rc, self.polls, self.signals, self.ends_on = rc, polls, [], ends_on

    def poll(self):
        if self.ends_on is not None and len(self.signals) >= self.ends_on:
            return self.rc
        self.polls -= 1
        return self.rc if self.polls <= 0 else None

    def send_signal(self, sig):
        self.signals.append(sig)

    def wait(self, timeout=None):
        return self.rc


def run_fake(items, jobs, rcs=None, polls=None):
    rcs, polls = rcs or {}, polls or {}
    live: set[str] = set()
    peak = [0]
    order: list[str] = []
    done: list[str] = []

    def launch(it):
        # every upstream item has ended (with exit code 0) before this one starts
        assert all(u in done for u in it.upstream if u in {i.name for i in items}), (it.name, done)
        live.add(it.name)
        peak[0] = max(peak[0], len(live))
        order.append(it.name)
        return FakeProcess(rcs.get(it.name, 0), polls.get(it.name, 2))

    def finished(it, rc, s):
        live.discard(it.name)
        if rc == 0:
            done.append(it.name)

    ended, not_started = run_items(items, jobs, launch, finished=finished, sleep=lambda s: None)
    return order, peak[0], ended, not_started


CHAIN = [
    item("train@0"),
    item("train@1"),
    item("extract@0", "train@0"),
    item("extract@1", "train@1"),
    item("evaluate@0", "extract@0"),
    item("evaluate@1", "extract@1"),
    item("report", "evaluate@0", "evaluate@1"),
]


@pytest.mark.parametrize("jobs", [1, 2, 3])
def test_at_most_jobs_items_run_and_each_after_its_upstream(jobs):
    order, peak, ended, not_started = run_fake(CHAIN, jobs, polls={"train@0": 5})
    assert sorted(order) == sorted(i.name for i in CHAIN) and not not_started
    assert peak == min(jobs, 2)  # two independent chains: never more than two items ready at once
    assert order[-1] == "report"
    assert all(rc == 0 for _, rc, _ in ended)


def test_with_one_job_the_items_run_in_the_order_given():
    order, peak, _, _ = run_fake(CHAIN, 1)
    assert order == [i.name for i in CHAIN] and peak == 1


def test_after_a_failure_nothing_new_starts_and_the_running_item_finishes():
    # extract@0 fails while extract@1 runs (slowly): extract@1 finishes, nothing after either starts
    order, _, ended, not_started = run_fake(CHAIN, 2, rcs={"extract@0": 1}, polls={"extract@1": 6})
    assert {i.name: rc for i, rc, _ in ended} == {"train@0": 0, "train@1": 0, "extract@0": 1, "extract@1": 0}
    assert set(not_started) == {"evaluate@0", "evaluate@1", "report"}
    assert "evaluate@1" not in order


def interrupted_run(ends_on: list[int], exc: type[BaseException] = KeyboardInterrupt, ctrl_c_again_at: int = 0):
    """run_items on CHAIN, 2 jobs, interrupted (`exc`) at the third poll sleep; its two running items
    end once they have had ends_on[i] signals; a fake clock advances 1 s a sleep, again_after 5 s.
    Returns the processes and the number of sleeps."""
    procs: list[FakeProcess] = []
    kinds = iter(ends_on)

    def launch(it):
        procs.append(FakeProcess(polls=10**9, ends_on=next(kinds)))
        return procs[-1]

    t = {"now": 0.0, "n": 0}

    def sleep(s):
        t["n"] += 1
        t["now"] += 1.0
        if t["n"] == 3:
            raise exc
        if t["n"] == ctrl_c_again_at:
            raise KeyboardInterrupt
        assert t["n"] < 100, "still waiting: the items were never stopped"

    with pytest.raises(exc):
        run_items(CHAIN, 2, launch, sleep=sleep, clock=lambda: t["now"], again_after=5.0)
    return procs, t["n"]


def test_an_interrupt_reaches_every_running_item_then_propagates():
    procs, _ = interrupted_run([1, 1])
    assert len(procs) == 2 and all(p.signals == [signal.SIGINT] for p in procs)


def test_a_lost_ctrl_c_is_sent_again_until_the_item_ends():
    # the second item's command misses the first SIGINT (a shell between fork and exec) and ends
    # on the second, which comes again_after (5 s) later; the first item got one and ended
    procs, sleeps = interrupted_run([1, 2])
    assert procs[0].signals == [signal.SIGINT] and procs[1].signals == [signal.SIGINT, signal.SIGINT]
    assert sleeps == 3 + 5
    # a second Ctrl-C while waiting passes it on at once rather than leaving the items running
    procs, sleeps = interrupted_run([1, 2], ctrl_c_again_at=4)
    assert procs[1].signals == [signal.SIGINT, signal.SIGINT] and sleeps == 4


def test_sigterm_goes_once_and_is_waited_for():
    from pipeline.distributed.local import Terminated

    # a stage stops on SIGTERM at its next safe point: no second one however long it takes
    procs: list[FakeProcess] = []

    def launch(it):
        procs.append(FakeProcess(polls=10**9))
        return procs[-1]

    t = {"n": 0}

    def sleep(s):
        t["n"] += 1
        if t["n"] == 3:
            raise Terminated
        if t["n"] == 40:
            for p in procs:
                p.polls = 0  # the stages reached their safe points

    with pytest.raises(Terminated):
        run_items(CHAIN, 2, launch, sleep=sleep, clock=lambda: float(t["n"]), again_after=5.0)
    assert all(p.signals == [signal.SIGTERM] for p in procs) and t["n"] == 40


def test_jobs_below_one_is_refused():
    with pytest.raises(ValueError, match="jobs must be at least 1"):
        run_items(CHAIN, 0, lambda it: FakeProcess())


def test_outcome_and_summary_read_what_dvc_printed():
    assert outcome_of("Stage 'a@0' didn't change, skipping\n", 0) == "unchanged"
    assert outcome_of("Stage 'a@0' is cached - skipping run, checking out outputs\n", 0) == "restored"
    assert outcome_of("Running stage 'a@0':\n> echo\n", 0) == "ran"
    assert outcome_of("Stage 'a@0' didn't change, skipping\n", 2) == "failed"
    table = summary_table(
        ReproResult([ItemResult("extract@mapex-td3-0", 0, 12.5, "ran"), ItemResult("b", 1, 1.0, "failed")], [], 13.0)
    )
    lines = table.splitlines()
    assert lines[1].split() == ["extract@mapex-td3-0", "ran", "12.5"] and lines[2].split() == ["b", "failed", "1.0"]
    assert lines[-1].startswith("2 items in 13.0 s wall")


# ------------------------------------------------------------------ the command on a toy project

# a@0 and a@1 each leave a flag and wait (up to 60 s) for the other's: both succeed only when
# they run at the same time. b@S copies a@S's output; c reads both b's, and exits 1 when FAIL exists.
TOY = textwrap.dedent(
    """\
    stages:
      a:
        matrix:
          s: [0, 1]
        cmd: >-
          touch flag${item.s} &&
          for i in $(seq 600); do [ -e flag$((1-${item.s})) ] && break; sleep 0.1; done &&
          [ -e flag$((1-${item.s})) ] && echo ${item.s} > "a${item.s}.txt"
        outs: ["a${item.s}.txt"]
      b:
        matrix:
          s: [0, 1]
        cmd: cat a${item.s}.txt > b${item.s}.txt
        deps: ["a${item.s}.txt"]
        outs: ["b${item.s}.txt"]
      c:
        cmd: test ! -e FAIL && cat b0.txt b1.txt > c.txt
        deps: [b0.txt, b1.txt]
        outs: [c.txt]
    """
)


def mapex(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [str(BIN / "python"), "-m", "stages.cli", *args], cwd=cwd, env=env, capture_output=True, text=True
    )


@pytest.fixture
def toy(tmp_path: Path) -> Path:
    (tmp_path / "dvc.yaml").write_text(TOY)
    (tmp_path / ".gitignore").write_text("flag*\nFAIL\n")
    for cmd in (["git", "init", "-q"], [DVC, "init", "-q"]):
        subprocess.run(cmd, cwd=tmp_path, check=True, capture_output=True)
    return tmp_path


@pytest.mark.integration  # real dvc processes, about 25 s
def test_independent_items_run_side_by_side_and_dvc_ends_up_to_date(toy):
    r = mapex(["repro", "--jobs", "2", "--root", str(toy)], toy)
    assert r.returncode == 0, r.stderr
    assert (toy / "c.txt").read_text() == "0\n1\n"
    lock = yaml.safe_load((toy / "dvc.lock").read_text())["stages"]
    assert set(lock) == {"a@0", "a@1", "b@0", "b@1", "c"}
    status = subprocess.run([DVC, "status"], cwd=toy, capture_output=True, text=True)
    assert "up to date" in status.stdout, status.stdout
    # a second run runs nothing: every item unchanged
    again = mapex(["repro", "-j", "2", "--root", str(toy)], toy)
    assert again.returncode == 0 and len(re.findall(r"^\[\d/5\] unchanged ", again.stderr, re.M)) == 5, again.stderr


@pytest.mark.integration  # real dvc processes, about 25 s
def test_a_failed_item_is_named_with_its_output_and_fails_the_command(toy):
    (toy / "FAIL").touch()
    r = mapex(["repro", "-j", "2", "--root", str(toy)], toy)
    assert r.returncode == 1
    assert "error: c failed" in r.stderr and "exited with" in r.stderr
    assert (toy / ".dvc" / "tmp" / "mapex-repro" / "c.log").is_file()
    assert (toy / "b0.txt").is_file() and not (toy / "c.txt").exists()


@pytest.mark.integration  # real dvc processes, about 25 s
def test_an_unknown_target_is_named(toy):
    r = mapex(["repro", "-j", "2", "--root", str(toy), "nope"], toy)
    assert r.returncode == 2 and "'nope' is no stage or stage item" in r.stderr


@pytest.mark.integration  # real dvc processes, about 10 s
@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_or_sigterm_stops_the_running_items_cleanly(toy, sig, code):
    # a@0 alone waits (up to 60 s) for a flag nobody leaves: it is still running when the signal comes
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "PYTHONPATH": str(ROOT)}
    p = subprocess.Popen(
        [str(BIN / "python"), "-m", "stages.cli", "repro", "-j", "2", "--root", str(toy), "a@0"],
        cwd=toy,
        env=env,
        stderr=subprocess.PIPE,
        text=True,
        # as from a terminal: SIGINT at its default, whatever this test process inherited (a process
        # started with SIGINT ignored keeps it ignored, and Python then raises no KeyboardInterrupt;
        # under the full suite an earlier test leaves the xdist worker so)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    for _ in range(600):  # the item's own shell has started once its flag exists
        if (toy / "flag0").exists():
            break
        time.sleep(0.05)
    assert (toy / "flag0").exists()
    p.send_signal(sig)
    _, err = p.communicate(timeout=30)  # well before the item's own 60 s
    assert p.returncode == code, err
    assert "stopped" in err and not (toy / "a0.txt").exists()
    # DVC let go of the item's outputs: no write lock is left behind
    rwlock = toy / ".dvc" / "tmp" / "rwlock"
    assert not rwlock.exists() or not json.loads(rwlock.read_text() or "{}").get("write")
