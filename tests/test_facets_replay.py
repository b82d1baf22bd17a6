"""benchmarks/facets_replay.py: whether the facet rule changed the gaps a run's roulette drew from,
read from a method's fronts folder (data/fronts/<method>/seedS/population.pt)."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "facets_replay.py"


def replay(fronts: Path, capsys, monkeypatch) -> str:
    """Run the script in this process (no interpreter start-up) on FRONTS; its standard output."""
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), str(fronts)])
    runpy.run_path(str(SCRIPT), run_name="__main__")
    return capsys.readouterr().out


def refusal(fronts: Path, monkeypatch) -> str:
    """The one line the script exits with on FRONTS."""
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), str(fronts)])
    with pytest.raises(SystemExit) as exc:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    return str(exc.value.code)


def test_replay_tells_whether_the_rule_changed_a_draw(tmp_path, capsys, monkeypatch):
    """A thin curved front (issue 31's arc) changes the gaps at ratio 3; a triangle of three of its
    points does not."""
    t = np.linspace(0, np.pi / 2, 12)
    arc = np.stack([np.cos(t), np.sin(t), np.sin(2 * t)], axis=1)
    # iteration 0: the arc's two ends and a middle point; iteration 1: the rest of the arc
    start = [0, 6, 11]
    members = [{"iteration": 0, "returns": arc[i].tolist()} for i in start]
    members += [{"iteration": 1, "returns": arc[i].tolist()} for i in range(12) if i not in start]
    members += [{"iteration": 2, "returns": [0.0, 0.0, 0.0]}]
    fronts = tmp_path / "data" / "fronts" / "mapex_td3"
    (fronts / "seed0").mkdir(parents=True)
    torch.save({"meta": {"n_objectives": 3}, "members": members}, fronts / "seed0" / "population.pt")
    out = replay(fronts, capsys, monkeypatch)
    rows = [line.split("|")[1:-1] for line in out.splitlines() if line.startswith("| 0 ")]
    rows = [[c.strip() for c in row] for row in rows]
    # iteration 1 draws from one triangle (unchanged by the rule); iteration 2 from the whole
    # arc, whose 10 facets the rule replaces by 3 facets and 7 steps (tests/test_gaps.py)
    assert rows[0][:7] == ["0", "1", "3", "3", "1", "1", "no"]
    assert rows[1][:7] == ["0", "2", "12", "12", "10", "10", "yes"]
    assert float(rows[1][7]) < 3.0


def test_replay_refuses_two_objectives_naming_the_file(tmp_path, monkeypatch):
    f = tmp_path / "seed0" / "population.pt"
    f.parent.mkdir(parents=True)
    torch.save({"meta": {"n_objectives": 2}, "members": [{"iteration": 1, "returns": [0.0, 0.0]}]}, f)
    assert refusal(tmp_path, monkeypatch) == f"{f}: 2 objectives; the facet rule is for 3 or more"


def test_replay_names_a_folder_without_fronts(tmp_path, monkeypatch):
    assert refusal(tmp_path, monkeypatch).startswith(f"{tmp_path}: no seedS/population.pt")
