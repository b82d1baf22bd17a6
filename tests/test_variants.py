"""Named variants (pipeline/params/variants.py): what a variant may say, the run lists it adds,
how its overrides reach a stage's sections, and the report's pairs of two forms of one method."""

from __future__ import annotations

import re

import numpy as np
import pytest

from pipeline.params import ParamsError, RunParams, section
from pipeline.params.extract import ExtractParams
from pipeline.params.runlists import derived_lists
from pipeline.params.variants import parse_variants, with_overrides
from pipeline.reporting.presentation import VARIANT_METHODS, label, specialist_kind, use_variants
from pipeline.reporting.runs import Run, methods_in
from pipeline.reporting.verdicts import verdicts

VARIANTS = {
    "mapex_td3_gentle": {"of": "mapex_td3", "label": "gentle", "extract": {"epochs": 2, "beta": 5.0}},
    "td3_shared": {"of": "td3", "td3": {"shared_init": True}},
    "interpolate_td3_shared": {"of": "interpolate_td3", "specialists": "td3_shared"},
    "warmup_shared": {"of": "warmup_only_td3", "specialists": "td3_shared"},
}


@pytest.fixture(autouse=True)
def _no_variants_left():
    yield
    use_variants({})  # the report's registry is per process: leave it empty for the other tests


def test_variants_add_their_own_run_lists():
    methods = ["mapex_td3", "warmup_only_td3", "mapex_td3_gentle", "interpolate_td3_shared", "warmup_shared"]
    lists = derived_lists(methods, [0, 1], variants=VARIANTS)
    assert lists["specialist_variants"] == ["td3_shared"]
    # one stage per method, a variant's from its base's template, naming the base it varies
    assert lists["method_runs"] == [
        {"name": "mapex_td3", "stage": "extract", "variant": "mapex", "kind": "td3", "specialists": "td3", "of": None},
        {
            "name": "warmup_only_td3",
            "stage": "warmup_only",
            "variant": "warmup_only",
            "kind": "td3",
            "specialists": "td3",
            "of": None,
        },
        {
            "name": "mapex_td3_gentle",
            "stage": "extract",
            "variant": "mapex",
            "kind": "td3",
            "specialists": "td3",
            "of": "mapex_td3",
        },
        {
            "name": "interpolate_td3_shared",
            "stage": "interpolate",
            "variant": None,
            "kind": "td3",
            "specialists": "td3_shared",
            "of": "interpolate_td3",
        },
        {
            "name": "warmup_shared",
            "stage": "warmup_only",
            "variant": "warmup_only",
            "kind": "td3",
            "specialists": "td3_shared",
            "of": "warmup_only_td3",
        },
    ]
    # a variant from a kind's own specialists trains that kind even with no plain method of it
    alone = derived_lists(["gentle_pderl"], [3], variants={"gentle_pderl": {"of": "mapex_pderl"}})
    assert alone["pderl_seeds"] == [3] and alone["method_runs"][0]["kind"] == "pderl"
    # validated with the top-level lists: a stale derived list names the command that fixes it
    ok = {"seeds": [0], "methods": methods, "variants": VARIANTS, **derived_lists(methods, [0], variants=VARIANTS)}
    assert section(ok, "", RunParams).variants == VARIANTS
    with pytest.raises(ParamsError, match=r"method_runs = \[\], but .*they are derived"):
        section({**ok, "method_runs": []}, "", RunParams)


