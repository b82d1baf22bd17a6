"""The resource fuzz's figures (issue 57): every hostile and valid file tests/test_resource_fuzz.py
reads, per format, with the largest memory growth and CPU time a read took. Run by hand:

    python benchmarks/bench_trust.py

It runs that test file (each read in a subprocess under RLIMIT_CPU, as the suite does) with
MAPEX_FUZZ_LOG set, then prints a markdown table for docs/benchmarks.md.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NAMES = {
    "sb3": "SB3 zip",
    "zarr": "Zarr buffer",
    "ts": "TorchScript",
    "stats": "statistics file",
    "cleanrl": "CleanRL (torch.save zip)",
}


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "fuzz.jsonl"
        env = os.environ | {"MAPEX_FUZZ_LOG": str(log)}
        r = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:randomly", "tests/test_resource_fuzz.py"],
            cwd=ROOT,
            env=env,
        )
        if r.returncode != 0:
            sys.exit(f"tests/test_resource_fuzz.py failed (exit {r.returncode}): the figures would not mean anything")
        rows = [json.loads(line) for line in log.read_text().splitlines()]
    by = defaultdict(list)
    for row in rows:
        by[row["kind"]].append(row)
    print("| format | files read | refused | largest file | worst peak-RSS growth past the imports | worst CPU |")
    print("|---|---|---|---|---|---|")
    for kind, cases in by.items():
        refused = sum(not c["ok"] for c in cases)
        print(
            f"| {NAMES.get(kind, kind)} | {len(cases)} | {refused} | {max(c['bytes'] for c in cases) / 1e6:.2f} MB "
            f"| {max(c['grow_mb'] for c in cases):.1f} MB | {max(c['cpu_s'] for c in cases):.2f} s |"
        )
    base = max(c["base_mb"] for c in rows)
    print(f"(peak RSS after the reader's imports, before any read: up to {base:.0f} MB; growth is above that peak)")
    for c in rows:
        print(f"  {c['kind']} {c['case']}: {'ok' if c['ok'] else 'refused'}, {c['grow_mb']:.1f} MB, {c['cpu_s']:.2f} s")


if __name__ == "__main__":
    main()
