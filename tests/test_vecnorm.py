"""Observation statistics of models trained under SB3's VecNormalize, without SB3: the
restricted reader refuses pickles that would run code, the normalising actor round-trips
through every artifact, and the params find the statistics in rl-zoo3's layout.

tests/test_import_vecnormalize.py runs the same with real SB3 models trained in the test."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.core.artifacts import ArtifactError
from pipeline.core.checkpoint import load_policy, save_policy
from pipeline.core.nets import Actor, NormalizedActor, StackedActor
from pipeline.core.population import Member, member_actor
from pipeline.core.precision import frozen
from pipeline.interop.vecnorm import read_vecnormalize, restricted_loads
from pipeline.params.import_specialists import ImportedPolicyEntry
from pipeline.params.methods import normalize_file, statistics_beside
from pipeline.params.runlists import derived_lists

OBS, ACT = 5, 2


class RunsCode:
    """Unpickled, it would run a shell command (touching `marker`)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


class EvalCall:
    """Unpickled, it would evaluate Python (creating `marker`)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (eval, (f"open({str(self.marker)!r}, 'w')",))


def test_a_pickle_that_would_run_code_is_refused_unrun(tmp_path):
    marker = tmp_path / "ran"
    path = tmp_path / "vecnormalize.pkl"
    path.write_bytes(pickle.dumps({"obs_rms": RunsCode(marker)}))
    with pytest.raises(ArtifactError) as exc:
        read_vecnormalize(path)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(str(path)) and f"{os.system.__module__}.system" in msg
    assert not marker.exists()
    # the same through builtins.eval, nested in a list
    path.write_bytes(pickle.dumps([1, EvalCall(marker)]))
    with pytest.raises(ArtifactError, match=r"builtins\.eval"):
        read_vecnormalize(path)
    assert not marker.exists()


class ObjectArrayFromBytes:
    """Unpickled by plain pickle, an ndarray of object dtype whose pointers are raw bytes: reading
    it would crash the interpreter, not raise."""

    def __reduce__(self):
        return (np.ndarray, ((1,), np.dtype("O"), b"\x41" * 8))


class FloatArrayFromBytes:
    """numpy.ndarray called directly with a plain dtype: still not how numpy pickles an array."""

    def __reduce__(self):
        return (np.ndarray, ((1,), np.dtype("f8"), b"\x41" * 8))


def test_arrays_are_rebuilt_as_numbers_only(tmp_path):
    path = tmp_path / "vecnormalize.pkl"
    path.write_bytes(pickle.dumps({"obs_rms": ObjectArrayFromBytes()}))
    with pytest.raises(ArtifactError, match=r"the pickle asks for dtype 'O8'; only plain numbers") as exc:
        read_vecnormalize(path)  # the object dtype is refused before ndarray is even reached
    assert "\n" not in str(exc.value)
    path.write_bytes(pickle.dumps({"obs_rms": FloatArrayFromBytes()}))
    with pytest.raises(ArtifactError, match=r"the pickle calls numpy\.ndarray directly"):
        read_vecnormalize(path)
    # float arrays and scalars pickled either way numpy does (protocol 4: _reconstruct and BUILD;
    # protocol 5: _frombuffer) come back equal, big-endian ones too
    values = {"a": np.arange(6, dtype=np.float64).reshape(2, 3), "s": np.float64(2.5), "b": np.arange(3, dtype=">f4")}
    for protocol in (4, 5):
        back = restricted_loads(pickle.dumps(values, protocol=protocol), path, "the test pickle")
        np.testing.assert_array_equal(back["a"], values["a"])
        np.testing.assert_array_equal(back["b"], values["b"])
        assert back["s"] == 2.5 and back["a"].dtype == np.float64
        assert back["b"].dtype == pickle.loads(pickle.dumps(values["b"], protocol=protocol)).dtype  # as numpy does
        assert type(back["a"]) is np.ndarray
    # an object array is refused whatever its items (statistics are numbers)
    mixed = np.array([1.5, "x"], dtype=object)
    with pytest.raises(ArtifactError, match=r"asks for dtype 'O8'"):
        restricted_loads(pickle.dumps(mixed, protocol=4), path, "the test pickle")


def test_the_reader_refuses_what_is_not_a_vecnormalize_file(tmp_path):
    path = tmp_path / "stats.pkl"
    path.write_bytes(pickle.dumps({"mean": np.zeros(3)}))  # numpy arrays are read, but a dict is not the wrapper
    with pytest.raises(ArtifactError, match=r"holds dict; expected a pickled stable_baselines3"):
        read_vecnormalize(path)
    path.write_bytes(b"not a pickle")
    with pytest.raises(ArtifactError, match="not a readable pickle"):
        read_vecnormalize(path)
    with pytest.raises(ArtifactError, match="no such file"):
        read_vecnormalize(tmp_path / "missing.pkl")


def stats(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=OBS), rng.uniform(0.5, 4.0, size=OBS)


def normalized_actor(clip: float = 2.0) -> NormalizedActor:
    torch.manual_seed(0)
    mean, var = stats()
    return NormalizedActor(OBS, ACT, [8], [-1, -2], [1, 2], mean, np.sqrt(var + 1e-8), clip).eval()


def test_the_normalized_actor_is_vecnormalize_then_the_mlp():
    actor = normalized_actor()
    mean, var = stats()
    obs = (np.random.default_rng(1).normal(size=(50, OBS)) * 5).astype(np.float32)
    z = np.clip((obs - mean) / np.sqrt(var + 1e-8), -2.0, 2.0).astype(np.float32)  # SB3's arithmetic
    plain = Actor(OBS, ACT, [8], [-1, -2], [1, 2])
    plain.load_state_dict({k: v for k, v in actor.state_dict().items() if not k.startswith("obs_")})
    with torch.no_grad():
        # two computations (torch's normalisation inside the actor, numpy's here): equal to rounding
        np.testing.assert_allclose(
            actor(torch.from_numpy(obs)).numpy(), plain(torch.from_numpy(z)).numpy(), rtol=1e-6, atol=1e-6
        )
        assert (np.abs(z) == 2.0).any()  # the clip was exercised
        assert not np.allclose(actor(torch.from_numpy(obs)).numpy(), plain(torch.from_numpy(obs)).numpy())


def test_a_bf16_copy_of_the_normalized_actor_keeps_its_statistics_and_acts_in_fp32():
    actor = normalized_actor()
    copy = frozen(actor, "bf16")
    assert copy.net[0].weight.dtype == torch.bfloat16 and copy.obs_mean.dtype == torch.float64
    obs = torch.from_numpy((np.random.default_rng(2).normal(size=(20, OBS)) * 3).astype(np.float32))
    with torch.no_grad():
        full, low = actor(obs), copy(obs)
    assert low.dtype == torch.float32 and torch.isfinite(low).all()
    assert (low - full).abs().max() < 0.05  # bf16's 8-bit mantissa through one small layer


def test_the_normalized_actor_round_trips_through_policy_and_population(tmp_path):
    actor = normalized_actor()
    meta = {"env_id": "x", "obs_dim": OBS, "act_dim": ACT, "n_objectives": 2, "action_low": [-1, -2]}
    meta |= {"action_high": [1, 2], "hidden_sizes": [8], "architecture": "normalized_mlp"}
    save_policy(tmp_path / "policy.pt", actor, meta)
    loaded, _ = load_policy(tmp_path / "policy.pt")
    obs = torch.randn(20, OBS) * 4
    member = Member("specialist", 0, 0, [], None, [0.0, 0.0], [0.0, 0.0], 1, 0, [8], actor.state_dict(), "policy")
    rebuilt = member_actor(member, meta)
    assert type(loaded) is NormalizedActor and type(rebuilt) is NormalizedActor
    with torch.no_grad():
        torch.testing.assert_close(loaded(obs), actor(obs), rtol=0, atol=0)
        torch.testing.assert_close(rebuilt(obs), actor(obs), rtol=0, atol=0)
    with pytest.raises(ValueError, match="cannot be stacked"):
        StackedActor([actor, actor])


def test_statistics_are_found_in_rl_zoo3_layout(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # paths in params are relative to the repository root
    run = Path("logs/td3/mo-halfcheetah-v5_2")
    (run / "mo-halfcheetah-v5").mkdir(parents=True)
    for name in ("mo-halfcheetah-v5.zip", "best_model.zip", "rl_model_400_steps.zip", "rl_model_800_steps.zip"):
        (run / name).write_bytes(b"")
    assert statistics_beside(str(run / "mo-halfcheetah-v5.zip")) is None  # nothing saved yet
    (run / "mo-halfcheetah-v5" / "vecnormalize.pkl").write_bytes(b"")
    (run / "rl_model_vecnormalize_400_steps.pkl").write_bytes(b"")
    final = "logs/td3/mo-halfcheetah-v5_2/mo-halfcheetah-v5/vecnormalize.pkl"
    assert statistics_beside(str(run / "mo-halfcheetah-v5.zip")) == final
    assert statistics_beside(str(run / "best_model.zip")) == final
    assert statistics_beside(str(run / "rl_model_400_steps.zip")) == f"{run}/rl_model_vecnormalize_400_steps.pkl"
    assert statistics_beside(str(run / "rl_model_800_steps.zip")) == final  # that step's own file is missing
    Path("models").mkdir()
    (Path("models") / "vec_normalize.pkl").write_bytes(b"")  # the Hub's name: never guessed
    assert statistics_beside("models/speed.zip") is None

    entry = {"objective": 0, "file": str(run / "mo-halfcheetah-v5.zip"), "format": "sb3"}
    assert normalize_file(entry) == final
    assert normalize_file(entry | {"normalize": False}) is None
    assert normalize_file(entry | {"normalize": "models/vec_normalize.pkl"}) == "models/vec_normalize.pkl"
    assert normalize_file(entry | {"format": "cleanrl"}) is None  # only SB3 saves statistics this way
    lists = derived_lists(
        ["mapex_posthoc_imported"],
        [0],
        [entry, {"objective": 1, "file": "models/energy.zip", "format": "sb3", "buffer": "b.zarr"}],
    )
    assert lists["import_collect"] == [entry | {"normalize": final, "normalize_dep": final}]
    assert lists["import_buffered"][0]["normalize"] == "none"
    assert lists["import_buffered"][0]["normalize_dep"] == "models/energy.zip"  # DVC needs a dep: the file again


def test_params_take_normalize_for_mlp_formats_only():
    base = {"objective": 0, "file": "m.zip", "format": "sb3"}
    assert ImportedPolicyEntry(**base, normalize="s.pkl").normalize == "s.pkl"
    assert ImportedPolicyEntry(**base, normalize=False).normalize is False
    with pytest.raises(ValueError, match="normalises inside its own module"):
        ImportedPolicyEntry(**(base | {"format": "torchscript"}), normalize="s.pkl")
    with pytest.raises(ValueError):
        ImportedPolicyEntry(**base, normalize=True)
    for word in ("none", "None", "auto"):  # the CLI's words, which YAML reads as file names
        with pytest.raises(ValueError, match=rf"normalize = '{word}' is a word of the command line.*write false"):
            ImportedPolicyEntry(**base, normalize=word)


def test_interpolation_mixes_normalized_actors_of_the_same_statistics_only():
    from pipeline.baselines.interpolate import architecture_problem, mix_actors

    a = normalized_actor()
    torch.manual_seed(1)
    b = NormalizedActor(OBS, ACT, [8], [-1, -2], [1, 2], a.obs_mean, a.obs_std, 2.0).eval()
    obs = torch.randn(10, OBS) * 4
    vertex = mix_actors([a, b], [0.0, 1.0])  # w = e_1: actor b's weights and the shared statistics
    assert type(vertex) is NormalizedActor
    with torch.no_grad():
        torch.testing.assert_close(vertex(obs), b(obs), rtol=0, atol=0)
    mean, var = stats(seed=5)
    other = NormalizedActor(OBS, ACT, [8], [-1, -2], [1, 2], mean, np.sqrt(var), 2.0)
    assert "differ in their observation statistics" in architecture_problem([a, other], ["obj0", "obj1"])
    plain = Actor(OBS, ACT, [8], [-1, -2], [1, 2])
    assert "obj0 normalise observations" in architecture_problem([a, plain], ["obj0", "obj1"])
