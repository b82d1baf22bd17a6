"""Run shell jobs from a plan file on N slots, highest priority first, each once its inputs exist.

    python benchmarks/jobqueue.py PLAN [--slots 2] [--log DIR] [--poll SECONDS]

PLAN is re-read every few seconds, so jobs can be added or reordered while it runs. One job a
line, tab-separated: NAME, DONE (a path; the job counts as done once it exists), DEPS (paths
joined by ',', or '-'), COMMAND (run with bash from the current directory). Lines starting with
'#' are skipped. A job is started when its DONE path is missing and every DEPS path exists; a job
that fails is not retried (its log is under DIR/NAME.log). The queue ends when nothing is running
and nothing more can start. Used by benchmarks/answer.sh for its long runs on a few cores.
"""

from __future__ import annotations

import argparse
import subprocess
import time
from datetime import datetime, timezone
from pathlib import Path


def read_plan(path: Path) -> list[tuple[str, Path, list[Path], str]]:
    jobs = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split("\t")
        if len(parts) != 4:
            raise SystemExit(f"{path}:{n}: expected 4 tab-separated fields (NAME DONE DEPS COMMAND), got {len(parts)}")
        name, done, deps, cmd = parts
        jobs.append((name, Path(done), [] if deps == "-" else [Path(d) for d in deps.split(",")], cmd))
    return jobs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("plan", type=Path)
    ap.add_argument("--slots", type=int, default=2)
    ap.add_argument("--log", type=Path, default=Path("queue-logs"))
    ap.add_argument("--poll", type=float, default=5.0, help="seconds between looks at the plan and the jobs")
    a = ap.parse_args()
    a.log.mkdir(parents=True, exist_ok=True)
    running: dict[str, tuple[subprocess.Popen, float]] = {}  # the job's process and start time
    failed: set[str] = set()

    def say(msg: str) -> None:
        line = f"{datetime.now(timezone.utc):%H:%M:%S} {msg}"
        print(line, flush=True)
        with open(a.log / "queue.log", "a") as f:
            f.write(line + "\n")

    while True:
        for name, (proc, t0) in list(running.items()):
            if proc.poll() is not None:
                del running[name]
                proc.stdout_log.close()
                if proc.returncode == 0:
                    say(f"{name}: done in {time.time() - t0:.0f} s")
                else:
                    failed.add(name)
                    say(
                        f"{name}: FAILED (exit {proc.returncode}) after {time.time() - t0:.0f} s; log {a.log / name}.log"
                    )
        jobs = read_plan(a.plan)
        waiting = [j for j in jobs if not j[1].exists() and j[0] not in running and j[0] not in failed]
        for name, done, deps, cmd in waiting:
            if len(running) >= a.slots:
                break
            if all(d.exists() for d in deps):
                log = open(a.log / f"{name}.log", "w")
                proc = subprocess.Popen(["bash", "-c", cmd], stdout=log, stderr=subprocess.STDOUT)
                proc.stdout_log = log  # closed when the job ends
                running[name] = (proc, time.time())
                say(f"{name}: started")
        if not running:
            startable = [j for j in waiting if all(d.exists() for d in j[2])]
            if not startable:
                left = [j[0] for j in waiting]
                say(
                    f"queue finished; failed: {sorted(failed) or 'none'}; never started (inputs missing): {left or 'none'}"
                )
                return
        time.sleep(a.poll)


if __name__ == "__main__":
    main()
