"""The MORL/D baseline (pipeline/baselines/morld.py, stages/morld.py), on tiny Swimmer runs.

Skipped as a whole when morl-baselines (the optional `baselines` extra) is not installed.
Checks: the exported actor computes MOSAC's deterministic action; the light archive keeps what
MORL/D's archive keeps; training and evaluation episodes stop at the cap; the stage writes a
population our loader accepts, with honestly evaluated returns; a run killed after two
exchanges resumes to the same bits as an uninterrupted one; a missing library is one clear
error, and the core modules import without it.
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import typer
from torch import nn
from typer.testing import CliRunner

pytest.importorskip("morl_baselines")

from morl_baselines.common.pareto import ParetoArchive  # noqa: E402
from morl_baselines.single_policy.ser.mosac_continuous_action import MOSACActor  # noqa: E402

import pipeline.baselines.morld  # noqa: E402
from pipeline.baselines.morld import (  # noqa: E402
    EVAL_STREAM,
    INSTALL_HINT,
    ActorArchive,
    BaselinesMissing,
    MorldRun,
    actor_from_mosac,
    require_morl_baselines,
)
from pipeline.core.drive import run_to_end  # noqa: E402
from pipeline.core.envs import env_spec, make_env  # noqa: E402
from pipeline.core.nets import hidden_sizes_of  # noqa: E402
from pipeline.core.population import Member, actor_state, load_population, member_actor  # noqa: E402
from pipeline.evaluation.episodes import eval_seeds, evaluate_policy  # noqa: E402
from pipeline.params.morld import MorldParams  # noqa: E402
from stages.morld import CHECKPOINT  # noqa: E402
from stages.morld import morld as morld_stage

REPO = Path(__file__).resolve().parents[1]
ENV = "mo-swimmer-v5"  # the cheapest env; it never terminates, so every episode runs to the cap
CAP = 30
EPISODES = 2
MORLD = {
    "total_frames": 400,
    "exchange_every": 100,
    "pop_size": 2,
    "hidden_sizes": [16, 16],
    "batch_size": 32,
    "learning_starts": 50,
    "buffer_size": 1000,
    "update_passes": 1,
    "front_eval_episodes": 1,
    "eval_episodes": EPISODES,
    "checkpoint_every": 1,
    "device": "cpu",
}


def random_mosac_actor(obs_dim: int, low: list[float], high: list[float], net_arch: list[int], seed: int) -> MOSACActor:
    """A MOSAC actor with every weight and bias random (its own init zeroes the biases)."""
    actor = MOSACActor(
        (obs_dim,), (len(low),), 2, np.array(low, np.float32), np.array(high, np.float32), net_arch=net_arch
    )
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in actor.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.7)
    return actor


# -- actor conversion -------------------------------------------------------------------------


def test_exported_actor_reproduces_mosac_deterministic_action():
    low, high = [-1.0, -2.0, 0.0], [1.0, 0.5, 3.0]  # asymmetric bounds: scale and bias both matter
    mosac = random_mosac_actor(8, low, high, [16, 8], seed=0)
    ours = actor_from_mosac(mosac)
    assert hidden_sizes_of(ours) == [16, 8]
    obs = torch.randn(512, 8, generator=torch.Generator().manual_seed(1)) * 3
    with torch.no_grad():
        _, _, theirs = mosac.get_action(obs)  # the third output: tanh(mean) * action_scale + action_bias
        mean, _ = mosac(obs)
        by_hand = torch.tanh(mean) * mosac.action_scale + mosac.action_bias
        mine = ours(obs)
    torch.testing.assert_close(mine, theirs, rtol=0, atol=1e-6)
    torch.testing.assert_close(theirs, by_hand, rtol=0, atol=0)
    assert (mine >= torch.tensor(low)).all() and (mine <= torch.tensor(high)).all()
    # and through the population format: the state dict loads into pipeline.core.nets.Actor as a member
    member = Member(
        "morld", None, 0, [], None, [0.0, 0.0], [0.0, 0.0], 1, 0, hidden_sizes_of(ours), actor_state(ours), "pop0"
    )
    rebuilt = member_actor(member, {"obs_dim": 8, "act_dim": 3, "action_low": low, "action_high": high})
    with torch.no_grad():
        torch.testing.assert_close(rebuilt(obs), mine, rtol=0, atol=0)


def test_conversion_refuses_actors_it_cannot_copy_exactly():
    mosac = random_mosac_actor(4, [-1.0], [1.0], [8], seed=2)
    mosac.latent_pi = nn.Sequential(nn.Linear(4, 8), nn.Tanh())
    with pytest.raises(ValueError, match="Linear, ReLU"):
        actor_from_mosac(mosac)


def test_actor_archive_keeps_what_morld_archive_keeps():
    """Same sequence of evaluations (with ties and duplicates): same entries, same order; the
    light archive stores the actor's weights, no agent and no buffer."""
    _, filter_fn = require_morl_baselines()
    rng = np.random.default_rng(3)
    theirs, ours = ParetoArchive(), ActorArchive(filter_fn, lambda: (7, 700))
    points = np.round(rng.normal(size=(40, 2)), 1)  # rounding makes ties and duplicates
    for i, point in enumerate(points):
        agent = SimpleNamespace(
            id=i,
            weights=np.array([0.5, 0.5]),
            wrapped=SimpleNamespace(actor=random_mosac_actor(3, [-1.0], [1.0], [4], i)),
        )
        theirs.add(agent, point)
        ours.add(agent, point)
    assert [tuple(e) for e in ours.evaluations] == [tuple(e) for e in theirs.evaluations]
    assert [r.policy for r in ours.individuals] == [c.id for c in theirs.individuals]
    rec = ours.individuals[0]
    assert (rec.exchange, rec.frames) == (7, 700) and set(rec.actor) >= {
        "latent_pi.0.weight",
        "fc_mean.weight",
        "action_scale",
    }


