"""Policy-set files (policies.pt, pipeline/core/policyset.py) round-trip, and bad ones are refused
naming the file. Extraction from policy sets through the stages: tests/test_extract_policy_sets.py."""

from __future__ import annotations

import pytest
import torch

from pipeline.core.artifacts import ArtifactError, torch_save_atomic
from pipeline.core.checkpoint import save_policy
from pipeline.core.nets import Actor
from pipeline.core.policyset import load_policy_set, save_policy_set

META = {
    "env_id": "toy",
    "obs_dim": 3,
    "act_dim": 2,
    "n_objectives": 2,
    "action_low": [-1.0, -1.0],
    "action_high": [1.0, 1.0],
    "hidden_sizes": [8],
    "objective": 1,
    "seed": 0,
}


def actor(seed: int) -> Actor:
    torch.manual_seed(seed)
    return Actor(3, 2, [8], [-1.0, -1.0], [1.0, 1.0])


def test_round_trip_keeps_every_actor_and_label(tmp_path):
    actors = [actor(s) for s in range(3)]
    save_policy_set(tmp_path / "policies.pt", actors, ["rl", "pop0", "pop1"], [1.5, None, -2.0], META)
    got = load_policy_set(tmp_path / "policies.pt")
    assert got.names == ["rl", "pop0", "pop1"] and got.fitness == [1.5, None, -2.0]
    assert got.meta["objective"] == 1
    obs = torch.randn(5, 3)
    for a, b in zip(actors, got.actors):
        assert torch.equal(a(obs), b(obs))
    torch.load(tmp_path / "policies.pt", weights_only=True)  # loadable without pickle


def test_a_single_policy_file_is_a_set_of_one(tmp_path):
    a = actor(0)
    save_policy(tmp_path / "policy.pt", a, META)
    got = load_policy_set(tmp_path / "policy.pt")
    assert got.names == ["policy"] and len(got.actors) == 1
    obs = torch.randn(4, 3)
    assert torch.equal(a(obs), got.actors[0](obs))


def test_bad_sets_are_refused(tmp_path):
    with pytest.raises(ValueError, match="unique"):
        save_policy_set(tmp_path / "p.pt", [actor(0), actor(1)], ["a", "a"], [None, None], META)
    with pytest.raises(ValueError, match="lacks"):
        save_policy_set(tmp_path / "p.pt", [actor(0)], ["a"], [None], {"env_id": "toy"})
    path = tmp_path / "policies.pt"
    torch_save_atomic(
        {
            "format": "mapex.policy_set",
            "format_version": 1,
            "meta": {"env_id": "toy"},
            "names": ["a"],
            "fitness": [None],
            "actors": [actor(0).state_dict()],
        },
        path,
    )
    with pytest.raises(ArtifactError, match=r"policies\.pt: metadata lacks"):
        load_policy_set(path)
    wrong = dict(META, hidden_sizes=[4])
    torch_save_atomic(
        {
            "format": "mapex.policy_set",
            "format_version": 1,
            "meta": wrong,
            "names": ["a"],
            "fitness": [None],
            "actors": [actor(0).state_dict()],
        },
        path,
    )
    with pytest.raises(ArtifactError, match="weights of actor 'a' do not match"):
        load_policy_set(path)
    with pytest.raises(ArtifactError, match="file not found"):
        load_policy_set(tmp_path / "missing.pt")
