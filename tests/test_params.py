"""params.yaml validation: defaults, rejected keys and values, and the wording of the errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from pipeline.params import MOVED_KEYS, EnvParams, ParamsError, RunParams, load_params, section
from pipeline.params.common import DERIVED_KEYS, GENERATED_BEGIN, GENERATED_END
from pipeline.params.extract import WARMUP_ONLY_KEYS, ExtractParams
from pipeline.params.planned import run_lists
from pipeline.params.runlists import derived_lists
from pipeline.params.td3 import TD3Params
from pipeline.params.tracked import tidied_text as synced_text
from pipeline.params.train_specialist import TrainSpecialistParams, check_against_td3

REPO = Path(__file__).resolve().parents[1]


def validate_td3(values: dict) -> TD3Params:
    return section({"td3": values}, "td3", TD3Params)


def validate_ts(values: dict) -> TrainSpecialistParams:
    return section({"train_specialist": values}, "train_specialist", TrainSpecialistParams)


def test_defaults_are_the_papers_td3_table():
    p = TD3Params()
    # Appendix table "PDERL and TD3 hyperparameters".
    assert p.learning_starts == 25_000
    assert p.gamma == 0.99
    assert p.tau == 0.005
    assert p.hidden_sizes == [256, 256]
    assert p.actor_lr == 3e-4 and p.critic_lr == 3e-4
    assert p.batch_size == 256
    assert p.buffer_size == 1_000_000
    assert p.exploration_noise == 0.1
    assert p.policy_noise == 0.2
    assert p.noise_clip == 0.5
    assert p.policy_freq == 2
    assert TrainSpecialistParams().total_steps == 2_000_000
    assert EnvParams().max_episode_steps == 750


def test_missing_section_takes_the_defaults():
    assert section({}, "td3", TD3Params) == TD3Params()
    assert section({"td3": None}, "td3", TD3Params) == TD3Params()
    assert section({}, "train_specialist", TrainSpecialistParams) == TrainSpecialistParams()
    assert section({"train_specialist": None}, "train_specialist", TrainSpecialistParams) == TrainSpecialistParams()


def test_unknown_key_is_rejected_and_named():
    with pytest.raises(ParamsError) as info:
        validate_td3({"gama": 0.9})
    msg = str(info.value)
    assert "td3.gama" in msg
    assert "unknown key" in msg
    assert "0.9" in msg


@pytest.mark.parametrize(
    ("name", "key", "value", "expected"),
    [
        ("td3", "gamma", 1.5, "less than 1"),
        ("td3", "tau", 0.0, "greater than 0"),
        ("td3", "batch_size", -3, "greater than 0"),
        ("td3", "policy_freq", 0, "greater than or equal to 1"),
        ("td3", "batch_size", "big", "valid integer"),
        ("train_specialist", "device", "tpu", "'auto', 'cpu' or 'cuda'"),
    ],
)
def test_bad_value_message_names_key_value_and_expectation(name, key, value, expected):
    validate = validate_td3 if name == "td3" else validate_ts
    with pytest.raises(ParamsError) as info:
        validate({key: value})
    msg = str(info.value)
    assert f"{name}.{key} = {value!r}" in msg
    assert expected in msg
    assert msg.startswith("params.yaml: invalid params")


def test_every_failing_key_is_reported():
    with pytest.raises(ParamsError) as info:
        validate_td3({"gamma": 2.0, "tau": -1.0})
    msg = str(info.value)
    assert "td3.gamma = 2.0" in msg
    assert "td3.tau = -1.0" in msg


def test_learning_starts_below_batch_size_is_rejected():
    with pytest.raises(ParamsError, match=r"learning_starts \(100\) must be >= batch_size \(256\)"):
        validate_td3({"learning_starts": 100})
    # Equal is fine.
    assert validate_td3({"learning_starts": 256}).learning_starts == 256


def test_learning_starts_must_leave_steps_to_train():
    """The one check across td3 and train_specialist: it names both keys, and is exactly <."""
    with pytest.raises(ValueError) as info:
        check_against_td3(validate_ts({"total_steps": 500}), validate_td3({"learning_starts": 500}))
    msg = str(info.value)
    assert "td3.learning_starts (500)" in msg and "train_specialist.total_steps (500)" in msg
    with pytest.raises(ValueError, match=r"td3.learning_starts \(25000\) must be < train_specialist.total_steps"):
        check_against_td3(validate_ts({"total_steps": 1000}), TD3Params())
    check_against_td3(validate_ts({"total_steps": 501}), validate_td3({"learning_starts": 500}))  # one step trains


def test_non_positive_hidden_size_is_rejected():
    with pytest.raises(ParamsError, match="hidden_sizes must be positive"):
        validate_td3({"hidden_sizes": [64, 0]})


def test_params_are_frozen():
    p = TD3Params()
    with pytest.raises(Exception):
        p.gamma = 0.5  # type: ignore[misc]
    with pytest.raises(Exception):
        TrainSpecialistParams().total_steps = 5  # type: ignore[misc]


@given(st.floats(allow_nan=False, allow_infinity=False, min_value=-5, max_value=5))
def test_gamma_accepted_exactly_on_its_range(gamma):
    inside = 0 <= gamma < 1
    if inside:
        assert validate_td3({"gamma": gamma}).gamma == gamma
    else:
        with pytest.raises(ParamsError, match="td3.gamma"):
            validate_td3({"gamma": gamma})


@given(st.integers(1, 400), st.integers(1, 400))
def test_cross_field_rule_is_exactly_learning_starts_ge_batch_size(learning_starts, batch_size):
    values = {"learning_starts": learning_starts, "batch_size": batch_size}
    if learning_starts >= batch_size:
        assert validate_td3(values).batch_size == batch_size
    else:
        with pytest.raises(ParamsError, match="must be >= batch_size"):
            validate_td3(values)


# --- the file level: load_params ----------------------------------------------------------


def test_unknown_top_level_section_is_rejected(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({"env": {"id": "mo-swimmer-v5"}, "trian_specialist": {"total_steps": 5}}))
    with pytest.raises(ParamsError) as info:
        load_params(path)
    msg = str(info.value)
    assert str(path) in msg
    assert "trian_specialist" in msg
    assert "train_specialist" in msg  # the list of what is expected


def test_missing_file_invalid_yaml_and_non_mapping(tmp_path):
    with pytest.raises(ParamsError, match="not found"):
        load_params(tmp_path / "absent.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("env: [unclosed\n")
    with pytest.raises(ParamsError, match="not valid YAML"):
        load_params(bad)
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(ParamsError, match="expected a mapping"):
        load_params(bad)


def test_section_error_names_the_params_file(tmp_path, write_params):
    path = write_params(tmp_path, {"td3": {"gamma": 1.5}})
    raw = load_params(path)
    with pytest.raises(ParamsError) as info:
        section(raw, "td3", TD3Params, path)
    assert str(info.value).startswith(f"{path}: invalid params")
    assert "td3.gamma = 1.5" in str(info.value)


def test_old_params_file_with_an_agent_key_under_train_specialist_names_its_new_home(tmp_path):
    """A params file written before the td3 section existed fails on load, naming each moved key
    with its new home, rather than the stages silently taking td3's defaults."""
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({"train_specialist": {"actor_lr": 0.001, "total_steps": 10}}))
    with pytest.raises(ParamsError) as info:
        load_params(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: ")
    assert "train_specialist.actor_lr -> td3.actor_lr" in msg
    assert "total_steps" not in msg  # a run key stays where it is
    # every moved key of the file is named, in one line
    path.write_text(
        yaml.safe_dump({"train_specialist": {"total_steps": 10, "learning_starts": 5, "hidden_sizes": [8]}})
    )
    with pytest.raises(ParamsError) as info:
        load_params(path)
    msg = str(info.value)
    assert "train_specialist.learning_starts -> td3.learning_starts" in msg
    assert "train_specialist.hidden_sizes -> td3.hidden_sizes" in msg
    assert "\n" not in msg
    # the same values in their new home load
    path.write_text(yaml.safe_dump({"td3": {"actor_lr": 0.001}, "train_specialist": {"total_steps": 10}}))
    raw = load_params(path)
    assert section(raw, "td3", TD3Params, path).actor_lr == 0.001
    assert section(raw, "train_specialist", TrainSpecialistParams, path).total_steps == 10


def test_moved_keys_are_exactly_the_td3_section():
    """Every key of section td3 came from train_specialist, and none is still there: a key added
    to either model must be placed in the map of moved keys (or kept out of it) on purpose."""
    new, keys = MOVED_KEYS["train_specialist"]
    assert new == "td3"
    added_since = {
        "shared_init",
        "shared_prefix_steps",
        "shared_prefix_weights",
    }  # new to td3, never in train_specialist
    assert set(keys) == set(TD3Params.model_fields) - added_since
    assert not set(keys) & set(TrainSpecialistParams.model_fields)


def test_run_params_reject_duplicates_and_negatives():
    assert section({"seeds": [3, 1], "objectives": [1]}, "", RunParams) == RunParams(seeds=[3, 1], objectives=[1])
    with pytest.raises(ParamsError, match=r"seeds = \[1, 1\].*unique"):
        section({"seeds": [1, 1]}, "", RunParams)
    with pytest.raises(ParamsError, match=r"objectives = \[-1\].*>= 0"):
        section({"objectives": [-1]}, "", RunParams)
    with pytest.raises(ParamsError, match="seeds"):
        section({"seeds": []}, "", RunParams)


def test_tiny_preset_validates(tiny_params):
    raw = load_params(tiny_params)
    cfg = section(raw, "train_specialist", TrainSpecialistParams, tiny_params)
    td3 = section(raw, "td3", TD3Params, tiny_params)
    assert cfg.total_steps == 350 and td3.hidden_sizes == [32, 32]
    check_against_td3(cfg, td3)
    assert section(raw, "env", EnvParams, tiny_params).max_episode_steps == 100


def test_repository_params_file_validates():
    path = REPO / "params.yaml"
    raw = load_params(path)
    section(raw, "env", EnvParams, path)
    section(raw, "", RunParams, path)
    cfg = section(raw, "train_specialist", TrainSpecialistParams, path)
    td3 = section(raw, "td3", TD3Params, path)
    assert td3.learning_starts < cfg.total_steps


def _run(name, stage, variant, kind, specialists=None, of=None):
    """One entry of derived_lists' method_runs."""
    return {
        "name": name,
        "stage": stage,
        "variant": variant,
        "kind": kind,
        "specialists": specialists or kind,
        "of": of,
    }


def test_run_lists_are_derived_from_methods_and_checked():
    ok = {
        "seeds": [0, 1],
        "pderl_seeds": [0, 1],
        "fidelity_from": ["td3", "pderl"],
        "posthoc_from": ["pderl"],
        "methods": ["mapex_td3", "mapex_pderl", "mapex_posthoc_pderl"],
    }
    assert section(ok, "", RunParams).posthoc_from == ["pderl"]
    assert derived_lists(ok["methods"], ok["seeds"]) == {
        k: v for k, v in ok.items() if k not in ("seeds", "methods")
    } | {
        "td3_seeds": [0, 1],
        "imported_seeds": [],
        "import_collect": [],
        "import_buffered": [],
        "import_train": [],
        "export_methods": [],
        "specialist_variants": [],
        # one stage per method, from its base's template
        "method_runs": [
            _run("mapex_td3", "extract", "mapex", "td3"),
            _run("mapex_pderl", "extract", "mapex", "pderl"),
            _run("mapex_posthoc_pderl", "extract_posthoc", "mapex_posthoc", "pderl"),
        ],
        "run_seeds": [0, 1],
        "run_objectives": [0, 1],
        "run_methods": ["mapex_td3", "mapex_pderl", "mapex_posthoc_pderl"],
        "variant_labels": {},
    }
    # a derived list that disagrees with methods names the list and the command that fixes it
    with pytest.raises(
        ParamsError, match=r"posthoc_from = \['pderl'\], but methods .* make it \['td3'\]: they are derived"
    ):
        section({**ok, "methods": ["mapex_td3", "mapex_pderl", "mapex_posthoc_td3"]}, "", RunParams)
    with pytest.raises(ParamsError, match=r"pderl_seeds = \[\], but .* make it \[0, 1\]"):
        section({**ok, "pderl_seeds": []}, "", RunParams)
    # PDERL specialists that no method reads may still be trained
    assert section(
        {"seeds": [0], "pderl_seeds": [0], "methods": ["mapex_td3", "warmup_only_td3"]}, "", RunParams
    ).pderl_seeds == [0]
    with pytest.raises(ParamsError, match=r"unknown methods \['mapex_awr_td3'\]"):
        section({**ok, "methods": ["mapex_awr_td3"]}, "", RunParams)
    with pytest.raises(ParamsError, match="posthoc_from"):
        section({**ok, "posthoc_from": ["sac"]}, "", RunParams)


def test_any_set_of_methods_plans_one_stage_each():
    """Each method has a stage of its own, so no set of methods needs another beside it (the
    matrices over variants x kinds, which did, are gone): MAPEX from PDERL specialists without
    warm-up only, warm-up only from imported specialists alone."""
    lists = derived_lists(["mapex_td3", "warmup_only_td3", "mapex_pderl"], [0])
    assert [r["name"] for r in lists["method_runs"]] == ["mapex_td3", "warmup_only_td3", "mapex_pderl"]
    assert lists["fidelity_from"] == ["td3", "pderl"] and lists["pderl_seeds"] == [0]
    imports = [{"objective": k, "file": f"models/td3_obj{k}.zip", "format": "sb3"} for k in (0, 1)]
    alone = derived_lists(["mapex_posthoc_imported", "warmup_only_imported"], [0, 1], imports)
    assert alone["method_runs"] == [
        _run("mapex_posthoc_imported", "extract_posthoc", "mapex_posthoc", "imported"),
        _run("warmup_only_imported", "warmup_only", "warmup_only", "imported"),
    ]
    assert alone["posthoc_from"] == ["imported"] and alone["fidelity_from"] == [] and alone["td3_seeds"] == []
    assert alone["imported_seeds"] == [0, 1]
    both = derived_lists(["mapex_td3", "warmup_only_imported", "mapex_posthoc_imported"], [0], imports)
    assert both["fidelity_from"] == ["td3"] and both["td3_seeds"] == [0]


def test_imports_may_leave_objectives_to_be_trained_here():
    """import_specialists.policies may cover some objectives: the others are import_train (stage
    train_specialist_imported trains them here); an entry for every objective trains nothing, as before;
    an objective outside `objectives` is one line naming it."""
    methods = ["mapex_posthoc_imported", "warmup_only_imported"]
    speed = [{"objective": 0, "file": "models/speed.zip", "format": "sb3"}]
    lists = derived_lists(methods, [0, 1], speed, objectives=[0, 1])
    assert lists["import_train"] == [1] and lists["imported_seeds"] == [0, 1]
    no_statistics = {"normalize": "none", "normalize_dep": "models/speed.zip"}
    assert lists["import_collect"] == [speed[0] | no_statistics]
    assert lists["td3_seeds"] == [] and lists["posthoc_from"] == ["imported"]
    assert derived_lists(methods, [0], speed, objectives=[0, 1, 2])["import_train"] == [1, 2]
    both = speed + [{"objective": 1, "file": "models/energy.zip", "format": "sb3"}]
    assert derived_lists(methods, [0], both, objectives=[0, 1])["import_train"] == []
    # entries no method reads train nothing either
    assert derived_lists(["mapex_td3", "warmup_only_td3"], [0], speed)["import_train"] == []
    with pytest.raises(
        ValueError, match=r"^import_specialists.policies: objective 2 is not one of objectives = \[0, 1\]$"
    ):
        derived_lists(methods, [0], [{"objective": 2, "file": "m.zip", "format": "sb3"}], objectives=[0, 1])
    # the validated section: the list follows `objectives`, and a stale one names the command that fixes it
    ok = {"seeds": [0], "objectives": [0, 1], "methods": methods, **derived_lists(methods, [0], speed)}
    assert RunParams.model_validate(ok, context={"imports": speed}).import_train == [1]
    with pytest.raises(ValueError, match=r"import_train = \[1\], but .* make it \[1, 2\]: they are derived"):
        RunParams.model_validate({**ok, "objectives": [0, 1, 2]}, context={"imports": speed})
    # the plan derives it from the file's own objectives
    text = yaml.safe_dump(
        {
            "seeds": [0],
            "objectives": [0, 1],
            "methods": methods,
            "import_specialists": {"policies": speed, "collect_rows": 100, "exploration_noise": 0.1},
        },
        sort_keys=False,
    )
    assert run_lists(yaml.safe_load(synced_text(text)))["import_train"] == [1]
    with pytest.raises(ValueError, match=r"^params.yaml: import_specialists.policies: objective 0 is not one of"):
        synced_text(text.replace("- 0\n- 1\n", "- 1\n- 2\n", 1))


def test_plan_keeps_the_users_file_and_drops_derived_lists_and_an_old_generated_block():
    text = (
        "# my comment\nseeds: [0, 1]   # two seeds\nmethods: [mapex_pderl, warmup_only_pderl, mopderl]\n"
        "fidelity_from: [td3]   # stale, hand-written\n\nextract:\n  beta: 0.5\n"
    )
    synced = synced_text(text)
    raw = yaml.safe_load(synced)
    assert not set(raw) & set(DERIVED_KEYS)  # nothing derived in the file the user edits
    lists = run_lists(raw)
    assert lists["fidelity_from"] == ["pderl"] and lists["pderl_seeds"] == [0, 1]
    assert [r["name"] for r in lists["method_runs"]] == ["mapex_pderl", "warmup_only_pderl", "mopderl"]
    # the extract keys stage warmup_only tracks are filled in at their defaults; beta stays
    assert raw["extract"] == {"beta": 0.5} | {k: ExtractParams.model_fields[k].default for k in WARMUP_ONLY_KEYS}
    assert synced.startswith("# my comment\nseeds: [0, 1]   # two seeds\nmethods:") and "stale" not in synced
    assert synced_text(synced) == synced  # syncing twice changes nothing
    # an older file's generated block goes, whatever it held
    old = (
        f"seeds: [0]\nmethods: [mapex_td3]\n{GENERATED_BEGIN}\ntd3_seeds: [5]\n{GENERATED_END}\nextract:\n  beta: 0.5\n"
    )
    assert synced_text(old) == synced_text("seeds: [0]\nmethods: [mapex_td3]\nextract:\n  beta: 0.5\n")
    assert "td3_seeds" not in synced_text(old) and "generated" not in synced_text(old)
    # without a warm-up-only method nothing is filled in
    plain = yaml.safe_load(synced_text("seeds: [0]\nmethods: [mapex_td3]\nextract:\n  beta: 0.5\n"))
    assert plain["extract"] == {"beta": 0.5} and run_lists(plain)["method_runs"][0]["stage"] == "extract"
    with pytest.raises(ValueError, match="f.yaml: unknown methods"):
        synced_text("methods: [nope]\n", "f.yaml")


def test_the_plan_is_written_beside_and_a_stale_one_is_one_line(tmp_path, cli):
    """`mapex plan` writes dvc.yaml beside params.yaml with only the stages that run; load_params
    merges the derived lists in, and a plan that no longer matches the params file (edited after
    the last plan, as `dvc exp run -S seeds=...` leaves it) is one line naming the key and the
    command. A derived list written into the user's file is refused, naming it."""
    params = tmp_path / "params.yaml"
    params.write_text("seeds: [0, 1]\nmethods: [mapex_td3, warmup_only_td3]\n")
    result = cli("plan", "--params", str(params))
    assert result.exit_code == 0, result.stderr
    dvc = tmp_path / "dvc.yaml"
    stages = yaml.safe_load(dvc.read_text())["stages"]
    assert sorted(stages) == [
        "critic_fidelity",
        "evaluate",
        "mapex_td3",
        "render",
        "report",
        "score",
        "train_specialist",
        "warmup_only_td3",
    ]
    assert stages["mapex_td3"]["matrix"] == {"seed": [0, 1]}  # a method's stage: over the seeds only
    assert stages["train_specialist"]["matrix"] == {"seed": [0, 1]}
    assert "planned 8 stages" in result.stderr
    assert load_params(params)["fidelity_from"] == ["td3"]
    params.write_text("seeds: [0, 1, 2]\nmethods: [mapex_td3, warmup_only_td3]\n")
    with pytest.raises(ParamsError) as err:
        load_params(params)
    assert str(err.value) == (
        f"{dvc}: stale: planned for td3_seeds = [0, 1], but params make it [0, 1, 2]: run `mapex plan`"
    )
    assert load_params(params, check_plan=False)["td3_seeds"] == [0, 1, 2]
    # a file named otherwise is not checked against the dvc.yaml beside it (it is not what DVC reads)
    other = tmp_path / "other.yaml"
    other.write_text(params.read_text())
    assert load_params(other)["run_seeds"] == [0, 1, 2]
    # a derived list written into the user's file beside a plan is refused, naming it
    params.write_text("seeds: [0]\nmethods: [mapex_td3, warmup_only_td3]\ntd3_seeds: [0]\n")
    with pytest.raises(ParamsError, match=r"td3_seeds is derived from methods, variants and seeds: delete it"):
        load_params(params)
    # without a plan beside (a file built by hand for one stage run) inline lists are checked by RunParams
    assert load_params(other)["td3_seeds"] == [0, 1, 2]
    other.write_text("seeds: [0]\nmethods: [mapex_td3, warmup_only_td3]\ntd3_seeds: [5]\n")
    with pytest.raises(ParamsError, match=r"td3_seeds = \[5\], but .* make it \[0\]: they are derived"):
        section(load_params(other), "", RunParams, other)
    # a dvc.yaml from before the plan (it loads params.gen.yaml) is named, and one of the user's own is left alone
    params.write_text("seeds: [0]\nmethods: [mapex_td3, warmup_only_td3]\n")
    dvc.write_text("vars:\n  - params.gen.yaml\nstages: {}\n")
    with pytest.raises(ParamsError, match=r"written before `mapex plan` .*: run `mapex plan`"):
        load_params(params)
    dvc.write_text("stages:\n  mine:\n    cmd: echo\n")
    assert load_params(params)["td3_seeds"] == [0]
    # replanning after the edit brings it back; a failed plan leaves the old dvc.yaml in place
    assert cli("plan", "--params", str(params)).exit_code == 0
    assert yaml.safe_load(dvc.read_text())["stages"]["train_specialist"]["matrix"] == {"seed": [0]}
    before = dvc.read_text()
    params.write_text("seeds: [0]\nmethods: [nope]\n")
    result = cli("plan", "--params", str(params))
    assert result.exit_code != 0 and "unknown methods" in result.stderr and dvc.read_text() == before


def test_every_preset_syncs_to_a_valid_params_file():
    for path in sorted((REPO / "presets").rglob("*.yaml")):
        if path.name == "envs.yaml" or path.parent.name == "studies":  # per-env facts; sweep grids
            continue
        raw = yaml.safe_load(synced_text(path.read_text(), str(path)))
        section(raw, "", RunParams, path)