def test_params_checks():
    assert MorldParams().frames() == 4_000_000
    assert MorldParams(total_frames=120_000).frames() == 150_000  # whole exchanges, as MORL/D spends them
    with pytest.raises(ValueError, match="neighborhood_size"):
        MorldParams(pop_size=2, neighborhood_size=2)
    with pytest.raises(ValueError):
        MorldParams(scalarization="tch")


# -- runs -------------------------------------------------------------------------------------


def test_episodes_capped_and_exported_actors_match_agents():
    env = make_env(ENV, CAP)
    spec = env_spec(env, ENV, CAP)
    env.close()
    run = MorldRun(spec, MorldParams(**MORLD), seed=0)
    run_to_end(run)
    assert run.frames == run.env.frames == 400 and run.exchange == 4
    # 100-frame turns of 30-step episodes: 30, 30, 30, 10 (each turn starts a new episode)
    assert run.env.longest_episode == CAP
    assert run.eval_env.longest_episode == CAP
    obs = torch.randn(64, spec.obs_dim, generator=torch.Generator().manual_seed(4))
    exported = {e.name: e for e in run.exported_actors()}
    for i, p in enumerate(run.algo.population):
        with torch.no_grad():
            torch.testing.assert_close(
                exported[f"pop{i}"].actor(obs), p.wrapped.actor.get_action(obs)[2], rtol=0, atol=1e-6
            )


def _stage_app() -> typer.Typer:
    app = typer.Typer()
    app.command()(morld_stage)
    return app


def _invoke(params: Path, out: Path):
    return CliRunner().invoke(_stage_app(), ["--seed", "0", "--out", str(out), "--params", str(params)])


@pytest.fixture(scope="module")
def params_file(tmp_path_factory, write_params) -> Path:
    return write_params(
        tmp_path_factory.mktemp("morld_params"), {"env": {"id": ENV, "max_episode_steps": CAP}, "morld": MORLD}
    )


@pytest.fixture(scope="module")
def finished(tmp_path_factory, params_file) -> Path:
    """An uninterrupted stage run."""
    out = tmp_path_factory.mktemp("morld") / "seed0"
    result = _invoke(params_file, out)
    assert result.exit_code == 0, (result.output, result.exception)
    return out


