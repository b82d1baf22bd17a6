"""benchmarks/device/payoff.sh and benchmarks/payoff_report.sh, end to end on a tiny preset.

They are written for a GPU machine whose time is scarce, so they must work the first time: the
run (specialists, then three extraction runs per seed), its resumption (a second call redoes
nothing) and the report of both forms from what it brings back.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from support.tiny_params import TINY_CHAIN as TINY_BASE

# The payoff scripts' whole stage chain: `make test-fast` leaves this file out.
pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent

TINY = {**TINY_BASE, "extract": {**TINY_BASE["extract"], "epochs": 3}}  # 3 epochs: the gentle form (1) differs


def sh(*args, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
        "PYTHON": sys.executable,
        "PYTHONPATH": str(ROOT),
        "MAPEX": f"{sys.executable} -m stages.cli",
    }
    return subprocess.run(["bash", *map(str, args)], cwd=cwd, env=env, capture_output=True, text=True)


@pytest.mark.slow  # about a minute: slow keeps `make test` within 8 minutes
def test_payoff_run_resumes_and_reports_both_forms(tmp_path):
    params = tmp_path / "tiny.yaml"
    params.write_text(yaml.safe_dump(TINY))
    work = tmp_path / "w"
    r = sh("benchmarks/device/payoff.sh", work, params)
    assert r.returncode == 0, r.stdout + r.stderr
    progress = (work / "progress.log").read_text()
    for name in (
        "train_specialist_seed0",
        "extract_paper_mapex_seed0",
        "extract_paper_warmup_only_seed0",
        "extract_gentle_mapex_seed0",
    ):
        assert f"{name}: done in" in progress, progress
    gentle = yaml.safe_load((work / "gentle.yaml").read_text())["extract"]
    assert (gentle["epochs"], gentle["lr"]) == (1, 1e-4)
    # the forms differ in their AWR phase only: the warm-up alone gives one population for both
    paper = torch.load(work / "fronts/paper/mapex_td3/seed0/population.pt", weights_only=False)
    soft = torch.load(work / "fronts/gentle/mapex_td3/seed0/population.pt", weights_only=False)
    assert paper["meta"]["params"]["extract"]["epochs"] == 3 and soft["meta"]["params"]["extract"]["epochs"] == 1

    # a second call finds everything done and redoes nothing
    again = sh("benchmarks/device/payoff.sh", work, params)
    assert again.returncode == 0 and again.stdout.count("done before") == 4, again.stdout + again.stderr

    # what comes back is small and enough to report from
    light = work / "light"
    assert not list(light.rglob("buffer.zarr")) and not list(light.rglob("critics.pt"))
    r = sh("benchmarks/payoff_report.sh", light)
    assert r.returncode == 0, r.stdout + r.stderr
    for form in ("paper", "gentle"):
        report = (light / "report" / form / "report.md").read_text()
        assert "MAPEX-TD3" in report and "warm-up only" in report
        # what produced every run came back beside the outputs (light/provenance/) and is shown
        provenance = report.split("## Provenance", 1)[1].split("## Definitions", 1)[0]
        rows = [line for line in provenance.splitlines() if line.startswith("| extract |") or "| score |" in line]
        assert rows and not [r for r in rows if "not recorded" in r], provenance
