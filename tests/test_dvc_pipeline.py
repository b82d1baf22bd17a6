"""The whole DVC pipeline on a tiny preset, in a temporary git + DVC copy of the repository.

Checks the caching users rely on: a second `dvc repro` runs nothing; changing an extraction
param reruns MAPEX (stage mapex_td3), evaluate, score and report but not the specialists; changing it back
restores the earlier outputs from DVC's run-cache without recomputation; a scoring setting or
the reference point reruns only score and report; a fidelity setting only critic_fidelity.
An edit to training code that changes no number reruns the training stage only: what produced
a run is recorded beside the artifacts (data/provenance/), not inside what later stages hash.
Every method in one chain is tests/test_dvc_methods.py (a file of its own, so the two heavy
chains run in parallel under pytest-xdist).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path

import pytest
import yaml
from support.dvc_repo import BIN, make_repo, ran, run
from support.tiny_params import TINY_CHAIN as TINY
from support.tiny_params import save_params

# The whole DVC pipeline, reproduced and edited: `make test-fast` leaves this file out.
pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def repo(tmp_path_factory) -> Path:
    return make_repo(tmp_path_factory.mktemp("repo"), TINY)


def set_key(root: Path, section: str, key: str, value) -> None:
    params = yaml.safe_load((root / "params.yaml").read_text())
    params.setdefault(section, {})[key] = value
    save_params(root / "params.yaml", params)


def set_beta(root: Path, beta: float) -> None:
    set_key(root, "extract", "beta", beta)


def test_repro_caches_and_reruns_only_what_a_param_change_touches(repo):
    dvc = str(BIN / "dvc")
    first = run([dvc, "repro"], repo)
    # posthoc_from: [] -> no post-hoc fits: joint-critic extraction does not depend on them
    assert ran(first) == {
        "train_specialist",
        "critic_fidelity",
        "mapex_td3",
        "warmup_only_td3",
        "evaluate",
        "score",
        "render",
        "report",
    }
    report = (repo / "data" / "report" / "report.md").read_text()
    metrics_before = (repo / "data" / "score" / "mapex_td3" / "seed0" / "metrics.json").read_text()

    # nothing changed: nothing runs
    assert ran(run([dvc, "repro"], repo)) == set()

    # an advantage-weighted param: MAPEX's extraction, its evaluation and score and the report
    # rerun; the specialists do not, nor the warm-up-only ablation, which does not read beta
    set_beta(repo, 0.5)
    changed = run([dvc, "repro"], repo)
    assert ran(changed) == {"mapex_td3", "evaluate", "score", "render", "report"}
    items = set(re.findall(r"Running stage '([^']+)'", changed))
    assert {"evaluate@0-mapex_td3", "score@0-mapex_td3"} <= items
    assert not {i for i in items if "warmup_only" in i}, items

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


def run_copy(cmd: list[str], root: Path) -> str:
    """`run`, but with the copy's own pipeline/ and stages/ on the import path: an edit there is
    the code that runs, and provenance records the copy's git state (`run` imports this checkout's)."""
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "PYTHONPATH": str(root)}
    r = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True)
    assert r.returncode == 0, f"{' '.join(cmd)} failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r.stdout + r.stderr


def test_an_edit_that_changes_no_number_reruns_only_the_stage_it_touches(repo):
    """A comment in the TD3 code, committed (HEAD moves): train_specialist reruns, its outputs come
    out bit for bit as before, so extraction, evaluation, scoring, the fidelity checks and the
    report stay cached; only its provenance record, an out of its own, tells the new commit."""
    dvc = str(BIN / "dvc")
    run_copy([dvc, "repro"], repo)  # up to date after the test above; the whole chain when run alone
    record = repo / "data" / "provenance" / "specialists" / "td3" / "seed0.json"
    before = json.loads(record.read_text())
    lock = yaml.safe_load((repo / "dvc.lock").read_text())["stages"]["train_specialist@0"]

    with open(repo / "pipeline" / "specialists" / "td3.py", "a") as fh:
        fh.write("\n# a comment: no number changes\n")
    run(["git", "commit", "-qam", "a comment in the training code"], repo)
    head = run(["git", "rev-parse", "HEAD"], repo).strip()
    assert ran(run_copy([dvc, "repro"], repo)) == {"train_specialist"}
    assert "up to date" in run_copy([dvc, "status"], repo)

    after = yaml.safe_load((repo / "dvc.lock").read_text())["stages"]["train_specialist@0"]
    outs = {o["path"]: o["md5"] for o in lock["outs"]}
    new_outs = {o["path"]: o["md5"] for o in after["outs"]}
    specialists, rel = "data/specialists/td3/seed0", str(record.relative_to(repo))
    assert new_outs[specialists] == outs[specialists]  # the artifacts: the same bytes
    assert new_outs[rel] != outs[rel]  # the record: the new commit
    assert before["stage"] == "train_specialist" and before["git_commit"] != head
    assert json.loads(record.read_text())["git_commit"] == head


def test_a_new_label_or_colour_reruns_only_the_stages_that_draw(repo):
    """Presentation is not computation: relabelling and recolouring MAPEX-TD3 leaves the
    specialists, the extractions, the evaluations and the scores up to date; only render and
    report see the change (their code closure holds the looks, no other stage's does)."""
    dvc = str(BIN / "dvc")
    run_copy([dvc, "repro"], repo)  # up to date after the tests above; the whole chain when run alone
    looks = repo / "pipeline" / "reporting" / "presentation.py"
    source = looks.read_text()
    row = '"mapex_td3": Look("MAPEX-TD3", "tab:green")'
    assert row in source
    looks.write_text(source.replace(row, '"mapex_td3": Look("MAPEX, TD3 specialists", "tab:olive")'))
    try:
        from test_dvc_methods import stale_stages

        assert stale_stages(repo) == {"render", "report"}
    finally:
        looks.write_text(source)
    assert "up to date" in run_copy([dvc, "status"], repo)
