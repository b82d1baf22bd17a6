"""Stage score on a hand-made run whose every number is computed by hand in the comments.

The population (extraction-time returns) and evaluated.csv (re-evaluated returns) are written
directly, so no episode runs; reference point (0, 0).

    id  origin      iteration  env_samples  extraction-time  re-evaluated
    0   specialist  0          100          (10, 1)          (9, 1)
    1   specialist  0          200          (1, 10)          (1, 9)
    2   child       1          300          (6, 6)           (5, 5)
    3   child       2          400          (7, 3)           (2, 2)   dominated by (5, 5)
    4   child       2          500          (2, 2)           (3, 4)   dominated by (5, 5)
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
from pathlib import Path

import pytest
import torch
import typer
import yaml
from typer.testing import CliRunner

import pipeline.params as params_module
from pipeline.core.nets import Actor
from pipeline.core.population import Member, actor_state, save_population
from pipeline.evaluation.reference_points import resolve_reference_point
from pipeline.params import ParamsError
from stages.score import score

ENV_ID = "mo-halfcheetah-v5"
EXTRACT = [(10.0, 1.0), (1.0, 10.0), (6.0, 6.0), (7.0, 3.0), (2.0, 2.0)]
REEVAL = [(9.0, 1.0), (1.0, 9.0), (5.0, 5.0), (2.0, 2.0), (3.0, 4.0)]
ITERATION = [0, 0, 1, 2, 2]
SAMPLES = [100, 200, 300, 400, 500]


@contextlib.contextmanager
def score_section_known():
    """Until pipeline.params.KNOWN_SECTIONS lists `score`, a params file holding a `score`
    section is rejected; let it through for these tests (a no-op once it is listed)."""
    with pytest.MonkeyPatch.context() as mp:
        if "score" not in params_module.KNOWN_SECTIONS:
            mp.setattr(params_module, "KNOWN_SECTIONS", (*params_module.KNOWN_SECTIONS, "score"))
        yield


def write_params(directory: Path, ref: list[float] | None = (0.0, 0.0), score_section: dict | None = None) -> Path:
    env = {"id": ENV_ID} | ({} if ref is None else {"reference_point": list(ref)})
    data = {"env": env, **({"score": score_section} if score_section is not None else {})}
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "params.yaml").write_text(yaml.safe_dump(data))
    return directory / "params.yaml"


def write_population(path: Path, meta_drop: tuple[str, ...] = (), extract=EXTRACT, seed: int = 0) -> None:
    actor = actor_state(Actor(17, 6, [4], [-1.0] * 6, [1.0] * 6))
    members = [
        Member(
            origin="specialist" if i < 2 else "child",
            objective=i if i < 2 else None,
            iteration=it,
            parents=[] if i < 2 else [0, 1],
            target_weight=None if i < 2 else [0.6, 0.8],
            returns=list(r),
            returns_std=[0.0, 0.0],
            eval_episodes=5,
            env_samples=s,
            hidden_sizes=[4],
            actor=actor,
        )
        for i, (r, it, s) in enumerate(zip(extract, ITERATION, SAMPLES))
    ]
    meta = dict(
        env_id=ENV_ID,
        obs_dim=17,
        act_dim=6,
        n_objectives=2,
        action_low=[-1.0] * 6,
        action_high=[1.0] * 6,
        seed=seed,
        method="mapex",
        params={},
    )
    save_population(path, members, {k: v for k, v in meta.items() if k not in meta_drop})


def write_evaluated(directory: Path, record: dict | None = None, drop_column: str | None = None) -> None:
    """evaluated.csv and evaluation.json as the evaluate stage writes them."""
    directory.mkdir(parents=True, exist_ok=True)
    header = [
        "id",
        "origin",
        "objective",
        "iteration",
        "parents",
        "env_samples",
        "obj0_extract",
        "obj1_extract",
        "obj0",
        "obj1",
        "obj0_std",
        "obj1_std",
    ]
    with open(directory / "evaluated.csv", "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow([h for h in header if h != drop_column])
        for i, (x, r, it, s) in enumerate(zip(EXTRACT, REEVAL, ITERATION, SAMPLES)):
            row = dict(
                zip(
                    header,
                    [
                        i,
                        "specialist" if i < 2 else "child",
                        i if i < 2 else "",
                        it,
                        "" if i < 2 else "0;1",
                        s,
                        *x,
                        *r,
                        0.5,
                        0.5,
                    ],
                )
            )
            w.writerow([v for k, v in row.items() if k != drop_column])
    base = {
        "env_id": ENV_ID,
        "method": "mapex",
        "seed": 0,
        "episodes": 10,
        "seed_stream": 1,
        "max_episode_steps": 750,
        "population": 5,
        "env_samples_evaluation": 37500,
    }
    (directory / "evaluation.json").write_text(json.dumps(base if record is None else record))


def invoke(*args) -> tuple[int, str]:
    app = typer.Typer()
    app.command("score")(score)
    app.command("noop")(lambda: None)  # two commands: typer keeps the subcommand name
    with score_section_known():
        result = CliRunner().invoke(app, ["score", *map(str, args)])
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result.exit_code, result.output


@pytest.fixture
def run(tmp_path) -> Path:
    write_population(tmp_path / "population.pt")
    write_evaluated(tmp_path / "evaluated")
    return tmp_path


def score_run(root: Path, params: Path | None = None, *extra) -> tuple[int, str]:
    return invoke(
        "--population",
        root / "population.pt",
        "--evaluated",
        root / "evaluated",
        "--out",
        root / "out",
        "--params",
        params or write_params(root),
        *extra,
    )


def read_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# ---------------------------------------------------------------- known answers


def test_metrics_hand_computed(run):
    code, out = score_run(run, write_params(run, score_section={"utility_weights": 3}))
    assert code == 0, out
    m = json.loads((run / "out" / "metrics.json").read_text())
    front = m["front"]
    # front (1,9), (5,5), (9,1): from (0,0), sweeping x downwards: 9*1 + 5*(5-1) + 1*(9-5) = 33
    assert front["hypervolume"] == pytest.approx(33.0)
    # the paper's: neighbours along obj0 are sqrt(4^2 + 4^2) apart twice -> mean 4 sqrt(2)
    assert front["sparsity"] == pytest.approx(4 * math.sqrt(2))
    # PGMORL's: obj0 sorted 1,5,9 and obj1 sorted 1,5,9: gaps 4,4 and 4,4 -> (16+16+16+16) / (3-1) = 32
    assert front["sparsity_pgmorl"] == pytest.approx(32.0)
    # weights (0,1), (.5,.5), (1,0): best utilities 9, 5, 9 -> 23/3
    assert front["expected_utility"] == pytest.approx(23 / 3)
    assert front["cardinality"] == 3 and front["distinct_count"] == 3
    # ideal (9, 9): box 81
    assert m["ideal_point"] == [9.0, 9.0] and front["hv_fraction"] == pytest.approx(33 / 81)
    # specialists (9,1), (1,9): 9 + 9 - 1*1 = 17
    assert m["specialists"]["hypervolume"] == pytest.approx(17.0)
    assert m["hv_ratio_vs_specialists"] == pytest.approx(33 / 17)
    # extraction-time front (10,1), (7,3), (6,6), (1,10): 10*1 + 7*2 + 6*3 + 1*4 = 46
    assert m["extraction_hypervolume"] == pytest.approx(46.0)
    assert (m["iterations"], m["population"], m["children"], m["env_samples_extraction"]) == (2, 5, 3, 500)
    assert (m["episodes"], m["env_samples_evaluation"], m["method"], m["seed"]) == (10, 37500, "mapex", 0)
    assert (m["reference_point"], m["distinct_tol"], m["utility_weights"]) == ([0.0, 0.0], 0.02, 3)
    assert "provenance" not in m  # a file of its own (--provenance): `dvc metrics show` stays a table of numbers


def test_front_csv_sorted_along_objective_0(run):
    code, out = score_run(run)
    assert code == 0, out
    rows = read_rows(run / "out" / "front.csv")
    assert [(r["id"], r["origin"], r["iteration"], float(r["obj0"]), float(r["obj1"])) for r in rows] == [
        ("1", "specialist", "0", 1.0, 9.0),
        ("2", "child", "1", 5.0, 5.0),
        ("0", "specialist", "0", 9.0, 1.0),
    ]


def test_hypervolume_history_hand_computed(run):
    code, out = score_run(run)
    assert code == 0, out
    rows = read_rows(run / "out" / "hypervolume.csv")
    assert list(rows[0]) == ["iteration", "population", "env_samples", "hypervolume_extract", "hypervolume"]
    got = [
        (
            int(r["iteration"]),
            int(r["population"]),
            int(r["env_samples"]),
            float(r["hypervolume_extract"]),
            float(r["hypervolume"]),
        )
        for r in rows
    ]
    # extraction-time: it 0: 10 + 10 - 1 = 19; it 1 adds (6,6): 10*1 + 6*5 + 1*4 = 44; it 2 adds (7,3): 46.
    # re-evaluated: it 0: 9 + 9 - 1 = 17; it 1 adds (5,5): 9 + 20 + 4 = 33; it 2 adds two dominated points: 33.
    assert got == [(0, 2, 200, 19.0, 17.0), (1, 3, 300, 44.0, 33.0), (2, 5, 500, 46.0, 33.0)]


def test_score_params_change_the_metrics(run):
    # tol 0.7 of the [0, 9] box: (1,9) and (5,5) are 0.63 apart normalised and merge; (9,1) stays
    code, out = score_run(run, write_params(run, score_section={"distinct_tol": 0.7}))
    assert code == 0, out
    assert json.loads((run / "out" / "metrics.json").read_text())["front"]["distinct_count"] == 2
    # another reference point: the front's HV from (-1, -1) is 10*2 + 6*4 + 2*4 = 52
    code, out = score_run(run, write_params(run, ref=[-1.0, -1.0]))
    assert code == 0, out
    assert json.loads((run / "out" / "metrics.json").read_text())["front"]["hypervolume"] == pytest.approx(52.0)


def test_provenance_record_is_written_beside_the_outputs(run):
    code, out = score_run(run, None, "--provenance", run / "records" / "score.json")
    assert code == 0, out
    record = json.loads((run / "records" / "score.json").read_text())
    assert record["stage"] == "score"
    assert {"git_commit", "git_dirty", "versions", "device", "torch_threads"} <= set(record)
    assert record["versions"]["torch"] == torch.__version__
    # OUT holds the numbers only
    assert sorted(p.name for p in (run / "out").iterdir()) == ["front.csv", "hypervolume.csv", "metrics.json"]


def test_outputs_do_not_depend_on_what_ran_them(run, monkeypatch):
    """Another commit (or a dirty checkout) changes the record only: OUT's bytes stay, so DVC
    reruns nothing after a rerun of this stage that changes no number."""
    import pipeline.core.provenance as prov

    outputs = []
    for i, commit in enumerate(["a" * 40, "b" * 40]):
        monkeypatch.setattr(prov, "_git", lambda commit=commit: {"git_commit": commit, "git_dirty": True})
        code, out = score_run(run, None, "--provenance", run / "records" / f"{i}.json")
        assert code == 0, out
        outputs.append({p.name: p.read_bytes() for p in (run / "out").iterdir()})
        assert json.loads((run / "records" / f"{i}.json").read_text())["git_commit"] == commit
    assert outputs[0] == outputs[1]


def test_without_provenance_option_no_record_is_written(run):
    code, out = score_run(run)
    assert code == 0, out
    assert sorted(p.name for p in run.iterdir()) == ["evaluated", "out", "params.yaml", "population.pt"]
    assert sorted(p.name for p in (run / "out").iterdir()) == ["front.csv", "hypervolume.csv", "metrics.json"]


# ---------------------------------------------------------------- bad inputs: one line, exit 2, nothing written


def fails(root: Path, params: Path | None = None, one_line: bool = True) -> str:
    code, out = score_run(root, params)
    assert code == 2, out
    assert not (root / "out").exists(), "nothing may be written on bad input"
    assert out.startswith("error: ") and "Traceback" not in out
    if one_line:  # a params validation error lists its keys one a line; any other error is one line
        assert len(out.strip().splitlines()) == 1, out
    return out


def test_missing_population(tmp_path):
    write_evaluated(tmp_path / "evaluated")
    out = fails(tmp_path)
    assert "population.pt" in out and "not found" in out


@pytest.mark.parametrize("key", ["method", "seed", "env_id"])
def test_population_metadata_key_missing(tmp_path, key):
    write_population(tmp_path / "population.pt", meta_drop=(key,))
    write_evaluated(tmp_path / "evaluated")
    out = fails(tmp_path)
    assert "population.pt" in out and f"'{key}'" in out


def test_population_without_n_objectives_is_not_a_key_error(tmp_path):
    # load_population itself reads meta["n_objectives"]
    write_population(tmp_path / "population.pt", meta_drop=("n_objectives",))
    write_evaluated(tmp_path / "evaluated")
    out = fails(tmp_path)
    assert "population.pt" in out and "'n_objectives'" in out


def test_missing_evaluation_json(run):
    (run / "evaluated" / "evaluation.json").unlink()
    out = fails(run)
    assert "evaluation.json" in out and "not found" in out


def test_missing_evaluated_csv(run):
    (run / "evaluated" / "evaluated.csv").unlink()
    out = fails(run)
    assert "evaluated.csv" in out and "not found" in out


@pytest.mark.parametrize("key", ["episodes", "env_samples_evaluation"])
def test_evaluation_json_key_missing(tmp_path, key):
    write_population(tmp_path / "population.pt")
    write_evaluated(tmp_path / "evaluated")
    record = json.loads((tmp_path / "evaluated" / "evaluation.json").read_text())
    del record[key]
    write_evaluated(tmp_path / "evaluated", record)
    out = fails(tmp_path)
    assert "evaluation.json" in out and f"'{key}'" in out


def test_evaluation_of_another_seed(run):
    record = json.loads((run / "evaluated" / "evaluation.json").read_text()) | {"seed": 3}
    write_evaluated(run / "evaluated", record)
    out = fails(run)
    assert "evaluation.json (seed = 3)" in out and "population.pt (seed = 0)" in out


def test_evaluated_csv_missing_column(tmp_path):
    write_population(tmp_path / "population.pt")
    write_evaluated(tmp_path / "evaluated", drop_column="obj1")
    out = fails(tmp_path)
    assert "evaluated.csv" in out and "obj1" in out


def test_evaluated_csv_of_another_population(tmp_path):
    other = [(10.0, 1.0), (1.0, 10.0), (6.0, 6.0), (7.0, 3.0), (2.0, 2.5)]  # member 4 differs
    write_population(tmp_path / "population.pt", extract=other)
    write_evaluated(tmp_path / "evaluated")
    out = fails(tmp_path)
    assert "evaluated.csv" in out and "row 4" in out


def test_bad_reference_point(run):
    out = fails(run, write_params(run, ref=[-100.0]))
    assert "env.reference_point = [-100.0] has 1 values, the env has 2 objectives" in out


REPO = Path(__file__).resolve().parents[1]
TABLE = REPO / "presets" / "envs.yaml"


@pytest.mark.parametrize(
    "env_id, n, point",
    [
        ("mo-halfcheetah-v5", 2, [-100.0, -4500.0]),
        ("mo-swimmer-v5", 2, [-50.0, -1500.0]),
        ("mo-hopper-v5", 3, [-100.0, -3390.0, -1510.0]),
    ],
)
def test_null_reference_point_is_the_envs_entry_in_the_table(env_id, n, point, tmp_path):
    ref = resolve_reference_point(None, env_id, n, tmp_path / "params.yaml", TABLE)
    assert ref.point.tolist() == point and ref.source.endswith(f"entry {env_id} (env.reference_point is null)")
    # a point set in params wins over the table
    given = resolve_reference_point([1.0] * n, env_id, n, tmp_path / "params.yaml", TABLE)
    assert given.point.tolist() == [1.0] * n and given.source == "env.reference_point in params"


def test_table_entry_of_the_wrong_length_names_the_table(tmp_path):
    with pytest.raises(
        ParamsError, match=r"envs.yaml: reference_point.mo-swimmer-v5 = \[-50.0, -1500.0\] .* has 2 values"
    ):
        resolve_reference_point(None, "mo-swimmer-v5", 3, tmp_path / "params.yaml", TABLE)


def test_score_with_null_reference_point_scores_against_the_table(run, monkeypatch):
    """The stage's default table is presets/envs.yaml of the repository root (DVC's cwd)."""
    monkeypatch.chdir(REPO)
    code, out = score_run(run, write_params(run, ref=None))
    assert code == 0, out
    m = json.loads((run / "out" / "metrics.json").read_text())
    assert m["reference_point"] == [-100.0, -4500.0]
    assert m["reference_point_source"] == ("presets/envs.yaml, entry mo-halfcheetah-v5 (env.reference_point is null)")


def test_score_of_an_env_without_an_entry_derives_its_point_from_the_starting_policies(run):
    """An env the table does not list, with env.reference_point null, is scored against the
    auto rule's point from the run's starting policies (issue 59), and metrics.json says so."""
    table = run / "points.yaml"
    table.write_text("reference_point:\n  mo-swimmer-v5: [-50.0, -1500.0]\n")
    code, out = score_run(run, write_params(run, ref=None), "--reference-points", table)
    assert code == 0, out
    metrics = json.loads((run / "out" / "metrics.json").read_text())
    assert metrics["reference_point_source"].startswith("auto: derived from this run's")
    assert len(metrics["reference_point"]) == 2 and all(math.isfinite(v) for v in metrics["reference_point"])


def test_unknown_score_param(run):
    out = fails(run, write_params(run, score_section={"distinct_tolerance": 0.1}), one_line=False)
    assert "score.distinct_tolerance" in out and "unknown key" in out
