"""A sample of benchmarks/fuzz_imports.py (100 mutated model and statistics files, every format and
kind of mutation taken in turn): no crash, no hang, no code run, every refusal one line naming
the file, every unmutated seed accepted (docs/benchmarks.md, "Fuzzing the imports")."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow  # about a minute: seeds (a torch.export among them), then 100 forked reads
def test_a_sample_of_mutated_imports_neither_crashes_hangs_nor_runs_code(tmp_path):
    out = tmp_path / "fuzz.json"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "fuzz_imports.py"), "--cases", "100", "--seed", "7"]
    env = os.environ | {"PYTHONPATH": str(ROOT)}
    r = subprocess.run([*cmd, "--out", str(out)], capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    report = json.loads(out.read_text())
    total, seeds = report["summary"]["all"], report["summary"]["kind:seed"]
    assert total["cases"] == 100 and set(report["summary"]) >= {
        "sb3",
        "cleanrl",
        "torchscript",
        "torch_export",
        "stats",
    }
    assert total["crash"] == 0 and total["hang"] == 0, report["findings"]
    assert total["refused"] > 50 and total["refused_without_file_name"] == 0, total
    assert seeds["accepted"] == seeds["cases"] > 0, seeds
    assert total["peak_growth_mb"] < 512, total  # the child's limit is 1024 MB of address space
    ran = {f["format"] for f in report["findings"] if f["code_ran"]}
    assert not ran, [f for f in report["findings"] if f["code_ran"]]