@pytest.mark.parametrize(
    "variants, methods, message",
    [
        ({"g": {"of": "mapex_sac"}}, ["g"], r"variants\.g\.of = 'mapex_sac': expected a method of"),
        (
            {"g": {"of": "mopderl", "td3": {"tau": 0.1}}},
            ["g"],
            r"variants\.g: key 'td3' is not one of \['of', 'label', 'specialists', 'mopderl'\]",
        ),
        (
            {"s": {"of": "td3"}, "g": {"of": "mapex_posthoc_td3", "specialists": "s"}},
            ["g"],
            r"variants\.g\.specialists = 's': a variant of mapex_posthoc_td3 starts from its own kind's specialists",
        ),
        ({"g": {"of": "mapex_td3", "td3": {"tau": 0.1}}}, ["g"], r"variants\.g: key 'td3' is not one of"),
        ({"g": {"of": "mapex_td3", "specialists": "pderl"}}, ["g"], r"variants\.g\.specialists = 'pderl'"),
        ({"g": {"of": "mapex_td3", "extract": 3}}, ["g"], r"variants\.g\.extract = 3: expected a mapping"),
        ({"mapex_td3": {"of": "mapex_td3"}}, ["mapex_td3"], r"variants\.mapex_td3: the name is taken"),
        ({"s": {"of": "pderl"}}, ["mapex_td3"], r"variants\.s\.of = 'pderl': specialists variants are of kind"),
        ({"s": {"of": "td3"}}, ["s"], r"methods lists 's', a specialists variant"),
        ({}, ["gentle"], r"unknown methods \['gentle'\]"),
        ({"Bad name": {"of": "mapex_td3"}}, ["mapex_td3"], r"name 'Bad name': expected lower-case"),
    ],
)
def test_a_bad_variant_is_one_line(variants, methods, message):
    with pytest.raises(ValueError, match=message) as err:
        derived_lists(methods, [0], variants=variants)
    assert "\n" not in str(err.value)


def test_overrides_are_merged_key_by_key_and_validated_by_the_section_model():
    raw = {"extract": {"epochs": 20, "lr": 0.001, "hidden_sizes": [64, 64]}, "td3": {"tau": 0.01}}
    gentle = parse_variants(VARIANTS)["mapex_td3_gentle"]
    merged = with_overrides(raw, gentle)
    assert merged["extract"] == {"epochs": 2, "lr": 0.001, "hidden_sizes": [64, 64], "beta": 5.0}
    assert raw["extract"]["epochs"] == 20 and merged["td3"] is raw["td3"]  # the file's params are untouched
    bad = parse_variants({"g": {"of": "mapex_td3", "extract": {"epochs": -1}}})["g"]
    with pytest.raises(ParamsError, match=r"extract\.epochs = -1"):
        section(with_overrides(raw, bad), "extract", ExtractParams)


def _run(method: str, seed: int, hv: float) -> Run:
    metrics = {"front": {"hypervolume": hv}, "iterations": 4}
    empty = np.zeros(0)
    return Run(method, seed, metrics, np.zeros((0, 2)), empty, empty, empty, {}, None)


def test_two_forms_of_one_method_are_paired_under_the_labels_given():
    use_variants(parse_variants(VARIANTS))
    assert label("mapex_td3_gentle") == "gentle" and specialist_kind("interpolate_td3_shared") == "td3_shared"
    assert label("specialists_td3_shared") == "td3_shared specialists only"
    runs = [_run("mapex_td3", s, h) for s, h in enumerate([10.0, 11.0, 12.0])]
    runs += [_run("mapex_td3_gentle", s, h) for s, h in enumerate([20.0, 22.0, 23.0])]
    assert methods_in(runs) == ["mapex_td3", "mapex_td3_gentle"]
    # by default a variant is compared with the method it varies
    (said,) = verdicts(runs)
    assert said.outcome == "beat" and said.sentence.startswith(
        "At this scale (3 seeds, up to 4 iterations), gentle beat"
    )
    assert "MAPEX-TD3" in said.sentence
    # report.pairs names any two runs, in either order
    (said,) = verdicts(runs, pairs=[["mapex_td3", "mapex_td3_gentle"]])
    assert said.outcome == "lost" and "MAPEX-TD3 lost to gentle" in said.sentence
    assert verdicts(runs, pairs=[]) == []
    use_variants({})
    assert VARIANT_METHODS == {} and label("mapex_td3_gentle") == "mapex_td3_gentle"


