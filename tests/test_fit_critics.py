"""Post-hoc critics (pipeline.critics.posthoc), critic fidelity (pipeline.critics.fidelity) and their stages.

Known answers: with a constant reward r and no terminal state, Q = r / (1 - gamma) whatever
the policy; with every transition terminal, Q = r; with reward = action and a constant
target policy c, Q(s, a) = a + gamma * c / (1 - gamma). The stages are run through the real
`mapex` typer app on a tiny specialist trained in a temp dir.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from pipeline.core.buffer import load_buffer
from pipeline.core.checkpoint import load_critics, save_policy
from pipeline.core.nets import Actor
from pipeline.core.specialist import load_slot
from pipeline.critics.fidelity import discounted_returns, score_critics, scored_states, tail_horizon
from pipeline.critics.posthoc import fit_posthoc_critics
from pipeline.params.fit_critics import FitCriticsParams
from stages.cli import app

FAST = dict(batch_size=64, lr=1e-2, gamma=0.5, tau=0.1, target_update_freq=1, hidden_sizes=[32, 32], device="cpu")


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Tiny nets and batches: a second intra-op thread only adds overhead on a shared CPU."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def synthetic_buffer(n: int, reward, terminated, truncated, rng, obs_dim: int = 3, act_dim: int = 2) -> dict:
    """n transitions between random states with a fixed reward vector per row."""
    return {
        "obs": rng.normal(size=(n, obs_dim)).astype(np.float32),
        "action": rng.uniform(-1, 1, (n, act_dim)).astype(np.float32),
        "reward": np.broadcast_to(np.asarray(reward, np.float32), (n, len(reward))).copy(),
        "next_obs": rng.normal(size=(n, obs_dim)).astype(np.float32),
        "terminated": np.asarray(terminated, bool),
        "truncated": np.asarray(truncated, bool),
        "episode": np.zeros(n, np.int64),
        "episode_step": np.arange(n, dtype=np.int32),
    }


def fit(data, policy, cfg, seed: int = 1):
    return fit_posthoc_critics(
        data, policy, [0, 1], cfg, np.random.default_rng(seed), torch.Generator().manual_seed(seed)
    )


def q_at(critic, data) -> torch.Tensor:
    with torch.no_grad():
        return critic.twin_min(torch.from_numpy(data["obs"]), torch.from_numpy(data["action"]))


def constant_actor(c: float, obs_dim: int = 1) -> Actor:
    actor = Actor(obs_dim, 1, [4], [-1.0], [1.0])
    with torch.no_grad():
        for p in actor.net.parameters():
            p.zero_()
        actor.net[-1].bias.fill_(float(np.arctanh(c)))
    return actor


# ---------------------------------------------------------------------------- fitting


def test_constant_reward_converges_to_geometric_sum():
    # Half the rows are time-limit cuts: they must bootstrap like any other row. Treating
    # them as terminal would give r / (1 - gamma / 2) = (1.33, -2.67) instead of (2, -4).
    rng = np.random.default_rng(0)
    n = 256
    data = synthetic_buffer(n, (1.0, -2.0), np.zeros(n), rng.random(n) < 0.5, rng)
    out = fit(data, Actor(3, 2, [8], [-1, -1], [1, 1]), FitCriticsParams(steps=400, **FAST))
    q = q_at(out.online, data)
    expect = torch.tensor([[2.0], [-4.0]])
    assert torch.allclose(q.mean(dim=1, keepdim=True), expect, atol=0.05)
    assert (q - expect).abs().max() < 0.25


def test_all_terminal_gives_immediate_reward():
    rng = np.random.default_rng(0)
    n = 256
    data = synthetic_buffer(n, (1.0, -2.0), np.ones(n), np.zeros(n), rng)
    q = q_at(fit(data, Actor(3, 2, [8], [-1, -1], [1, 1]), FitCriticsParams(steps=400, **FAST)).online, data)
    assert torch.allclose(q.mean(dim=1), torch.tensor([1.0, -2.0]), atol=0.05)


@pytest.mark.parametrize("c", [0.8, -0.8])
def test_target_action_comes_from_the_given_policy(c):
    # One state, reward_0 = a, reward_1 = 1, never terminal: Q_0(s, a) = a + gamma * c / (1 - gamma).
    rng = np.random.default_rng(0)
    n = 512
    a = rng.uniform(-1, 1, (n, 1)).astype(np.float32)
    data = {
        "obs": np.zeros((n, 1), np.float32),
        "action": a,
        "reward": np.concatenate([a, np.ones_like(a)], axis=1),
        "next_obs": np.zeros((n, 1), np.float32),
        "terminated": np.zeros(n, bool),
        "truncated": np.zeros(n, bool),
        "episode": np.zeros(n, np.int64),
        "episode_step": np.arange(n, dtype=np.int32),
    }
    cfg = FitCriticsParams(steps=400, policy_noise=0.0, **FAST)
    out = fit(data, constant_actor(c), cfg)
    grid = torch.linspace(-1, 1, 5)[:, None]
    with torch.no_grad():
        q = out.online.twin_min(torch.zeros(5, 1), grid)
    assert torch.allclose(q[0], grid[:, 0] + c, atol=0.05)  # gamma c / (1 - gamma) = c at gamma 0.5
    assert torch.allclose(q[1], torch.full((5,), 2.0), atol=0.05)


def test_fitting_is_deterministic_given_the_generators():
    rng = np.random.default_rng(3)
    data = synthetic_buffer(64, (0.5, 1.0), np.zeros(64), np.zeros(64), rng)
    policy = Actor(3, 2, [8], [-1, -1], [1, 1])
    cfg = FitCriticsParams(steps=20, **FAST)  # smoothing noise on: the torch generator matters too
    a, b, other = fit(data, policy, cfg, seed=5), fit(data, policy, cfg, seed=5), fit(data, policy, cfg, seed=6)
    for key, value in a.online.state_dict().items():
        assert torch.equal(value, b.online.state_dict()[key])
        assert torch.equal(a.target.state_dict()[key], b.target.state_dict()[key])
    assert not torch.equal(a.online.weights[0], other.online.weights[0])


def test_stops_when_fidelity_stops_improving_and_keeps_the_best_weights():
    """A scripted error: improves for 3 checks, then 4 checks that do not beat the best by
    min_improvement (one of them slightly better: kept, still counted as stale). With patience
    4 the fit stops at the 7th check and returns the weights of the best check."""
    rng = np.random.default_rng(0)
    data = synthetic_buffer(64, (0.5, 1.0), np.zeros(64), np.zeros(64), rng)
    script = iter([0.9, 0.6, 0.5, 0.52, 0.499, 0.51, 0.55, 0.1])
    snapshots = {}

    def error(critic):
        e = next(script)
        snapshots[e] = {k: v.clone() for k, v in critic.state_dict().items()}
        return e

    cfg = FitCriticsParams(steps=1000, check_every=10, patience=4, min_improvement=0.01, **FAST)
    out = fit_posthoc_critics(
        data,
        Actor(3, 2, [8], [-1, -1], [1, 1]),
        [0, 1],
        cfg,
        np.random.default_rng(1),
        torch.Generator().manual_seed(1),
        error=error,
    )
    assert [c.step for c in out.checks] == [10, 20, 30, 40, 50, 60, 70]
    assert (out.steps, out.best_step) == (70, 50)
    for key, value in out.online.state_dict().items():
        assert torch.equal(value, snapshots[0.499][key])


def test_without_checks_it_runs_exactly_the_steps():
    rng = np.random.default_rng(0)
    data = synthetic_buffer(64, (0.5, 1.0), np.zeros(64), np.zeros(64), rng)
    calls = []
    cfg = FitCriticsParams(steps=30, check_every=0, **FAST)
    out = fit_posthoc_critics(
        data,
        Actor(3, 2, [8], [-1, -1], [1, 1]),
        [0, 1],
        cfg,
        np.random.default_rng(1),
        torch.Generator().manual_seed(1),
        error=lambda c: calls.append(1) or 0.0,
    )
    assert (out.steps, out.best_step, out.checks, calls) == (30, 30, (), [])


# ---------------------------------------------------------------------------- fidelity


def naive_returns(reward: np.ndarray, episode: np.ndarray, gamma: float) -> np.ndarray:
    g = np.zeros(reward.shape)
    for t in range(len(reward)):
        for i in range(t, len(reward)):
            if episode[i] != episode[t]:
                break
            g[t] += gamma ** (i - t) * reward[i]
    return g


def episodes_buffer(rng) -> dict:
    """Episodes of length 5 (terminated), 10 (truncated), 6 (unfinished); obs[:, 0] = row index."""
    lengths, n = (5, 10, 6), 21
    episode = np.repeat(np.arange(3), lengths)
    terminated, truncated = np.zeros(n, bool), np.zeros(n, bool)
    terminated[4], truncated[14] = True, True
    obs = np.zeros((n, 2), np.float32)
    obs[:, 0] = np.arange(n)
    data = synthetic_buffer(n, (0.0, 0.0), terminated, truncated, rng, obs_dim=2, act_dim=1)
    data.update(obs=obs, episode=episode, reward=rng.normal(size=(n, 2)).astype(np.float32))
    return data


class LookupCritic:
    """A fake ensemble whose prediction at s is scale * (the exact return stored for s's row)."""

    def __init__(self, returns: np.ndarray, scale: float = 1.0):
        self.returns, self.scale = torch.as_tensor(returns.T, dtype=torch.float32), scale

    def twin_min(self, obs, action):
        return self.scale * self.returns[:, obs[:, 0].long()]


def test_discounted_returns_match_naive_loop():
    rng = np.random.default_rng(1)
    r = rng.normal(size=(30, 3))
    assert np.allclose(discounted_returns(r, 0.9), naive_returns(r, np.zeros(30), 0.9))


def test_tail_horizon():
    assert tail_horizon(0.99, 0.01) == 459  # 0.99^459 < 0.01 <= 0.99^458
    assert tail_horizon(0.5, 0.25) == 2
    assert tail_horizon(0.5, 0.1) == 4


def test_scored_states_drop_the_tail_of_cut_episodes():
    data = episodes_buffer(np.random.default_rng(2))
    g_all = naive_returns(data["reward"].astype(np.float64), data["episode"], 0.5)
    # H = 4: terminated keeps 5 rows, truncated 10 - 4 + 1 = 7, unfinished 6 - 4 + 1 = 3.
    idx, g, n_ep = scored_states(data, 0.5, episodes=3, horizon=4)
    assert n_ep == 3
    assert idx.tolist() == [0, 1, 2, 3, 4, *range(5, 12), 15, 16, 17]
    assert np.allclose(g, g_all[idx])
    idx, _, n_ep = scored_states(data, 0.5, episodes=2, horizon=4)
    assert (n_ep, len(idx)) == (2, 10)


def test_exact_critic_scores_perfectly_and_half_critic_shows_its_bias():
    data = episodes_buffer(np.random.default_rng(2))
    g_all = naive_returns(data["reward"].astype(np.float64), data["episode"], 0.5)
    policy = Actor(2, 1, [4], [-1.0], [1.0])
    exact = score_critics(data, LookupCritic(g_all), [0, 1], policy, 0.5, episodes=3, tail_tolerance=0.1)
    assert exact.horizon == 4
    for f in exact.per_objective:
        assert f.n_states == 15
        assert f.pearson == pytest.approx(1.0)
        assert f.rel_error == pytest.approx(0.0, abs=1e-6)
    half = score_critics(data, LookupCritic(g_all[:, [1]], 0.5), [1], policy, 0.5, episodes=3, tail_tolerance=0.1)
    (f,) = half.per_objective
    assert f.objective == 1
    assert f.rel_error == pytest.approx(0.5, abs=1e-6)
    assert f.mean_q == pytest.approx(0.5 * f.mean_g, abs=1e-6)
    assert half.to_dict()["obj1"]["n_states"] == 15


# ---------------------------------------------------------------------------- stages

TINY_PARAMS = """\
env:
  id: mo-halfcheetah-v5
  max_episode_steps: 100
td3:
  learning_starts: 260
  batch_size: 64
  hidden_sizes: [32, 32]
train_specialist:
  total_steps: 300
  device: cpu
fit_critics:
  steps: 50
  batch_size: 64
  hidden_sizes: [32, 32]
  device: cpu
  check_every: 20
  fidelity_episodes: 2
  tail_tolerance: 0.5
critic_fidelity:
  episodes: 2
  tail_tolerance: 0.5
"""

runner = CliRunner()


def mapex(*args: str):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A tiny specialist (objective 0) with joint critics, its post-hoc critics and joint fidelity."""
    root = tmp_path_factory.mktemp("fit_critics")
    params = root / "params.yaml"
    params.write_text(TINY_PARAMS)
    res = mapex("train-specialist", "--objective", 0, "--out", root, "--params", params)
    (root / "obj0").rename(root / "spec")
    assert res.exit_code == 0, res.output
    res = mapex(
        "fit-critics", "--objective", 0, "--specialist", root / "spec", "--out", root / "posthoc", "--params", params
    )
    assert res.exit_code == 0, res.output
    res = mapex(
        "critic-fidelity",
        "--objective",
        0,
        "--specialist",
        root / "spec",
        "--out",
        root / "joint.json",
        "--params",
        params,
    )
    assert res.exit_code == 0, res.output
    res = mapex(
        "critic-fidelity",
        "--objective",
        0,
        "--specialist",
        root / "spec",
        "--critics",
        root / "posthoc" / "critics.pt",
        "--out",
        root / "posthoc.json",
        "--params",
        params,
    )
    assert res.exit_code == 0, res.output
    return root


def test_fit_critics_stage_writes_loadable_posthoc_critics(run_dir):
    online, target, meta = load_critics(run_dir / "posthoc" / "critics.pt")
    assert meta["source"] == "posthoc"
    assert (meta["buffer_objective"], meta["objectives"], meta["env_id"]) == (0, [0, 1], "mo-halfcheetah-v5")
    assert meta["hidden_sizes"] == [32, 32] and meta["params"]["fit_critics"]["steps"] == 50
    assert online.n_members == target.n_members == 4
    assert not torch.equal(online.weights[0], target.weights[0])  # targets lag the online critics
    obs = torch.zeros(7, meta["obs_dim"])
    assert online.twin_min(obs, torch.zeros(7, meta["act_dim"])).shape == (2, 7)


@pytest.mark.parametrize("path, source", [("posthoc.json", "posthoc"), ("joint.json", "joint")])
def test_fidelity_metrics_files(run_dir, path, source):
    import json

    m = json.loads((run_dir / path).read_text())
    # 3 truncated 100-step episodes; last 2 scored; H = 69 at gamma 0.99, tolerance 0.5 -> 32 states each.
    assert (m["buffer_objective"], m["n_episodes"], m["horizon"], m["gamma"]) == (0, 2, 69, 0.99)
    assert (m["source"], m["actor"]) == (source, "target")
    for key in ("obj0", "obj1"):
        assert m[key]["n_states"] == 64
        assert -1.0 <= m[key]["pearson"] <= 1.0
        assert m[key]["rel_error"] >= 0.0 and isinstance(m[key]["mean_g"], float)


def test_joint_critics_discount_is_read_from_their_td3_section(run_dir, tmp_path):
    """Joint critics are scored at the discount their specialist trained with: meta
    params["td3"]["gamma"]. Critics whose meta has no td3 section (the layout before it
    existed: the agent's keys under train_specialist) are refused, naming the file."""
    import json

    obj = torch.load(run_dir / "spec" / "critics.pt", weights_only=True)
    assert obj["meta"]["source"] == "joint" and obj["meta"]["params"]["td3"]["gamma"] == 0.99
    for name, params, code in (
        ("g09.pt", obj["meta"]["params"] | {"td3": obj["meta"]["params"]["td3"] | {"gamma": 0.9}}, 0),
        ("old.pt", {"train_specialist": obj["meta"]["params"]["td3"]}, 2),
    ):
        torch.save(obj | {"meta": obj["meta"] | {"params": params}}, tmp_path / name)
        out = tmp_path / f"{name}.json"
        res = mapex(
            "critic-fidelity",
            "--objective",
            0,
            "--specialist",
            run_dir / "spec",
            "--critics",
            tmp_path / name,
            "--out",
            out,
            "--params",
            run_dir / "params.yaml",
        )
        assert res.exit_code == code, res.output
        if code == 0:
            assert json.loads(out.read_text())["gamma"] == 0.9
        else:
            assert f"{tmp_path / name}: metadata does not record the critics' discount" in res.stderr
            assert not out.exists()


def test_fit_csv_records_every_check_and_meta_the_fit(run_dir):
    lines = (run_dir / "posthoc" / "fit.csv").read_text().splitlines()
    assert lines[0] == "step,loss,mean_rel_error"
    assert [int(line.split(",")[0]) for line in lines[1:]] == [20, 40, 50]  # every 20 steps, and the last
    _, _, meta = load_critics(run_dir / "posthoc" / "critics.pt")
    errors = [float(line.split(",")[2]) for line in lines[1:]]
    assert meta["fit"]["steps"] == 50 and meta["fit"]["best_error"] == pytest.approx(min(errors), rel=1e-5)
    assert meta["fit"]["best_step"] == [20, 40, 50][errors.index(min(errors))]
    data, attrs = load_buffer(run_dir / "spec" / "buffer.zarr")
    assert meta["buffer_checksums"] == attrs["checksums"]


def test_posthoc_and_joint_critics_share_one_format(run_dir):
    joint = torch.load(run_dir / "spec" / "critics.pt", weights_only=True)
    post = torch.load(run_dir / "posthoc" / "critics.pt", weights_only=True)
    assert joint.keys() == post.keys()
    assert post["meta"].keys() - joint["meta"].keys() == {"buffer_checksums", "fit"}  # post-hoc only
    assert joint["meta"].keys() <= post["meta"].keys()
    assert joint["meta"]["source"] == "joint" and post["meta"]["source"] == "posthoc"
    for part in ("online", "target"):
        assert {k: v.shape for k, v in joint[part].items()} == {k: v.shape for k, v in post[part].items()}


def test_stage_fits_with_the_specialists_target_actor(run_dir):
    spec = load_slot(run_dir / "spec", 0)
    saved = torch.load(run_dir / "spec" / "policy.pt", weights_only=True)
    for key, value in spec.actor_target.state_dict().items():
        assert torch.equal(value, saved["actor_target"][key])
    assert not torch.equal(spec.actor_target.net[0].weight, spec.actor.net[0].weight)


def bad_specialist(run_dir: Path, tmp_path: Path, kind: str) -> Path:
    spec = tmp_path / "spec"
    shutil.copytree(run_dir / "spec", spec)
    if kind == "missing buffer":
        shutil.rmtree(spec / "buffer.zarr")
    elif kind == "truncated buffer":
        chunk = next(p for p in (spec / "buffer.zarr" / "reward").rglob("*") if p.is_file() and p.name != "zarr.json")
        chunk.unlink()
    elif kind == "other env policy":
        actor = Actor(11, 3, [32, 32], [-1.0] * 3, [1.0] * 3)
        meta = {
            "env_id": "mo-hopper-2obj-v5",
            "obs_dim": 11,
            "act_dim": 3,
            "n_objectives": 2,
            "action_low": [-1.0] * 3,
            "action_high": [1.0] * 3,
            "hidden_sizes": [32, 32],
            "objective": 0,
        }
        save_policy(spec / "policy.pt", actor, meta, actor)
    return spec


@pytest.mark.parametrize(
    "kind, objective, names, says",
    [
        ("missing buffer", 0, "buffer.zarr", "no Zarr group"),
        ("truncated buffer", 0, "buffer.zarr", "reward"),
        ("other env policy", 0, "policy.pt", "env_id"),
        ("ok", 5, "buffer.zarr", "objectives 0..1"),
        ("ok", 1, "buffer.zarr", "expected 1"),  # obj-0 buffer passed as specialist 1
    ],
)
@pytest.mark.parametrize("command", ["fit-critics", "critic-fidelity"])
def test_bad_inputs_exit_2_name_the_file_and_write_nothing(run_dir, tmp_path, command, kind, objective, names, says):
    spec = bad_specialist(run_dir, tmp_path, kind)
    out = tmp_path / "out"
    target = out if command == "fit-critics" else out / "fidelity.json"
    res = mapex(
        command, "--objective", objective, "--specialist", spec, "--out", target, "--params", run_dir / "params.yaml"
    )
    assert res.exit_code == 2, res.output
    assert str(spec / names) in res.stderr and says in res.stderr
    assert not out.exists()


def test_fit_critics_refuses_a_specialist_of_another_seed(run_dir, tmp_path):
    res = mapex(
        "fit-critics",
        "--objective",
        0,
        "--seed",
        7,
        "--specialist",
        run_dir / "spec",
        "--out",
        tmp_path / "out",
        "--params",
        run_dir / "params.yaml",
    )
    assert res.exit_code == 2, res.output
    assert str(run_dir / "spec" / "policy.pt") in res.stderr and "expected --seed 7" in res.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "change, says",
    [
        ({"seed": 3}, "critics of seed 3"),
        ({"buffer_checksums": {"obs": "0"}}, "fitted on a different buffer"),
        ({"buffer_checksums": None}, "without 'buffer_checksums'"),
    ],
)
def test_critic_fidelity_refuses_posthoc_critics_of_another_run(run_dir, tmp_path, change, says):
    other = tmp_path / "critics.pt"
    obj = torch.load(run_dir / "posthoc" / "critics.pt", weights_only=True)
    obj["meta"] = {k: v for k, v in (obj["meta"] | change).items() if v is not None}
    torch.save(obj, other)
    res = mapex(
        "critic-fidelity",
        "--objective",
        0,
        "--specialist",
        run_dir / "spec",
        "--critics",
        other,
        "--out",
        tmp_path / "f.json",
        "--params",
        run_dir / "params.yaml",
    )
    assert res.exit_code == 2, res.output
    assert str(other) in res.stderr and says in res.stderr
    assert not (tmp_path / "f.json").exists()


def test_critic_fidelity_rejects_critics_of_another_env(run_dir, tmp_path):
    other = tmp_path / "critics.pt"
    obj = torch.load(run_dir / "spec" / "critics.pt", weights_only=True)
    obj["meta"] = obj["meta"] | {"env_id": "mo-walker2d-v5"}
    torch.save(obj, other)
    res = mapex(
        "critic-fidelity",
        "--objective",
        0,
        "--specialist",
        run_dir / "spec",
        "--critics",
        other,
        "--out",
        tmp_path / "f.json",
        "--params",
        run_dir / "params.yaml",
    )
    assert res.exit_code == 2 and str(other) in res.stderr and "env_id" in res.stderr
    assert not (tmp_path / "f.json").exists()


@pytest.mark.parametrize(
    "bad",
    [
        "steps: 0\n  batch_size: 64\n  hidden_sizes: [32, 32]",
        "steps: 50\n  batch_size: 64\n  hidden_sizes: [32, 0]",
        "steps: 50\n  learning_rate: 0.1\n  hidden_sizes: [32, 32]",  # unknown key
    ],
)
def test_invalid_fit_critics_params_exit_2_before_anything_is_written(run_dir, tmp_path, bad):
    params = tmp_path / "params.yaml"
    text = TINY_PARAMS.replace(
        "fit_critics:\n  steps: 50\n  batch_size: 64\n  hidden_sizes: [32, 32]", "fit_critics:\n  " + bad
    )
    assert text != TINY_PARAMS
    params.write_text(text)
    out = tmp_path / "out"
    res = mapex("fit-critics", "--objective", 0, "--specialist", run_dir / "spec", "--out", out, "--params", params)
    assert res.exit_code == 2 and str(params) in res.stderr and "fit_critics." in res.stderr
    assert not out.exists()
