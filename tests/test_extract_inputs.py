"""The extract stage's inputs through the real `mapex extract` command: cross-checked specialist
artifacts (bad ones exit 2 with one line naming both files), post-hoc critics, and the
advantage options end to end."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

from pipeline.core.buffer import load_buffer
from pipeline.core.checkpoint import load_critics, save_critics
from pipeline.core.nets import CriticEnsemble
from pipeline.core.population import load_population

# Specialists, then `mapex extract` in subprocesses: `make test-fast` leaves this file out.
pytestmark = pytest.mark.integration

EXTRACT = {
    "iterations": 2,
    "child_buffer_size": 200,
    "eval_episodes": 1,
    "warmup_steps": 10,
    "warmup_batch_size": 32,
    "epochs": 1,
    "beta": 1.0,
    "omega_max": 1.0,
    "batch_size": 32,
    "hidden_sizes": [16, 16],
    "device": "cpu",
}


@pytest.fixture(scope="module")
def trained(tmp_path_factory, write_params, mapex) -> Path:
    """Specialists of seed 0 (both objectives), trained once for this module."""
    root = tmp_path_factory.mktemp("inputs")
    params = write_params(root, {"extract": EXTRACT})
    r = mapex("train-specialist", "--seed", "0", "--out", root / "specs", "--params", params, cwd=root)
    assert r.returncode == 0, r.stderr
    return root / "specs"


@pytest.fixture
def specs(trained, tmp_path) -> Path:
    """A private copy of the specialists, free to tamper with."""
    return Path(shutil.copytree(trained, tmp_path / "specs"))


def extract(
    mapex,
    write_params,
    tmp_path: Path,
    specs: Path,
    name: str = "out",
    seed: int = 0,
    posthoc: Path | None = None,
    variant: str = "mapex",
    **updates,
):
    params = write_params(tmp_path, {"extract": {**EXTRACT, **updates}}, name=f"{name}.yaml")
    extra = ["--posthoc", posthoc] if posthoc is not None else []
    return mapex(
        "extract",
        "--seed",
        seed,
        "--variant",
        variant,
        "--specialists",
        specs,
        "--out",
        tmp_path / name,
        "--resume-dir",
        tmp_path / f"resume_{name}",
        "--params",
        params,
        *extra,
        cwd=tmp_path,
    )


def assert_refused(r, tmp_path: Path, *fragments: str, name: str = "out", one_line: bool = True) -> None:
    """Exit 2, an `error:` message on stderr holding every fragment (on one line, for a bad
    artifact; a params error lists each bad key on a line of its own), and no output written."""
    assert r.returncode == 2, r.stderr
    lines = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, r.stderr
    message = lines[0] if one_line else r.stderr[r.stderr.index("error:") :]
    for f in fragments:
        assert f in message, (f, message)
    assert not (tmp_path / name).exists()


def rewrite_meta(path: Path, **changes) -> None:
    obj = torch.load(path, weights_only=True)
    for key, value in changes.items():
        if value is None:
            del obj["meta"][key]
        else:
            obj["meta"][key] = value
    torch.save(obj, path)


# ---------------------------------------------------------------- specialist artifacts disagree


def test_policy_of_the_other_objective_is_refused(specs, tmp_path, mapex, write_params):
    shutil.copy(specs / "obj1" / "policy.pt", specs / "obj0" / "policy.pt")
    r = extract(mapex, write_params, tmp_path, specs)
    assert_refused(r, tmp_path, "obj0/policy.pt (objective = 1)", "obj0/buffer.zarr (objective = 0)")


def test_critics_of_the_other_buffer_are_refused(specs, tmp_path, mapex, write_params):
    shutil.copy(specs / "obj0" / "critics.pt", specs / "obj1" / "critics.pt")
    r = extract(mapex, write_params, tmp_path, specs)
    assert_refused(r, tmp_path, "obj1/buffer.zarr (objective = 1)", "obj1/critics.pt (buffer_objective = 0)")


def test_policy_of_another_seed_is_refused(specs, tmp_path, mapex, write_params):
    rewrite_meta(specs / "obj1" / "policy.pt", seed=7)
    r = extract(mapex, write_params, tmp_path, specs)
    assert_refused(r, tmp_path, "obj1/policy.pt (seed = 7)", "obj1/buffer.zarr (seed = 0)")


def test_specialists_of_another_run_seed_are_refused(specs, tmp_path, mapex, write_params):
    r = extract(mapex, write_params, tmp_path, specs, seed=3)
    assert_refused(r, tmp_path, "obj0/policy.pt", "obj0/buffer.zarr", "seed = 0", "--seed 3")


def test_missing_metadata_key_is_refused(specs, tmp_path, mapex, write_params):
    rewrite_meta(specs / "obj0" / "critics.pt", seed=None)
    r = extract(mapex, write_params, tmp_path, specs)
    assert_refused(r, tmp_path, "obj0/critics.pt: metadata has no 'seed'", "obj0/buffer.zarr")


def test_critics_without_secondary_heads_are_refused_naming_the_td3_key(specs, tmp_path, mapex, write_params):
    """Joint critics that cover the primary objective only (a specialist trained with
    td3.secondary_critics: false) cannot drive extraction: the message names the key to set."""
    _, _, meta = load_critics(specs / "obj1" / "critics.pt")
    heads = [CriticEnsemble(meta["obs_dim"], meta["act_dim"], meta["hidden_sizes"], 2) for _ in range(2)]
    save_critics(specs / "obj1" / "critics.pt", *heads, {**meta, "objectives": [1]})
    r = extract(mapex, write_params, tmp_path, specs)
    assert_refused(r, tmp_path, "obj1/critics.pt: critics covering objectives [1]", "td3.secondary_critics: true")


def test_zero_hidden_width_is_refused(specs, tmp_path, mapex, write_params):
    r = extract(mapex, write_params, tmp_path, specs, hidden_sizes=[0])
    assert_refused(r, tmp_path, "extract.hidden_sizes.0 = 0", "greater than 0", one_line=False)


def test_warmup_only_reads_no_critics(specs, tmp_path, mapex, write_params):
    """Warm-up only (epochs = 0) runs from specialists without critics.pt, with exactly the
    children it makes when the critics are there; MAPEX without them is one line naming the file."""
    with_critics = extract(mapex, write_params, tmp_path, specs, name="with", variant="warmup_only")
    assert with_critics.returncode == 0, with_critics.stderr
    for k in (0, 1):
        (specs / f"obj{k}" / "critics.pt").unlink()
    r = extract(mapex, write_params, tmp_path, specs, name="without", variant="warmup_only")
    assert r.returncode == 0, r.stderr
    mw, meta_w = load_population(tmp_path / "with" / "population.pt")
    mn, meta_n = load_population(tmp_path / "without" / "population.pt")
    assert meta_n == meta_w and meta_n["params"]["extract"]["epochs"] == 0 and len(mn) == len(mw) == 4
    for a, b in zip(mw, mn):
        assert all(torch.equal(a.actor[k], b.actor[k]) for k in a.actor) and a.returns == b.returns
    r = extract(mapex, write_params, tmp_path, specs, name="mapex")
    assert_refused(r, tmp_path, "obj0/critics.pt: file not found", name="mapex")


# ---------------------------------------------------------------- post-hoc critics


def write_posthoc(specs: Path, root: Path, checksums: bool = True, reinit: bool = False) -> Path:
    """Critics in the post-hoc format (source "posthoc", buffer_checksums of the buffer they
    were fitted on) holding the joint critics' weights, or fresh ones if `reinit`."""
    for k in (0, 1):
        online, target, meta = load_critics(specs / f"obj{k}" / "critics.pt")
        _, attrs = load_buffer(specs / f"obj{k}" / "buffer.zarr")
        meta = {**meta, "source": "posthoc"}
        if checksums:
            meta["buffer_checksums"] = dict(attrs["checksums"])
        if reinit:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(100 + k)
                online = CriticEnsemble(meta["obs_dim"], meta["act_dim"], meta["hidden_sizes"], online.n_members)
        save_critics(root / f"obj{k}" / "critics.pt", online, target, meta)
    return root


