"""Keep-best selection of TD3 specialists (train_specialist.keep_best_every > 0).

The schedule of the checks; that they leave the training itself bitwise as it is with
keep-best off; that the kept actor is exactly the one of its recorded step and its score the
best finite one (the earlier on ties); that a score is the mean deterministic return on the
specialist's own objective over episodes seeded from (seed, objective, check index); resume;
what the stage writes; and the params' validation. Tiny Hopper runs (a few tenths of a second
each); every comparison is between two runs on this machine, no digest is pinned.
"""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest
import torch

import pipeline.specialists.keep_best as keep_best
from pipeline.core.artifacts import torch_load_checked
from pipeline.core.buffer import FIELDS
from pipeline.core.checkpoint import POLICY_FORMAT
from pipeline.core.drive import run_to_end
from pipeline.core.envs import env_spec, make_env
from pipeline.params import ParamsError, section
from pipeline.params.td3 import TD3Params
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.specialists.keep_best import (
    keep_best_due,
    keep_best_hook,
    keep_best_score,
    keep_best_seeds,
    keep_best_steps,
)
from pipeline.specialists.td3_training import SpecialistsRun

ENV, CAP = "mo-hopper-2obj-v5", 40
# learning from step 100; checks every 40 steps past it: 120, 160, 200, 240, 280 and the last, 300
TD3 = TD3Params(learning_starts=100, batch_size=32, hidden_sizes=[16, 16], buffer_size=180)
CFG = TrainSpecialistParams(
    total_steps=300,
    checkpoint_every=70,
    device="cpu",
    keep_best_every=40,
    keep_best_episodes=2,
)
CHECK_STEPS = [120, 160, 200, 240, 280, 300]
JOBS = [(0, 0), (0, 1)]


@pytest.fixture(autouse=True)
def one_thread():
    """One torch thread, as the `mapex` command uses by default (bitwise comparisons need one count)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def make_run(cfg: TrainSpecialistParams = CFG, jobs=JOBS) -> SpecialistsRun:
    envs = [make_env(ENV, CAP) for _ in jobs]
    return SpecialistsRun(envs, env_spec(envs[0], ENV, CAP), TD3, cfg, jobs, torch.device("cpu"))


def to_the_end(run: SpecialistsRun, on_checkpoint=None, fresh: bool = True):
    """Step `run` to its end (pipeline.core.drive.run_to_end), `on_checkpoint(run)` where a
    checkpoint is due; its results."""
    hooks = [keep_best_hook]
    if on_checkpoint is not None:
        hooks.append(lambda run: on_checkpoint(run) if run.checkpoint_due() else None)
    return run_to_end(run, hooks, fresh).results()


def train(cfg: TrainSpecialistParams = CFG, jobs=JOBS, on_checkpoint=None):
    """(the finished run, its results)."""
    run = make_run(cfg, jobs)
    results = to_the_end(run, on_checkpoint)
    run.close()
    return run, results


def same_state_dict(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def final_actors(run: SpecialistsRun, s: int) -> tuple[dict, dict]:
    """Specialist s's final actor and target actor (what results() gives with keep-best off)."""
    return run.state.actor.unstack(s).state_dict(), run.state.actor_target.unstack(s).state_dict()


# --- schedule and params -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("every", "expected"),
    [
        (40, CHECK_STEPS),
        (50, [150, 200, 250, 300]),  # the last step is a multiple: checked once
        (100, [200, 300]),  # learning_starts itself (the untrained actor) is not checked
        (300, [300]),  # only the final actor: the same as keep-best off
        (0, []),
    ],
)
def test_checks_follow_multiples_past_learning_starts_and_the_last_step(every, expected):
    cfg = CFG.model_copy(update={"keep_best_every": every})
    assert keep_best_steps(cfg, TD3.learning_starts) == expected
    assert [t for t in range(1, 400) if keep_best_due(cfg, TD3.learning_starts, t)] == expected