def test_a_stage_run_as_a_variant_checks_the_name_and_its_base(tmp_path, cli, write_params):
    """`--method NAME` must be a variant of the method the stage runs, named in params' variants:
    otherwise one line and exit 2, before anything is read."""
    methods = ["mapex_td3", "warmup_only_td3", "mapex_td3_gentle"]
    params = write_params(
        tmp_path, {"methods": methods, "variants": {"mapex_td3_gentle": VARIANTS["mapex_td3_gentle"]}}
    )
    args = ["extract", "--specialists", tmp_path / "none", "--out", tmp_path / "out", "--params", params]
    r = cli(*args, "--method", "nope")
    assert r.exit_code == 2 and "variants has no entry 'nope'" in r.output, r.output
    r = cli(*args, "--variant", "warmup_only", "--method", "mapex_td3_gentle")
    assert r.exit_code == 2, r.output
    assert (
        "--method mapex_td3_gentle: variants.mapex_td3_gentle.of is 'mapex_td3', but this run is 'warmup_only_td3'"
        in r.output
    )
    # a bad override is named by its variant
    bad = write_params(
        tmp_path / "bad",
        {"methods": methods, "variants": {"mapex_td3_gentle": {"of": "mapex_td3", "extract": {"epochs": -2}}}},
    )
    r = cli(
        "extract",
        "--specialists",
        tmp_path / "none",
        "--out",
        tmp_path / "out",
        "--params",
        bad,
        "--method",
        "mapex_td3_gentle",
    )
    assert (
        r.exit_code == 2
        and "with the overrides of variants.mapex_td3_gentle" in r.output
        and "extract.epochs = -2" in r.output
    )
    assert not (tmp_path / "out").exists()


def test_a_variant_of_any_base_is_a_stage_of_its_own_from_params_alone():
    """MAPEX-PostHoc and MORL/D had no variant stage; now the plan writes every method that runs a
    stage of its own from its base's template, so a variant of either is an edit of params (the
    test params EVERY_STAGE list one of each): the stage is named for the variant, runs its base's
    command with --method, tracks variants.<name> and writes data/fronts/<name>/."""
    import yaml
    from support.tiny_params import EVERY_STAGE

    from pipeline.params.plan import plan_text

    stages = yaml.safe_load(plan_text(EVERY_STAGE))["stages"]
    posthoc, morld = stages["mapex_posthoc_td3_gentle"], stages["morld_small"]
    assert posthoc["cmd"].startswith(
        "mapex extract --seed ${item.seed} --variant mapex_posthoc --kind td3 --method mapex_posthoc_td3_gentle"
    )
    assert "data/posthoc/td3/seed${item.seed}" in posthoc["deps"]  # the kind's post-hoc critics, fitted once
    assert "variants.mapex_posthoc_td3_gentle" in posthoc["params"]
    assert morld["cmd"].startswith(
        "mapex morld --seed ${item.seed} --method morld_small --out data/fronts/morld_small/"
    )
    assert "variants.morld_small" in morld["params"] and "variants.morld_small" not in stages["morld"]["params"]
    assert morld["matrix"] == posthoc["matrix"] == {"seed": EVERY_STAGE["seeds"]}
    # the report's matrices list them like any method
    assert {"mapex_posthoc_td3_gentle", "morld_small"} <= set(stages["evaluate"]["matrix"]["method"])


# ---------------------------------------------------------------- the built-in hybrid


