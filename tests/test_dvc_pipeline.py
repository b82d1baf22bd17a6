"""The whole DVC pipeline on a tiny preset, in a temporary git + DVC copy of the repository.

Checks the caching users rely on: a second `dvc repro` runs nothing; changing an extraction
param reruns extract, evaluate, score and report but not the specialists; changing it back
restores the earlier outputs from DVC's run-cache without recomputation; a scoring setting or
the reference point reruns only score and report; a fidelity setting only critic_fidelity.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from tiny_params import MOPDERL_TINY, MORLD_TINY, PDERL_TINY, TINY

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def run(cmd: list[str], cwd: Path) -> str:
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "PYTHONPATH": str(ROOT)}
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    assert r.returncode == 0, f"{' '.join(cmd)} failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r.stdout + r.stderr


def ran(output: str) -> set[str]:
    """Names of the stages `dvc repro` actually executed."""
    return {m.split("@")[0] for m in re.findall(r"Running stage '([^']+)'", output)}


@pytest.fixture(scope="module")
def repo(tmp_path_factory) -> Path:
    if shutil.which("dvc", path=str(BIN)) is None:
        pytest.fail(f"dvc is not installed next to {sys.executable}")
    root = tmp_path_factory.mktemp("repo")
    for name in ("pipeline", "stages"):
        shutil.copytree(ROOT / name, root / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "dvc.yaml", root / "dvc.yaml")
    (root / "params.yaml").write_text(yaml.safe_dump(TINY))
    (root / ".gitignore").write_text("/data/\n__pycache__/\nMUJOCO_LOG.TXT\n")
    run(["git", "init", "-q"], root)
    run(["git", "config", "user.email", "test@example.com"], root)
    run(["git", "config", "user.name", "test"], root)
    run([str(BIN / "dvc"), "init", "-q"], root)
    run(["git", "add", "-A"], root)
    run(["git", "commit", "-qm", "tiny pipeline"], root)
    return root


def set_key(root: Path, section: str, key: str, value) -> None:
    params = yaml.safe_load((root / "params.yaml").read_text())
    params.setdefault(section, {})[key] = value
    (root / "params.yaml").write_text(yaml.safe_dump(params))


def set_beta(root: Path, beta: float) -> None:
    set_key(root, "extract", "beta", beta)


def test_repro_caches_and_reruns_only_what_a_param_change_touches(repo):
    dvc = str(BIN / "dvc")
    first = run([dvc, "repro"], repo)
    # posthoc_from: [] -> no post-hoc fits: joint-critic extraction does not depend on them
    assert ran(first) == {"train_specialist", "critic_fidelity", "extract", "evaluate", "score", "report"}
    report = (repo / "data" / "report" / "report.md").read_text()
    metrics_before = (repo / "data" / "score" / "mapex_td3" / "seed0" / "metrics.json").read_text()

    # nothing changed: nothing runs
    assert ran(run([dvc, "repro"], repo)) == set()

    # an extraction param: extract (both variants), evaluate and report rerun, specialists do not
    set_beta(repo, 0.5)
    changed = run([dvc, "repro"], repo)
    assert ran(changed) == {"extract", "evaluate", "score", "report"}

    # back to the old value: everything comes from the run-cache, nothing is recomputed
    set_beta(repo, 1.0)
    restored = run([dvc, "repro"], repo)
    assert ran(restored) == set()
    assert "run-cache" in restored or "is cached" in restored
    assert (repo / "data" / "score" / "mapex_td3" / "seed0" / "metrics.json").read_text() == metrics_before
    assert (repo / "data" / "report" / "report.md").read_text() == report

    # a scoring setting reruns no episode: only score and report
    set_key(repo, "score", "distinct_tol", 0.05)
    assert ran(run([dvc, "repro"], repo)) == {"score", "report"}

    # the reference point is scoring too: extraction and evaluation stay cached
    env = yaml.safe_load((repo / "params.yaml").read_text())["env"]
    set_key(repo, "env", "reference_point", [x - 1.0 for x in env["reference_point"]])
    assert ran(run([dvc, "repro"], repo)) == {"score", "report"}

    # a fidelity setting reruns only the fidelity check
    set_key(repo, "critic_fidelity", "episodes", 3)
    assert ran(run([dvc, "repro"], repo)) == {"critic_fidelity"}


# Every method through one evaluate -> score -> report chain: TD3 and PDERL specialists, the
# extraction variants from both, and the baselines (MORL/D when its optional extra is installed).
def test_every_method_is_scored_by_one_chain(tmp_path_factory):
    try:
        import morl_baselines  # noqa: F401

        baselines = ["mopderl", "morld"]
    except ImportError:  # the optional extra is not installed: the chain without MORL/D
        baselines = ["mopderl"]
    root = tmp_path_factory.mktemp("methods")
    for name in ("pipeline", "stages"):
        shutil.copytree(ROOT / name, root / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "dvc.yaml", root / "dvc.yaml")
    methods = ["mapex_td3", "mapex_posthoc_td3", "mapex_pderl", "mapex_posthoc_pderl", *baselines]
    params = {
        **TINY,
        "pderl_seeds": [0],
        "extract_from": ["td3", "pderl"],
        "extract_variants": ["mapex"],
        "posthoc_from": ["td3", "pderl"],
        "mopderl_seeds": [0],
        "morld_seeds": [0] if "morld" in baselines else [],
        "methods": methods,
        "train_specialist": {**TINY["train_specialist"], "buffer_size": 2000},
        "train_pderl": PDERL_TINY,
        "mopderl": MOPDERL_TINY,
        "morld": MORLD_TINY,
        "extract": {**TINY["extract"], "iterations": 1},
        "evaluate": {"episodes": 1},
    }
    (root / "params.yaml").write_text(yaml.safe_dump(params))
    (root / ".gitignore").write_text("/data/\n__pycache__/\nMUJOCO_LOG.TXT\n")
    for cmd in (
        ["git", "init", "-q"],
        ["git", "config", "user.email", "t@example.com"],
        ["git", "config", "user.name", "t"],
        [str(BIN / "dvc"), "init", "-q"],
        ["git", "add", "-A"],
        ["git", "commit", "-qm", "methods"],
    ):
        run(cmd, root)
    out = run([str(BIN / "dvc"), "repro"], root)
    assert {"train_pderl", "mopderl", "extract", "evaluate", "score", "report"} <= ran(out)
    for m in methods:
        metrics = json.loads((root / "data" / "score" / m / "seed0" / "metrics.json").read_text())
        assert metrics["method"] == m and metrics["front"]["cardinality"] >= 1
    # PDERL's policy sets start the PDERL methods (population + RL actor per objective); TD3 one each
    assert (
        json.loads((root / "data" / "score" / "mapex_pderl" / "seed0" / "metrics.json").read_text())[
            "starting_policies"
        ]
        == 8
    )
    assert (
        json.loads((root / "data" / "score" / "mapex_td3" / "seed0" / "metrics.json").read_text())["starting_policies"]
        == 2
    )
    report = (root / "data" / "report" / "report.md").read_text()
    for name in (
        "| MAPEX |",
        "| MAPEX-PostHoc |",
        "| MAPEX-TD3 |",
        "| MOPDERL |",
        "| PDERL specialists only |",
        "| TD3 specialists only |",
        "MAPEX (PDERL specialists)",
        "Sample efficiency",
        "| MAPEX | MOPDERL |",
    ):
        assert name in report, name
    if "morld" in baselines:
        assert "| MORL/D |" in report
    assert ran(run([str(BIN / "dvc"), "repro"], root)) == set()

    # an edit to MAPEX's code (pipeline/extraction/) leaves the specialists, the post-hoc
    # critics and the baselines up to date: only extraction and what reads its fronts rerun
    with open(root / "pipeline" / "extraction" / "mapex.py", "a") as fh:
        fh.write("\n# an edit\n")
    status = json.loads(
        subprocess.run(
            [str(BIN / "dvc"), "status", "--json"],
            cwd=root,
            capture_output=True,
            text=True,
            env={**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"},
        ).stdout
    )
    stale = {name.split("@")[0] for name in status}
    assert "extract" in stale and "extract_posthoc" in stale
    assert not stale & {"train_specialist", "train_pderl", "fit_critics", "mopderl", "morld", "critic_fidelity"}, stale
