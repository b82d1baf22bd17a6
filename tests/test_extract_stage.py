"""The extract stage end to end through the real `mapex` command, including kill-and-resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from pipeline.core.population import load_population
from pipeline.core.resume import FORMAT as RESUME_FORMAT
from pipeline.core.resume import Checkpoint

# Stage commands in subprocesses, kill and resume: `make test-fast` leaves this file out.
pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[1]

TINY = {
    "env": {"id": "mo-halfcheetah-v5", "max_episode_steps": 40, "reference_point": [-100.0, -4500.0]},
    "seeds": [0],
    "objectives": [0, 1],
    "td3": {"learning_starts": 200, "batch_size": 32, "hidden_sizes": [32, 32]},
    "train_specialist": {"total_steps": 300},
    "extract": {
        "iterations": 3,
        "child_buffer_size": 200,
        "eval_episodes": 2,
        "warmup_steps": 20,
        "warmup_batch_size": 32,
        "epochs": 1,
        "beta": 1.0,
        "omega_max": 1.0,
        "batch_size": 32,
        "hidden_sizes": [16, 16],
    },
}


def mapex(*args: str, cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "stages.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})},
    )


def write_params(path: Path, **extract_updates) -> Path:
    p = {**TINY, "extract": {**TINY["extract"], **extract_updates}}
    path.write_text(yaml.safe_dump(p))
    return path


@pytest.fixture(scope="module")
def specialists(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("specs")
    params = write_params(root / "params.yaml")
    # one command trains both objectives' specialists (stacked) into root/obj0 and root/obj1
    r = mapex("train-specialist", "--seed", "0", "--out", str(root), "--params", str(params), cwd=root)
    assert r.returncode == 0, r.stderr
    return root


def extract_cmd(specialists: Path, out: Path, params: Path, resume: Path | None, variant: str = "mapex") -> list[str]:
    """The extract command; resume None: no --resume-dir (progress goes to $MAPEX_RESUME_ROOT or data/resume)."""
    return [
        "extract",
        "--seed",
        "0",
        "--variant",
        variant,
        "--specialists",
        str(specialists),
        "--out",
        str(out),
        *(["--resume-dir", str(resume)] if resume is not None else []),
        "--params",
        str(params),
    ]


def test_extract_end_to_end_population_and_history(specialists, tmp_path):
    params = write_params(tmp_path / "params.yaml")
    record = tmp_path / "provenance" / "seed0.json"
    cmd = extract_cmd(specialists, tmp_path / "out", params, tmp_path / "resume")
    r = mapex(*cmd, "--provenance", str(record), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    members, meta = load_population(tmp_path / "out" / "population.pt")
    assert [m.origin for m in members] == ["specialist", "specialist", "child", "child", "child"]
    assert [m.iteration for m in members] == [0, 0, 1, 2, 3]
    assert meta["env_id"] == "mo-halfcheetah-v5" and meta["n_objectives"] == 2
    samples = [m.env_samples for m in members]
    assert samples == sorted(samples) and samples[0] == 2 * 40  # 2 episodes capped at 40 steps
    for i, m in enumerate(members[2:], start=2):
        assert len(m.parents) == 2 and all(0 <= p < i for p in m.parents)
        assert np.linalg.norm(m.target_weight) == pytest.approx(1.0)
        assert len(m.returns) == 2 and m.eval_episodes == 2
    lines = (tmp_path / "out" / "history.csv").read_text().splitlines()
    assert lines[0] == "iteration,population,front_size,env_samples"  # no hypervolume: no reference point here
    assert len(lines) == 1 + 4
    assert [int(line.split(",")[1]) for line in lines[1:]] == [2, 3, 4, 5]
    assert not (tmp_path / "resume" / "extract" / "mapex_td3" / "seed0").exists()  # cleaned up when done
    # what produced the run is beside OUT, not in it (OUT holds what inputs and params fix)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["history.csv", "population.pt"]
    assert "provenance" not in meta
    prov = json.loads(record.read_text())
    assert prov["stage"] == "extract"
    # extract.device is auto here: CUDA on a GPU machine (benchmarks/device/check.sh runs this file there)
    assert (
        prov["device"].startswith("cuda" if torch.cuda.is_available() else "cpu")
        and prov["versions"]["torch"] == torch.__version__
    )
    assert "reference_point" not in meta and "reference_point" not in meta["params"]["env"]


def test_children_per_iteration_end_to_end(specialists, tmp_path):
    """K = 2: each iteration adds two children whose parents were on the population before it."""
    params = write_params(tmp_path / "params.yaml", children_per_iteration=2)
    r = mapex(*extract_cmd(specialists, tmp_path / "out", params, tmp_path / "resume"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    members, meta = load_population(tmp_path / "out" / "population.pt")
    assert meta["params"]["extract"]["children_per_iteration"] == 2
    assert [m.iteration for m in members] == [0, 0, 1, 1, 2, 2, 3, 3]
    for i, m in enumerate(members[2:], start=2):
        first_of_iteration = 2 + 2 * (m.iteration - 1)
        assert all(0 <= p < first_of_iteration for p in m.parents), (i, m.parents)  # siblings never parents
        assert np.linalg.norm(m.target_weight) == pytest.approx(1.0) and len(m.returns) == 2
    samples = [m.env_samples for m in members]
    assert samples == [80 * (i + 1) for i in range(8)]  # 2 episodes x 40 steps each, cumulative
    # siblings are different policies (own hybrid buffer, own seeds)
    assert not torch.equal(members[2].actor["net.0.weight"], members[3].actor["net.0.weight"])
    lines = (tmp_path / "out" / "history.csv").read_text().splitlines()
    assert [line.split(",")[:2] for line in lines[1:]] == [["0", "2"], ["1", "4"], ["2", "6"], ["3", "8"]]


def _population_equal(a: Path, b: Path) -> None:
    ma, meta_a = load_population(a)
    mb, meta_b = load_population(b)
    assert meta_a == meta_b
    assert len(ma) == len(mb)
    for x, y in zip(ma, mb):
        assert (x.returns, x.parents, x.target_weight, x.env_samples) == (
            y.returns,
            y.parents,
            y.target_weight,
            y.env_samples,
        )
        for k in x.actor:
            assert torch.equal(x.actor[k], y.actor[k]), k


@pytest.mark.parametrize(
    ("k", "sig"),
    [
        pytest.param(1, signal.SIGKILL, id="kill"),
        # the two other cases in the slow tier (CI runs it): about 35 s that `make test` need not repeat
        pytest.param(2, signal.SIGKILL, id="kill-k2", marks=pytest.mark.slow),
        pytest.param(1, signal.SIGTERM, id="term", marks=pytest.mark.slow),
    ],
)
def test_killed_extract_resumes_to_identical_artifacts(specialists, tmp_path, k, sig):
    """k = 2 also stands for a sweep's retry on another node: no --resume-dir, progress on shared
    storage ($MAPEX_RESUME_ROOT, as `mapex repro --ray --resume-root` sets it), and the rerun in
    another working directory. SIGTERM (a scheduler's warning): the stage stops once the
    iteration it is in is checkpointed, says so in one line and exits with 143."""
    params = write_params(tmp_path / "params.yaml", iterations=8, warmup_steps=200, children_per_iteration=k)
    # uninterrupted reference run
    r = mapex(*extract_cmd(specialists, tmp_path / "ref", params, tmp_path / "resume_ref"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    # run again, SIGKILL it as soon as its first iteration is checkpointed
    resume = tmp_path / "resume"
    state_file = resume / "extract" / "mapex_td3" / "seed0" / "state.pt"
    shared = {"MAPEX_RESUME_ROOT": str(resume)} if k == 2 else {}
    node_a, node_b = (tmp_path / "node_a", tmp_path / "node_b") if k == 2 else (tmp_path, tmp_path)
    node_a.mkdir(exist_ok=True)
    node_b.mkdir(exist_ok=True)
    cmd = [
        sys.executable,
        "-m",
        "stages.cli",
        *extract_cmd(specialists, tmp_path / "out", params, None if k == 2 else resume),
    ]
    proc = subprocess.Popen(
        cmd, cwd=node_a, env={**os.environ, "PYTHONPATH": str(ROOT), **shared}, stderr=subprocess.PIPE, text=True
    )
    deadline = time.time() + 120

    def children_saved() -> int:
        try:
            return torch.load(state_file, weights_only=True)["n_items"] - 2
        except (FileNotFoundError, RuntimeError, EOFError):
            return 0

    # kill as soon as the first iteration is checkpointed (the specialists are saved before it)
    while children_saved() < 1 and proc.poll() is None and time.time() < deadline:
        time.sleep(0.01)
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=120)
    assert state_file.exists(), "the run ended before it could be killed mid-way"
    saved = torch.load(state_file, weights_only=True)
    assert saved["format"] == RESUME_FORMAT
    done = saved["n_items"] - 2
    if sig == signal.SIGTERM:
        assert proc.returncode == 143, stderr[-3000:]
        line = (
            f"extract mapex_td3 seed 0: SIGTERM: checkpoint written at iteration {done} ({state_file}); rerun to resume"
        )
        assert line in stderr.splitlines() and "Traceback" not in stderr
    # each finished policy is its own file, written once
    assert len(list(state_file.parent.glob("state.item_*.pt"))) >= saved["n_items"]
    assert 1 <= done < 8 * k and done % k == 0  # whole iterations only
    assert not (tmp_path / "out" / "population.pt").exists()  # nothing final written by the killed run
    # rerun: resumes from the checkpoint and ends with the same artifacts
    r = mapex(*extract_cmd(specialists, tmp_path / "out", params, None if k == 2 else resume), cwd=node_b, env=shared)
    assert r.returncode == 0, r.stderr
    assert f"resuming from iteration {done // k} of 8 ({state_file.parent})" in r.stderr  # it did resume
    assert not (node_b / "data").exists()  # nothing went to the working directory's data/resume
    _population_equal(tmp_path / "ref" / "population.pt", tmp_path / "out" / "population.pt")
    assert (tmp_path / "ref" / "history.csv").read_text() == (tmp_path / "out" / "history.csv").read_text()


def test_changed_params_start_over_instead_of_resuming(specialists, tmp_path):
    from dataclasses import asdict

    said: list[str] = []
    ckpt = Checkpoint(tmp_path / "progress" / "state.pt", "fingerprint-a", said.append)
    ckpt.save({"log": [{"x": 1}, {"x": 2}], "history": []})
    ckpt.save({"log": [{"x": 1}, {"x": 2}, {"x": 3}], "history": [1]})
    assert len(list((tmp_path / "progress").glob("state.item_*.pt"))) == 3  # each entry written once
    assert Checkpoint(ckpt.path, "fingerprint-a", said.append).load() == {
        "log": [{"x": 1}, {"x": 2}, {"x": 3}],
        "history": [1],
    }
    assert (
        Checkpoint(ckpt.path, "fingerprint-b", said.append).load() is None
        and "changed since it was written" in said[-1]
    )
    (tmp_path / "progress" / "state.item_00001.pt").unlink()  # a lost entry invalidates the checkpoint
    assert Checkpoint(ckpt.path, "fingerprint-a", said.append).load() is None and "cannot be read" in said[-1]
    # end to end: a finished run's state planted as the checkpoint of a run with another beta
    params_a = write_params(tmp_path / "a.yaml", beta=1.0)
    r = mapex(*extract_cmd(specialists, tmp_path / "a", params_a, tmp_path / "resume_a"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    members_a, _ = load_population(tmp_path / "a" / "population.pt")
    planted = tmp_path / "resume_b" / "extract" / "mapex_td3" / "seed0"
    Checkpoint(planted / "state.pt", "stale", print).save({"log": [asdict(m) for m in members_a], "history": []})
    params_b = write_params(tmp_path / "b.yaml", beta=0.3)
    r = mapex(*extract_cmd(specialists, tmp_path / "b", params_b, tmp_path / "resume_b"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    members_b, meta_b = load_population(tmp_path / "b" / "population.pt")
    assert meta_b["params"]["extract"]["beta"] == 0.3
    assert len(members_b) == len(members_a)
    # the children were retrained (a resumed stale run would have copied a's children)
    assert not torch.equal(members_a[-1].actor["net.0.weight"], members_b[-1].actor["net.0.weight"])


def test_warmup_only_variant_and_bad_inputs(specialists, tmp_path):
    params = write_params(tmp_path / "params.yaml")
    r = mapex(*extract_cmd(specialists, tmp_path / "w", params, tmp_path / "r", variant="warmup_only"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    _, meta = load_population(tmp_path / "w" / "population.pt")
    assert meta["params"]["extract"]["epochs"] == 0 and meta["method"] == "warmup_only_td3"
    # missing specialist directory: the file is named, nothing is written
    r = mapex(*extract_cmd(tmp_path / "nowhere", tmp_path / "x", params, tmp_path / "r"), cwd=tmp_path)
    assert r.returncode == 2
    assert "nowhere/obj0/policy.pt" in r.stderr and "not found" in r.stderr
    assert not (tmp_path / "x").exists()
    # a bad param value: key, value and expectation named
    bad = write_params(tmp_path / "bad.yaml", beta=-1)
    r = mapex(*extract_cmd(specialists, tmp_path / "y", bad, tmp_path / "r"), cwd=tmp_path)
    assert r.returncode == 2 and "extract.beta = -1" in r.stderr and "greater than 0" in r.stderr
    assert not (tmp_path / "y").exists()


def test_reference_point_is_not_an_input_of_extraction(specialists, tmp_path):
    """Progress made under one env.reference_point is resumed under another (here: none)."""
    resume = tmp_path / "resume"
    params_a = write_params(tmp_path / "a.yaml")
    # OUT is a plain file, so this run fails writing its outputs, after its last checkpoint
    blocked = tmp_path / "blocked"
    blocked.write_text("")
    r = mapex(*extract_cmd(specialists, blocked, params_a, resume), cwd=tmp_path)
    assert r.returncode != 0
    progress = resume / "extract" / "mapex_td3" / "seed0"
    assert torch.load(progress / "state.pt", weights_only=True)["n_items"] == 2 + 3
    # mark the first child's saved record (returns_std steers nothing) to tell a resumed run from a fresh one
    item = torch.load(progress / "state.item_00002.pt", weights_only=True)
    item["item"]["returns_std"] = [-1.0, -1.0]
    torch.save(item, progress / "state.item_00002.pt")
    params_b = tmp_path / "b.yaml"
    params_b.write_text(
        yaml.safe_dump({**TINY, "env": {k: v for k, v in TINY["env"].items() if k != "reference_point"}})
    )
    r = mapex(*extract_cmd(specialists, tmp_path / "out", params_b, resume), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    members, _ = load_population(tmp_path / "out" / "population.pt")
    assert members[2].returns_std == [-1.0, -1.0]  # resumed, not recomputed
    assert len(members) == 5


def test_facet_bridge_ratio_is_not_an_input_with_two_objectives(specialists, tmp_path):
    """With 2 objectives the paper's edges never read extract.facet_bridge_ratio: a run with it
    null and one with the default give the same population, meta included (the key is not in
    the recorded params), so 2-objective artifacts are those from before the key existed."""
    r = mapex(
        *extract_cmd(specialists, tmp_path / "a", write_params(tmp_path / "a.yaml"), tmp_path / "ra"), cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr
    params_b = write_params(tmp_path / "b.yaml", facet_bridge_ratio=None)
    r = mapex(*extract_cmd(specialists, tmp_path / "b", params_b, tmp_path / "rb"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    _population_equal(tmp_path / "a" / "population.pt", tmp_path / "b" / "population.pt")
    (_, meta_a), (_, meta_b) = (load_population(tmp_path / d / "population.pt") for d in "ab")
    assert meta_a == meta_b and "facet_bridge_ratio" not in meta_a["params"]["extract"]


def test_hybrid_extraction_end_to_end_records_seeds_fallbacks_stop_and_costs(specialists, tmp_path):
    """extract.init interpolate with seeds and early stopping through the command: the seeds are
    members of origin 'interpolated', the children start from their parents' mix (children
    32-32 like the specialists) or, at 16-16, fall back and say why; the stop and the fallbacks
    are in the meta, the costs in the provenance record."""
    hybrid = dict(init="interpolate", seed_interpolation=3, stop_patience=1, stop_min_gain=1e9)  # stops after 1
    params = write_params(tmp_path / "params.yaml", hidden_sizes=[32, 32], **hybrid)
    record = tmp_path / "provenance.json"
    cmd = extract_cmd(specialists, tmp_path / "out", params, tmp_path / "resume")
    r = mapex(*cmd, "--provenance", str(record), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    members, meta = load_population(tmp_path / "out" / "population.pt")
    assert [m.origin for m in members] == ["specialist"] * 2 + ["interpolated"] * 3 + ["child"]
    assert meta["stopped_at"] == 1 and meta["seed_interpolation"] == {"policies": 3, "problem": None}
    assert members[-1].init == "interpolated" and meta["init_fallbacks"] == {}
    # children 16-16 from 32-32 parents: the paper's start, counted
    narrow = write_params(tmp_path / "narrow.yaml", **hybrid)
    r = mapex(*extract_cmd(specialists, tmp_path / "narrow", narrow, tmp_path / "resume3"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    members_n, meta_n = load_population(tmp_path / "narrow" / "population.pt")
    assert members_n[-1].init == "warmup" and sum(meta_n["init_fallbacks"].values()) == 1
    assert "hidden sizes [32, 32]" in next(iter(meta_n["init_fallbacks"]))
    extract = meta["params"]["extract"]
    assert extract["init"] == "interpolate" and extract["stop_patience"] == 1
    cost = json.loads(record.read_text())["cost"]
    assert cost["cpu_seconds"] > 0 and cost["wall_seconds"] > 0
    assert [row["phase"] for row in cost["iterations"]] == ["start", "seeds", "children"]
    assert cost["iterations"][1]["policies"] == 3 and cost["iterations"][2]["train_cpu_s"] > 0
    # a paper run's meta and params say nothing of the extensions
    plain = write_params(tmp_path / "plain.yaml")
    r = mapex(*extract_cmd(specialists, tmp_path / "plain", plain, tmp_path / "resume2"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    _, meta = load_population(tmp_path / "plain" / "population.pt")
    assert not {"stopped_at", "init_fallbacks", "seed_interpolation"} & set(meta)
    assert not {"init", "seed_interpolation", "stop_patience", "stop_min_gain"} & set(meta["params"]["extract"])
