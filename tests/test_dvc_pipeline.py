"""The whole DVC pipeline on a tiny preset, in a temporary git + DVC copy of the repository.

Checks the caching users rely on: a second `dvc repro` runs nothing; changing an extraction
param reruns extract, evaluate, score and report but not the specialists; changing it back
restores the earlier outputs from DVC's run-cache without recomputation; a scoring setting or
the reference point reruns only score and report; a fidelity setting only critic_fidelity.
Every method in one chain is tests/test_dvc_methods.py (a file of its own, so the two heavy
chains run in parallel under pytest-xdist).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from support.dvc_repo import BIN, make_repo, ran, run
from support.tiny_params import TINY_CHAIN as TINY

# The whole DVC pipeline, reproduced and edited: `make test-fast` leaves this file out.
pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def repo(tmp_path_factory) -> Path:
    return make_repo(tmp_path_factory.mktemp("repo"), TINY)


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