def test_posthoc_critics_end_to_end(specs, tmp_path, mapex, write_params):
    """--variant mapex_posthoc reads the --posthoc critics: with the joint critics' weights
    it makes exactly the joint run's children, with other weights other children."""
    joint = extract(mapex, write_params, tmp_path, specs, name="joint")
    assert joint.returncode == 0, joint.stderr
    same = write_posthoc(specs, tmp_path / "posthoc_same")
    r = extract(mapex, write_params, tmp_path, specs, name="same", posthoc=same, variant="mapex_posthoc")
    assert r.returncode == 0, r.stderr
    other = write_posthoc(specs, tmp_path / "posthoc_other", reinit=True)
    r = extract(mapex, write_params, tmp_path, specs, name="other", posthoc=other, variant="mapex_posthoc")
    assert r.returncode == 0, r.stderr
    mj, _ = load_population(tmp_path / "joint" / "population.pt")
    ms, meta = load_population(tmp_path / "same" / "population.pt")
    mo, _ = load_population(tmp_path / "other" / "population.pt")
    assert meta["params"]["critics"] == "posthoc" and meta["method"] == "mapex_posthoc_td3" and len(ms) == len(mj) == 4
    for a, b in zip(mj[2:], ms[2:]):
        assert all(torch.equal(a.actor[k], b.actor[k]) for k in a.actor) and a.returns == b.returns
    assert not torch.equal(mj[-1].actor["net.0.weight"], mo[-1].actor["net.0.weight"])