def test_checks_start_past_the_learning_starts_given():
    """The schedule's start is td3.learning_starts, passed in: not a fixed step."""
    assert keep_best_steps(CFG, 150) == [160, 200, 240, 280, 300]
    assert keep_best_steps(CFG, 1) == [40, 80, 120, 160, 200, 240, 280, 300]
    assert not keep_best_due(CFG, 160, 160) and keep_best_due(CFG, 159, 160)


def test_a_run_checks_at_the_scheduled_steps_and_defaults_are_off():
    assert TrainSpecialistParams().keep_best_every == 0 and TrainSpecialistParams().keep_best_episodes == 3
    _, results = train()
    for r in results:
        assert [t for t, _ in r.keep_best.checks] == CHECK_STEPS
        assert (r.keep_best.every, r.keep_best.episodes) == (40, 2)
    _, off = train(CFG.model_copy(update={"keep_best_every": 0}))
    assert all(r.keep_best is None for r in off)


@pytest.mark.parametrize(
    ("values", "expected"),
    [
        ({"keep_best_every": 400}, "keep_best_every (400) must be <= total_steps (300)"),
        ({"keep_best_every": -1}, "train_specialist.keep_best_every = -1: Input should be greater than or equal to 0"),
        (
            {"keep_best_episodes": 0},
            "train_specialist.keep_best_episodes = 0: Input should be greater than or equal to 1",
        ),
    ],
)
def test_bad_keep_best_params_are_named(values, expected):
    base = CFG.model_dump() | values
    with pytest.raises(ParamsError) as info:
        section({"train_specialist": base}, "train_specialist", TrainSpecialistParams)
    assert expected in str(info.value)


def test_keep_best_every_may_equal_total_steps():
    assert TrainSpecialistParams(**(CFG.model_dump() | {"keep_best_every": 300})).keep_best_every == 300


# --- training untouched ------------------------------------------------------------------


def test_keep_best_leaves_training_bitwise_as_without_it():
    """Buffers, critics, the final actors, the episode history and every RNG stream (torch's
    global one included) end the same with keep-best on as off; only the returned actor may differ."""
    on_run = make_run()
    on = to_the_end(on_run)
    sa = on_run.state_dict()  # now: torch's RNG is global, and the next run seeds it again
    off_run = make_run(CFG.model_copy(update={"keep_best_every": 0}))
    off = to_the_end(off_run)
    sb = off_run.state_dict()
    for s, (x, y) in enumerate(zip(on, off, strict=True)):
        for name in FIELDS:
            assert x.buffer[name].tobytes() == y.buffer[name].tobytes(), name
        for part in ("critic", "critic_target"):
            assert same_state_dict(getattr(x, part).state_dict(), getattr(y, part).state_dict()), part
        assert [(e.end_step, e.returns.tobytes()) for e in x.episodes] == [
            (e.end_step, e.returns.tobytes()) for e in y.episodes
        ]
        for a, b in zip(final_actors(on_run, s), final_actors(off_run, s)):
            assert same_state_dict(a, b)
        # keep-best off returns the final actor
        assert same_state_dict(y.actor.state_dict(), final_actors(off_run, s)[0])
    assert torch.equal(sa["rng"]["torch"], sb["rng"]["torch"])
    assert sa["rng"]["numpy"] == sb["rng"]["numpy"]
    assert all(torch.equal(a, b) for a, b in zip(sa["rng"]["noise"], sb["rng"]["noise"]))


# --- which actor is kept -------------------------------------------------------------------

# Scripted scores per objective, one per check (steps CHECK_STEPS): objective 0 peaks at 160
# and ties there at 240 (the earlier is kept), non-finite scores are never kept (+inf
# included); objective 1 peaks at 280.
SCRIPT = {
    0: [1.0, 5.0, math.nan, 5.0, math.inf, 2.0],
    1: [-math.inf, 0.0, 1.0, 2.0, 9.0, 3.0],
}
KEPT = {0: (160, 5.0), 1: (280, 9.0)}


def scripted(monkeypatch, script=SCRIPT) -> None:
    calls = {k: 0 for k in script}

    def score(actor, env, objective, seeds):
        i = calls[objective]
        calls[objective] += 1
        return script[objective][i]

    monkeypatch.setattr(keep_best, "keep_best_score", score)  # the name keep_best_hook calls


