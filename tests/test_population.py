"""Population artifacts (population.pt, pipeline/core/population.py): load_population refuses
incomplete records with an ArtifactError naming file and key, reads the older format versions,
and the stages that read a population report a missing key in one line."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import pytest
import torch

from pipeline.core.artifacts import ArtifactError
from pipeline.core.population import FORMAT, load_population, save_population

# ---------------------------------------------------------------- load_population (issue 11)


def _population(path: Path, drop_meta: str | None = None, drop_member: str | None = None, version: int = 3) -> Path:
    """A two-member population written as torch.save would (meta or member key dropped on request)."""
    from pipeline.core.nets import Actor
    from pipeline.core.population import Member, actor_state

    actor = actor_state(Actor(17, 6, [4], [-1.0] * 6, [1.0] * 6))
    members = [
        Member("specialist", 0, 0, [], None, [1.0, 2.0], [0.0, 0.0], 1, 10, [4], actor, "rl"),
        Member("child", None, 1, [0, 0], [0.6, 0.8], [2.0, 1.0], [0.0, 0.0], 1, 20, [4], actor, None),
    ]
    meta = {
        "env_id": "mo-halfcheetah-v5",
        "obs_dim": 17,
        "act_dim": 6,
        "n_objectives": 2,
        "action_low": [-1.0] * 6,
        "action_high": [1.0] * 6,
        "seed": 0,
        "method": "mapex",
        "params": {},
    }
    records = [asdict(m) for m in members]
    if version == 1:
        records = [{k: v for k, v in r.items() if k != "policy_name"} for r in records]
    if drop_member is not None:
        del records[1][drop_member]
    if drop_meta is not None:
        del meta[drop_meta]
    torch.save({"format": FORMAT, "format_version": version, "meta": meta, "members": records}, path)
    return path


@pytest.mark.parametrize("key", ["returns", "origin", "actor", "policy_name"])
def test_load_population_names_the_missing_member_key(tmp_path, key):
    path = _population(tmp_path / "population.pt", drop_member=key)
    with pytest.raises(ArtifactError) as err:
        load_population(path)
    assert str(path) in str(err.value) and "member 1" in str(err.value) and f"{key!r}" in str(err.value)


@pytest.mark.parametrize("key", ["n_objectives", "seed"])
def test_load_population_names_the_missing_meta_key(tmp_path, key):
    path = _population(tmp_path / "population.pt", drop_meta=key)
    if key == "seed":
        load_population(path)  # only the keys asked for are required
    with pytest.raises(ArtifactError) as err:
        load_population(path, ("env_id", "seed"))
    assert str(path) in str(err.value) and f"{key!r}" in str(err.value)


def test_load_population_without_members_or_meta(tmp_path):
    path = _population(tmp_path / "population.pt")
    obj = torch.load(path, weights_only=True)
    for key in ("members", "meta"):
        torch.save({k: v for k, v in obj.items() if k != key}, path)
        with pytest.raises(ArtifactError, match=f"no '{key}' key"):
            load_population(path)


def test_load_population_reads_version_1(tmp_path):
    members, meta = load_population(_population(tmp_path / "population.pt", version=1))
    assert [m.policy_name for m in members] == ["policy", None]  # a version-1 specialist came from a policy.pt
    assert meta["n_objectives"] == 2
    # a version-1 record holding a version-2 key is malformed
    path = _population(tmp_path / "v1.pt", version=1)
    obj = torch.load(path, weights_only=True)
    obj["members"][0]["policy_name"] = "rl"
    torch.save(obj, path)
    with pytest.raises(ArtifactError, match="unknown key"):
        load_population(path)
    # an unknown version is refused naming the current one
    obj["format_version"] = 9
    torch.save(obj, path)
    with pytest.raises(ArtifactError, match="format_version 9, expected 3"):
        load_population(path)
    # saved anew it is the current version
    save_population(tmp_path / "again.pt", members, meta)
    assert torch.load(tmp_path / "again.pt", weights_only=True)["format_version"] == 3


def test_load_population_reads_version_2_variant_as_method(tmp_path):
    """Version 2 called the method `variant` in its meta; it loads with the key `method`."""
    path = _population(tmp_path / "population.pt", version=2)
    obj = torch.load(path, weights_only=True)
    obj["meta"]["variant"] = obj["meta"].pop("method")
    torch.save(obj, path)
    members, meta = load_population(path, ["method"])
    assert meta["method"] == "mapex" and "variant" not in meta and len(members) == 2


def test_stages_report_a_member_key_missing_in_one_line(tmp_path, cli, tiny_params):
    path = _population(tmp_path / "population.pt", drop_member="returns")
    for args in (
        ["evaluate", "--population", path, "--out", tmp_path / "ev", "--params", tiny_params],
        [
            "score",
            "--population",
            path,
            "--evaluated",
            tmp_path / "ev",
            "--out",
            tmp_path / "sc",
            "--params",
            tiny_params,
        ],
    ):
        result = cli(*args)
        assert result.exit_code == 2, result.output
        out = result.stderr
        assert "member 1 has no 'returns' key" in out and str(path) in out and "Traceback" not in out
