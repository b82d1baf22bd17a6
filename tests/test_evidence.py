"""Every study's evidence recomputes its verdicts (presets/studies/evidence/verdicts.yaml): from the
per-seed metrics.json a study kept, the report's own rule gives the outcome and paired difference
the file records, and the docs/results.md section it names states that difference; every evidence
folder is either recomputed or says why not."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import yaml

from pipeline.reporting.runs import Run
from pipeline.reporting.verdicts import hv_verdict

ROOT = Path(__file__).resolve().parents[1]
EVIDENCE = ROOT / "presets" / "studies" / "evidence"
SPEC = yaml.safe_load((EVIDENCE / "verdicts.yaml").read_text())
RESULTS = (ROOT / "docs" / "results.md").read_text()


def runs_of(folder: Path) -> list[Run]:
    """The scored runs a study kept: runs/<method>/seed<k>/metrics.json (only what a verdict reads)."""
    out = []
    for path in sorted(folder.glob("runs/*/seed*/metrics.json")):
        seed = int(path.parent.name.removeprefix("seed"))
        out.append(Run(path.parent.parent.name, seed, json.loads(path.read_text()), None, None, None, None, {}))
    return out


def section(number: str) -> str:
    """The text of docs/results.md's section `number` (e.g. 2.6.1), to the next heading."""
    m = re.search(rf"^#{{2,4}} {re.escape(number)}\.? .*$", RESULTS, re.M)
    assert m, f"docs/results.md has no section {number}"
    nxt = re.search(r"^#{2,4} ", RESULTS[m.end() :], re.M)
    return RESULTS[m.start() : m.end() + (nxt.start() if nxt else len(RESULTS))]


@pytest.mark.parametrize("entry", SPEC["verdicts"], ids=lambda e: f"{e['evidence']}:{e['a']}-vs-{e['b']}")
def test_the_evidence_recomputes_the_stated_verdict(entry):
    runs = runs_of(EVIDENCE / entry["evidence"])
    assert {entry["a"], entry["b"]} <= {r.method for r in runs}, f"{entry['evidence']}: runs missing"
    v = hv_verdict(runs, a=entry["a"], b=entry["b"], noise_sems=2.0)
    assert (v.outcome, v.difference) == (entry["verdict"], entry["difference"])
    text = section(entry["section"])
    percent, sems = entry["difference"].split(", ")[:2]
    assert percent in text and sems in text, f"results.md {entry['section']} does not state {entry['difference']}"


def test_every_evidence_folder_is_recomputed_or_says_why_not():
    recomputed = {e["evidence"] for e in SPEC["verdicts"]}
    excused = set(SPEC["not_recomputed"])
    assert not recomputed & excused
    studies = {p.name for p in EVIDENCE.iterdir() if p.is_dir()}
    for study in studies:
        covered = {k for k in recomputed | excused if k == study or k.startswith(study + "/")}
        assert covered, f"{study}: neither recomputed nor listed under not_recomputed"
    for key in recomputed | excused:
        assert (EVIDENCE / key).is_dir(), f"verdicts.yaml names {key}, which is not under {EVIDENCE}"
    # a folder with per-seed metrics is recomputed unless it says why not
    for runs in EVIDENCE.rglob("runs"):
        key = str(runs.parent.relative_to(EVIDENCE))
        assert key in recomputed or key in excused, f"{key}: has runs/ but no verdict is recomputed from it"
