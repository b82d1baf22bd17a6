"""benchmarks/project_grid.py: the sweep's wall-time model and the per-child arithmetic it
projects from (no timing is asserted: the inputs are the script's constants)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import project_grid as pg  # noqa: E402


def test_sweep_wall_is_bound_by_the_cores_or_the_longest_chain():
    chains = [(2.0, 10.0), (1.0, 3.0), (4.0, 1.0), (1.0, 1.0)] * 3
    work = sum(2 * s + e for s, e in chains)
    longest = max(s + e for s, e in chains)
    for cores in (2, 3, 8, 64):
        wall = pg.sweep_wall(cores, chains)
        assert wall >= max(longest, work / cores) - 1e-9
    assert pg.sweep_wall(64, chains) == pytest.approx(longest)  # every chain at once
    # 2 cores: one specialists' stage at a time, each extraction waiting behind the queued specialists
    assert pg.sweep_wall(2, [(1.0, 1.0), (1.0, 1.0)]) == pytest.approx(3.0)
    with pytest.raises(ValueError, match="2 cores"):
        pg.sweep_wall(1, chains)


def test_halfcheetah_child_reproduces_its_measured_seconds():
    """At K = 1 the model's HalfCheetah child is the measured one plus its evaluation; K = 4 is
    cheaper per child by the measured step ratio; fewer epochs (Hopper) cost less."""
    for p in ("fp32", "bf16"):
        assert pg.child_seconds("mo-halfcheetah-v5", p, 1) == pytest.approx(
            pg.MEASURED["child_s"][p] + pg.EVAL_S_PER_CHILD
        )
        assert pg.child_seconds("mo-halfcheetah-v5", p, 4) < pg.child_seconds("mo-halfcheetah-v5", p, 1)
        assert pg.child_seconds("mo-hopper-2obj-v5", p, 1) < pg.child_seconds("mo-halfcheetah-v5", p, 1)
        assert pg.child_seconds("mo-ant-2obj-v5", p, 1) > pg.child_seconds("mo-halfcheetah-v5", p, 1)
    # a specialist: 2M steps at the measured env steps/s
    assert pg.specialist_hours("mo-halfcheetah-v5", "fp32") == pytest.approx(2e6 / 77.7 / 3600)
