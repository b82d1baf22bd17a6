"""pipeline.core.drive: one loop for every run (resume, safe points, SIGTERM, divergence, progress)."""

from __future__ import annotations

import os
import signal

import pytest

from pipeline.core.drive import drive, run_to_end
from pipeline.core.finite import TrainingDiverged
from pipeline.core.resume import Checkpoint
from pipeline.core.signals import Stopped


class Counter:
    """A toy run: `n` steps of 10 units each, checkpointed every `every` steps."""

    def __init__(self, n: int = 5, every: int = 2, nan_at: int | None = None, term_at: int | None = None):
        self.n, self.every, self.nan_at, self.term_at = n, every, nan_at, term_at
        self.t, self.started, self.finished, self.closed = 0, False, False, False
        self.on_progress = None

    @property
    def done(self) -> bool:
        return self.t >= self.n

    def start(self) -> None:
        self.started = True

    def step(self) -> None:
        self.t += 1
        if self.t == self.nan_at:
            raise TrainingDiverged("a weight", "NaN", self.t)
        if self.t == self.term_at:
            os.kill(os.getpid(), signal.SIGTERM)

    def finish(self) -> None:
        self.finished = True

    def progress(self) -> tuple[int, str]:
        return 10 * self.t, f"t {self.t}"

    def checkpoint_due(self) -> bool:
        return self.t > 0 and self.t % self.every == 0 and not self.done

    def where(self) -> str:
        return f"step {self.t}"

    def state_dict(self) -> dict:
        return {"t": self.t}

    def load_state_dict(self, state: dict) -> None:
        self.t = int(state["t"])

    def close(self) -> None:
        self.closed = True


def go(tmp_path, run, said=None, sent=None, saved=None, **kw):
    ckpt = Checkpoint(tmp_path / "state.pt", "fp", (said if said is not None else []).append)
    sent = sent if sent is not None else []
    return drive(
        lambda: run,
        ckpt,
        who="toy seed 0",
        stage="toy",
        resumed=lambda r: f"resuming from step {r.t}",
        save=lambda r: (saved if saved is not None else []).append(r.t),
        send=lambda kind, value: sent.append((kind, value)),
        **kw,
    )


def test_a_run_goes_to_its_end_reports_progress_and_clears_its_checkpoint(tmp_path):
    sent, saved = [], []
    run = go(tmp_path, Counter(), sent=sent, saved=saved)
    assert run.started and run.finished and run.closed and saved == [5]
    assert sum(v for k, v in sent if k == "steps") == 50
    assert [v for k, v in sent if k == "returns"] == [f"t {t}" for t in range(1, 6)]
    assert not (tmp_path / "state.pt").exists()


def test_sigterm_checkpoints_at_the_next_safe_point_and_the_rerun_resumes(tmp_path):
    with pytest.raises(Stopped) as info:
        go(tmp_path, Counter(term_at=3))
    path = tmp_path / "state.pt"
    assert str(info.value) == f"toy seed 0: SIGTERM: checkpoint written at step 3 ({path}); rerun to resume"
    said, saved = [], []
    run = Counter()
    go(tmp_path, run, said=said, saved=saved)
    assert said == ["resuming from step 3"] and not run.started and saved == [5]


def test_without_checkpoints_sigterm_stops_and_says_why(tmp_path):
    with pytest.raises(Stopped, match=r"^toy seed 0: SIGTERM at step 2: no checkpoint \(not MuJoCo\)$"):
        go(tmp_path, Counter(term_at=2), problem="not MuJoCo")
    assert not (tmp_path / "state.pt").exists()


def test_divergence_names_the_stage_and_the_last_good_checkpoint(tmp_path):
    with pytest.raises(TrainingDiverged) as info:
        go(tmp_path, Counter(nan_at=3))
    path = tmp_path / "state.pt"
    assert str(info.value) == f"toy: a weight is NaN at step 3 (the last good checkpoint is kept: {path})"
    with pytest.raises(TrainingDiverged) as info:
        go(tmp_path / "none", Counter(nan_at=1), periodic=False)
    assert str(info.value) == "toy: a weight is NaN at step 1"


def test_hooks_run_after_every_step_and_run_to_end_is_the_bare_loop(tmp_path):
    seen = []
    go(tmp_path, Counter(), hooks=[lambda r: seen.append(r.t)])
    assert seen == [1, 2, 3, 4, 5]
    run = run_to_end(Counter(), [lambda r: seen.append(-r.t)])
    assert run.started and run.finished and not run.closed and seen[5:] == [-1, -2, -3, -4, -5]


def test_a_checkpoint_of_other_library_versions_is_not_resumed(tmp_path, monkeypatch):
    """The "libraries changed" line is true: the fingerprint holds the numeric libraries' versions."""
    import pipeline.core.resume as resume
    from pipeline.core.provenance import NUMERIC_LIBRARIES, library_versions

    assert {"torch", "numpy", "mujoco", "gymnasium"} <= set(NUMERIC_LIBRARIES)
    config = {"seed": 0}
    fp = resume.run_fingerprint("extract", config, "cpu")
    assert resume.run_fingerprint("extract", config, "cpu") == fp
    said = []
    Checkpoint(tmp_path / "state.pt", fp, said.append).save({"t": 3})
    for lib in ("torch", "mujoco"):
        other = {**library_versions(), lib: "0.0.1"}
        monkeypatch.setattr(resume, "library_versions", lambda other=other: other)
        fp_other = resume.run_fingerprint("extract", config, "cpu")
        assert fp_other != fp, lib
        assert Checkpoint(tmp_path / "state.pt", fp_other, said.append).load() is None
        assert "libraries changed" in said[-1]
    monkeypatch.undo()
    assert Checkpoint(tmp_path / "state.pt", fp, said.append).load() == {"t": 3}