def test_stage_writes_loadable_population(finished: Path):
    members, meta = load_population(
        finished / "population.pt", ("env_id", "obs_dim", "act_dim", "action_low", "action_high")
    )
    assert (meta["env_id"], meta["obs_dim"], meta["act_dim"], meta["n_objectives"]) == (ENV, 8, 2, 2)
    assert (meta["action_low"], meta["action_high"]) == ([-1.0, -1.0], [1.0, 1.0])
    assert meta["method"] == "morld" and meta["seed"] == 0 and meta["params"]["morld"]["pop_size"] == 2
    assert meta["training_frames"] == 400 and "provenance" not in meta
    names = [m.policy_name for m in members]
    assert names[:2] == ["pop0", "pop1"] and all(n.startswith("archive") for n in names[2:])
    assert names == list(meta["morld_estimates"])
    assert all(m.origin == "morld" and m.objective is None and m.parents == [] for m in members)
    assert all(m.eval_episodes == EPISODES and m.hidden_sizes == [16, 16] and len(m.returns) == 2 for m in members)
    assert all(abs(sum(m.target_weight) - 1) < 1e-9 for m in members)  # MORL/D's L1-normalised weights
    assert [m.env_samples for m in members[:2]] == [400, 400] and [m.iteration for m in members[:2]] == [4, 4]
    assert all(0 <= m.iteration <= 4 and m.env_samples == 100 * m.iteration for m in members)
    # returns are our deterministic evaluation on eval_seeds stream EVAL_STREAM, member i on index i
    envs = [make_env(ENV, CAP) for _ in range(EPISODES)]
    for i in (0, len(members) - 1):
        res = evaluate_policy(member_actor(members[i], meta), envs, eval_seeds(0, EVAL_STREAM, i, EPISODES))
        np.testing.assert_allclose(res.mean, members[i].returns, rtol=1e-5, atol=1e-5)
    with open(finished / "history.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["exchange"]) for r in rows] == [0, 1, 2, 3, 4]
    assert [int(r["frames"]) for r in rows] == [0, 100, 200, 300, 400]
    assert [int(r["trained_policy"]) for r in rows] == [-1, 0, 1, 0, 1]
    assert not (finished / CHECKPOINT).exists()


def test_killed_run_resumes_to_the_same_population(tmp_path: Path, params_file: Path, finished: Path, monkeypatch):
    out = tmp_path / "seed0"
    real_step = MorldRun.step
    calls = {"n": 0}

    class Killed(Exception):
        pass

    def dying_step(self):
        if calls["n"] == 2:
            raise Killed
        calls["n"] += 1
        return real_step(self)

    monkeypatch.setattr(MorldRun, "step", dying_step)
    result = _invoke(params_file, out)
    assert isinstance(result.exception, Killed)
    assert (out / CHECKPOINT).exists() and not (out / "population.pt").exists()
    monkeypatch.setattr(MorldRun, "step", real_step)
    result = _invoke(params_file, out)
    assert result.exit_code == 0, (result.output, result.exception)
    assert "resuming after exchange 2" in result.output
    got, got_meta = load_population(out / "population.pt")
    want, want_meta = load_population(finished / "population.pt")
    assert [m.policy_name for m in got] == [m.policy_name for m in want]
    for a, b in zip(got, want):
        assert (a.returns, a.target_weight, a.iteration, a.env_samples) == (
            b.returns,
            b.target_weight,
            b.iteration,
            b.env_samples,
        )
        assert all(torch.equal(a.actor[k], b.actor[k]) for k in b.actor)
    assert got_meta["morld_estimates"] == want_meta["morld_estimates"]
    assert (out / "history.csv").read_text() == (finished / "history.csv").read_text()
    assert not (out / CHECKPOINT).exists()


def test_sigterm_checkpoints_the_exchange_and_the_rerun_resumes(
    tmp_path: Path, write_params, finished: Path, monkeypatch
):
    """SIGTERM during exchange 2, no periodic checkpoint due: the stage checkpoints once that
    exchange ends, says so in one line and exits with 143; the rerun resumes to the same population."""
    params = write_params(
        tmp_path, {"env": {"id": ENV, "max_episode_steps": CAP}, "morld": MORLD | {"checkpoint_every": 1000}}
    )
    out = tmp_path / "seed0"
    real_step = MorldRun.step
    calls = {"n": 0}

    def sigterm_in_second(self):
        calls["n"] += 1
        if calls["n"] == 2:
            os.kill(os.getpid(), signal.SIGTERM)  # deferred by the stage until its next safe point
        return real_step(self)

    monkeypatch.setattr(MorldRun, "step", sigterm_in_second)
    result = _invoke(params, out)
    assert result.exit_code == 143, (result.output, result.exception)
    line = f"morld seed 0: SIGTERM: checkpoint written at exchange 2 ({out / CHECKPOINT}); rerun to resume"
    assert line in result.output.splitlines() and calls["n"] == 2
    assert not (out / "population.pt").exists()
    monkeypatch.setattr(MorldRun, "step", real_step)
    result = _invoke(params, out)
    assert result.exit_code == 0, (result.output, result.exception)
    assert "resuming after exchange 2" in result.output
    got, _ = load_population(out / "population.pt")
    want, _ = load_population(finished / "population.pt")
    assert [(m.policy_name, m.returns, m.env_samples) for m in got] == [
        (m.policy_name, m.returns, m.env_samples) for m in want
    ]
    for a, b in zip(got, want):
        assert all(torch.equal(a.actor[k], b.actor[k]) for k in b.actor)
    assert (out / "history.csv").read_text() == (finished / "history.csv").read_text()


# -- without the library ----------------------------------------------------------------------


def test_missing_library_is_one_clear_error(tmp_path: Path, params_file: Path, monkeypatch):
    for name in [n for n in sys.modules if n == "morl_baselines" or n.startswith("morl_baselines.")]:
        monkeypatch.setitem(sys.modules, name, None)  # `import morl_baselines...` now raises ImportError
    with pytest.raises(BaselinesMissing, match=r'pip install -e "\.\[baselines\]"'):
        require_morl_baselines()
    result = _invoke(params_file, tmp_path / "out")
    assert result.exit_code == 2
    assert INSTALL_HINT in result.output and "morl-baselines==1.3.0" in result.output
    assert not (tmp_path / "out").exists()  # failed before writing anything


def test_core_modules_import_without_the_library():
    code = (
        "import sys; sys.modules['morl_baselines'] = None\n"
        "import pipeline.baselines.morld, pipeline.params.morld, stages.morld\n"
        "try:\n    pipeline.baselines.morld.require_morl_baselines()\n"
        "except pipeline.baselines.morld.BaselinesMissing as exc:\n    print('missing:', exc)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "missing:" in proc.stdout and INSTALL_HINT in proc.stdout
    assert pipeline.baselines.morld.__name__ == "pipeline.baselines.morld"