def test_the_hybrid_is_a_built_in_method_planned_with_no_variants_entry(tmp_path):
    """`methods: [hybrid_td3]` runs MAPEX-TD3 with the hybrid's keys (METHODS' row), its stage
    passing --method and tracking no variants.hybrid_td3 (the file has none: the definition is code)."""
    from pipeline.params.methods import HYBRID, METHODS

    assert METHODS["hybrid_td3"].of == "mapex_td3" and METHODS["hybrid_td3"].overrides == {"extract": HYBRID}
    lists = derived_lists(["mapex_td3", "hybrid_td3"], [0], variants=None)
    (run,) = [r for r in lists["method_runs"] if r["name"] == "hybrid_td3"]
    assert run == {
        "name": "hybrid_td3",
        "stage": "extract",
        "variant": "mapex",
        "kind": "td3",
        "specialists": "td3",
        "of": "mapex_td3",
        "builtin": True,
    }
    built = parse_variants(None)["hybrid_td3"]
    resolved = section(with_overrides({"extract": {"epochs": 3}}, built), "extract", ExtractParams)
    assert (resolved.init, resolved.seed_interpolation, resolved.epochs) == ("interpolate", 48, 3)
    from pipeline.params.plan import method_block, plan_text

    template = [
        "  extract:\n",
        "    cmd: mapex extract{method_option}\n",
        "    params:\n",
        "      - {variant_params}\n",
    ]
    assert method_block(template, run) == [
        "  hybrid_td3:\n",
        "    cmd: mapex extract --method hybrid_td3\n",
        "    params:\n",
    ]
    text = plan_text({"methods": ["mapex_td3", "hybrid_td3"], "seeds": [0]}, "params.yaml")
    stage = re.search(r"\n  hybrid_td3:\n(.*?)\n  \w+:\n", text, flags=re.S).group(1)
    assert "--method hybrid_td3" in stage and "variants.hybrid_td3" not in stage


def test_an_entry_named_for_the_hybrid_refines_it_and_keeps_its_stage():
    """The study presets' `hybrid_td3: {of: mapex_td3, extract: {...}}` entries: accepted, merged
    over the built-in's keys, and tracked (variants.hybrid_td3) as before it had a name."""
    entry = {"of": "mapex_td3", "label": "hybrid (grid)", "extract": {"init": "interpolate", "seed_interpolation": 12}}
    parsed = parse_variants({"hybrid_td3": entry})
    assert parsed["hybrid_td3"].overrides == {"extract": {"init": "interpolate", "seed_interpolation": 12}}
    assert parsed["hybrid_td3"].label == "hybrid (grid)"
    (run,) = [r for r in derived_lists(["hybrid_td3"], [0], variants={"hybrid_td3": entry})["method_runs"]]
    assert "builtin" not in run and run["of"] == "mapex_td3"
    # a variant of the hybrid is a variant of its base with the hybrid's keys
    further = parse_variants({"hybrid_e2": {"of": "hybrid_td3", "extract": {"epochs": 2}}})["hybrid_e2"]
    assert further.of == "mapex_td3"
    assert further.overrides == {"extract": {"init": "interpolate", "seed_interpolation": 48, "epochs": 2}}


@pytest.mark.parametrize(
    "entry, message",
    [
        ({"of": "mapex_pderl"}, "variants.hybrid_td3.of = 'mapex_pderl': hybrid_td3 is the built-in hybrid"),
        ({"of": "mapex_td3", "extract": {"init": "warmup"}}, "variants.hybrid_td3.extract.init = 'warmup'"),
    ],
)
def test_an_entry_that_would_unmake_the_hybrid_is_one_line(entry, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        parse_variants({"hybrid_td3": entry})


def test_the_report_knows_a_hybrid_from_the_params_and_shows_it_once():
    from pipeline.params.variants import is_hybrid

    variants = parse_variants({"mine": {"of": "mapex_posthoc_td3", "extract": {"init": "interpolate"}}})
    raw = {"extract": {"init": "warmup"}}
    got = [
        m
        for m in ("mapex_td3", "hybrid_td3", "mine", "warmup_only_td3", "interpolate_td3")
        if is_hybrid(raw, m, variants)
    ]
    assert got == ["hybrid_td3", "mine"]
    # with the file's own section interpolating, the plain method is a hybrid too (warm-up only never)
    assert is_hybrid({"extract": {"init": "interpolate"}}, "mapex_td3", {})
    assert not is_hybrid({"extract": {"init": "interpolate"}}, "warmup_only_td3", {})
    use_variants(variants)
    assert label("hybrid_td3") == "hybrid (interpolated start)" and label("mine") == "mine"
    empty = np.zeros(0)
    runs = [Run(m, 0, {}, np.zeros((0, 2)), empty, empty, empty, {}, None) for m in ("hybrid_td3", "mapex_td3")]
    assert methods_in(runs) == ["mapex_td3", "hybrid_td3"]