def test_the_kept_actor_is_the_one_of_its_recorded_step(monkeypatch):
    """The returned actor and target actor are bitwise those a run stopped at the kept step
    ends with; the critics and buffer stay the final ones."""
    scripted(monkeypatch)
    run, results = train()
    for s, r in enumerate(results):
        k = r.objective
        assert [x for _, x in r.keep_best.checks] == pytest.approx(SCRIPT[k], nan_ok=True)
        assert (r.keep_best.step, r.keep_best.score) == KEPT[k]
        stopped, _ = train(CFG.model_copy(update={"total_steps": KEPT[k][0], "keep_best_every": 0}))
        actor, target = final_actors(stopped, s)
        assert same_state_dict(r.actor.state_dict(), actor)
        assert same_state_dict(r.actor_target.state_dict(), target)
        final_actor, _ = final_actors(run, s)
        assert not same_state_dict(r.actor.state_dict(), final_actor)  # the final actor moved on


def test_no_finite_score_keeps_the_final_actor(monkeypatch):
    scripted(monkeypatch, {0: [math.nan] * 6, 1: [math.inf, -math.inf, math.nan, math.nan, math.inf, math.nan]})
    run, results = train()
    for s, r in enumerate(results):
        assert r.keep_best.step is None and r.keep_best.score is None
        assert len(r.keep_best.checks) == len(CHECK_STEPS)
        assert same_state_dict(r.actor.state_dict(), final_actors(run, s)[0])


def test_a_non_finite_weight_scores_nan_without_stepping_the_env():
    env = make_env(ENV, CAP)
    actor = make_run(jobs=[(0, 0)]).state.actor.unstack(0)
    assert math.isfinite(keep_best_score(actor, env, 0, [1, 2]))
    with torch.no_grad():
        actor.net[0].weight[0, 0] = math.nan
    env.step = None  # any episode would fail
    assert math.isnan(keep_best_score(actor, env, 0, [1, 2]))


def episode_return(actor, objective: int, seed: int) -> float:
    """One deterministic episode on a fresh env, written out here: the undiscounted return on `objective`."""
    env = make_env(ENV, CAP)
    obs, _ = env.reset(seed=seed)
    total, done = 0.0, False
    while not done:
        with torch.no_grad():
            a = actor(torch.as_tensor(obs, dtype=torch.float32)[None])[0].numpy()
        obs, r, term, trunc, _ = env.step(a)
        total += float(r[objective])
        done = term or trunc
    env.close()
    return total


def test_scores_are_deterministic_returns_on_the_own_objective():
    """Stacked specialists: each kept score is the best finite check score, the first check
    that reached it is kept, and re-running the kept actor (and the final one) on the seeds of
    its check on a fresh env, alone, gives the recorded score."""
    run, results = train()
    for s, r in enumerate(results):
        kb, (seed, k) = r.keep_best, JOBS[s]
        scores = [x for _, x in kb.checks]
        assert all(math.isfinite(x) for x in scores)
        assert kb.score == max(scores)
        index = scores.index(kb.score)
        assert kb.step == kb.checks[index][0]
        seeds = keep_best_seeds(seed, k, index, CFG.keep_best_episodes)
        assert len(set(seeds)) == CFG.keep_best_episodes
        mean = np.mean([episode_return(r.actor, k, x) for x in seeds])
        assert mean == pytest.approx(kb.score, rel=1e-9, abs=1e-9)
        other = np.mean([episode_return(r.actor, 1 - k, x) for x in seeds])
        assert other != pytest.approx(kb.score, rel=1e-6)  # the other objective would not give it
        final = final_actors(run, s)[0]
        actor = run.state.actor.unstack(s)
        actor.load_state_dict(final)
        last = keep_best_seeds(seed, k, len(scores) - 1, CFG.keep_best_episodes)
        assert np.mean([episode_return(actor, k, x) for x in last]) == pytest.approx(scores[-1], rel=1e-9, abs=1e-9)
    # the checks' seeds differ between specialists and between checks
    assert keep_best_seeds(0, 0, 0, 2) != keep_best_seeds(0, 1, 0, 2) != keep_best_seeds(0, 0, 1, 2)