def test_posthoc_critics_of_another_buffer_are_refused(specs, tmp_path, mapex, write_params):
    posthoc = write_posthoc(specs, tmp_path / "posthoc")
    rewrite_meta(posthoc / "obj1" / "critics.pt", buffer_checksums={"obs": "00000000"})
    r = extract(mapex, write_params, tmp_path, specs, posthoc=posthoc, variant="mapex_posthoc")
    assert_refused(r, tmp_path, "obj1/critics.pt was fitted on a different buffer than", "obj1/buffer.zarr", "'obs'")


def test_posthoc_critics_without_buffer_checksums_are_refused(specs, tmp_path, mapex, write_params):
    posthoc = write_posthoc(specs, tmp_path / "posthoc", checksums=False)
    r = extract(mapex, write_params, tmp_path, specs, posthoc=posthoc, variant="mapex_posthoc")
    assert_refused(r, tmp_path, "obj0/critics.pt: the post-hoc critics do not record which buffer", "obj0/buffer.zarr")


def test_joint_critics_given_as_posthoc_are_refused(specs, tmp_path, mapex, write_params):
    r = extract(mapex, write_params, tmp_path, specs, posthoc=specs, variant="mapex_posthoc")
    assert_refused(
        r,
        tmp_path,
        "obj0/critics.pt: critics of source 'joint'",
        "obj0/buffer.zarr",
        "the variant reads 'posthoc' critics",
    )


# ---------------------------------------------------------------- advantage options


def test_advantage_recompute_once_end_to_end(specs, tmp_path, mapex, write_params):
    every = extract(mapex, write_params, tmp_path, specs, name="every")
    once = extract(
        mapex, write_params, tmp_path, specs, name="once", advantage_recompute="once", advantage_norm="zscore"
    )
    assert every.returncode == 0 and once.returncode == 0, once.stderr
    me, _ = load_population(tmp_path / "every" / "population.pt")
    mo, meta = load_population(tmp_path / "once" / "population.pt")
    assert meta["params"]["extract"]["advantage_recompute"] == "once"
    assert [m.parents for m in mo[:3]] == [m.parents for m in me[:3]]  # same draws up to the first child's training
    assert not torch.equal(me[2].actor["net.0.weight"], mo[2].actor["net.0.weight"])  # the weights differ