# --- resume --------------------------------------------------------------------------------


def assert_same_results(a, b) -> None:
    for x, y in zip(a, b, strict=True):
        for name in FIELDS:
            assert x.buffer[name].tobytes() == y.buffer[name].tobytes(), name
        for part in ("actor", "actor_target", "critic", "critic_target"):
            assert same_state_dict(getattr(x, part).state_dict(), getattr(y, part).state_dict()), part
        assert x.keep_best == y.keep_best


def test_a_resumed_run_keeps_the_same_actor_and_checks():
    """Restored before any check (step 70) and after three (210, a best snapshot kept): the
    run ends with the same kept actors, scores and check history as the uninterrupted one."""
    saved: dict[int, bytes] = {}

    def keep(run) -> None:
        buf = io.BytesIO()
        torch.save(run.state_dict(), buf)
        saved[run.t] = buf.getvalue()

    _, reference = train(on_checkpoint=keep)
    assert sorted(saved) == [70, 140, 210, 280]
    for t, n_checks in ((70, 0), (210, 3)):
        state = torch.load(io.BytesIO(saved[t]), weights_only=True)
        assert [len(x["check_step"]) for x in state["keep_best"]] == [n_checks] * len(JOBS)
        assert all((x["best"] is None) == (n_checks == 0) for x in state["keep_best"])
        run = make_run()
        run.load_state_dict(state)
        results = to_the_end(run, fresh=False)
        run.close()
        assert_same_results(results, reference)


def test_a_state_without_its_checks_is_refused():
    run = make_run()
    for _ in range(130):
        run.step()
    state = run.state_dict()
    state["keep_best"] = state["keep_best"][:1]
    with pytest.raises(ValueError, match="keep-best checks of 1 specialists"):
        make_run().load_state_dict(state)


# --- the stage -----------------------------------------------------------------------------


def test_stage_records_the_kept_step_score_and_every_check(tmp_path, write_params, cli):
    params = write_params(
        tmp_path,
        {"env": {"id": ENV, "max_episode_steps": CAP}, "td3": TD3.model_dump(), "train_specialist": CFG.model_dump()},
    )
    result = cli("train-specialist", "--seed", 0, "--out", tmp_path / "out", "--params", params)
    assert result.exit_code == 0, result.stderr
    for k in (0, 1):
        out = tmp_path / "out" / f"obj{k}"
        assert sorted(p.name for p in out.iterdir()) == [
            "buffer.zarr",
            "critics.pt",
            "keep_best.csv",
            "policy.pt",
            "returns.csv",
        ]
        meta = torch_load_checked(out / "policy.pt", POLICY_FORMAT, 1)["meta"]
        kb = meta["keep_best"]
        assert [t for t, _ in kb["checks"]] == CHECK_STEPS
        assert kb["score"] == max(x for _, x in kb["checks"])
        assert kb["step"] == next(t for t, x in kb["checks"] if x == kb["score"])
        with open(out / "keep_best.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        assert [int(r["step"]) for r in rows] == CHECK_STEPS
        assert [int(r["kept"]) for r in rows] == [int(t == kb["step"]) for t in CHECK_STEPS]
        np.testing.assert_allclose([float(r["score"]) for r in rows], [x for _, x in kb["checks"]], rtol=1e-5)
        assert f"obj {k} (" in result.stderr and f"keep-best kept the actor of step {kb['step']}" in result.stderr


def test_a_loop_without_the_keep_best_hook_is_refused():
    """Keep-best is a hook on the loop: a run stepped without it, with keep-best on, hands on no
    actors (its results name the missing check) rather than the final ones unannounced."""
    run = make_run()
    run_to_end(run)
    with pytest.raises(RuntimeError, match="keep_best_hook"):
        run.results()
    run.close()
