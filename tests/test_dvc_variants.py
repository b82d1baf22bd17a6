"""Named variants through DVC, in a temporary git + DVC copy of the repository: a variant of
MAPEX-TD3 (another `extract.epochs`) beside the method itself on the same specialists, and
interpolation between shared-init specialists (a specialists variant) beside interpolation
between the usual ones. DVC tracks each variant's overrides exactly: changing one reruns that
variant's stages and nothing else, and the report pairs the two forms of MAPEX-TD3 under the
names the params file gave them."""

from __future__ import annotations

import json

import pytest
import torch
from support.dvc_repo import BIN, make_repo, ran, run
from support.tiny_params import TINY_CHAIN, merge, save_params, with_lists
from test_dvc_methods import stale_stages

# Two sets of specialists and four fronts through DVC (about 3.5 min on the loaded 2-core machine):
# `make test-slow`, so that `make test` stays within 8 minutes (tests/test_variants.py covers the
# rest without DVC).
pytestmark = [pytest.mark.integration, pytest.mark.slow]

VARIANTS = {
    "mapex_td3_gentle": {"of": "mapex_td3", "label": "gentle MAPEX-TD3", "extract": {"epochs": 2, "beta": 5.0}},
    "td3_shared": {"of": "td3", "td3": {"shared_init": True}},
    "interpolate_td3_shared": {"of": "interpolate_td3", "specialists": "td3_shared"},
}


def test_variants_run_side_by_side_and_rerun_alone(tmp_path_factory):
    methods = ["mapex_td3", "mapex_td3_gentle", "warmup_only_td3", "interpolate_td3", "interpolate_td3_shared"]
    params = merge(
        TINY_CHAIN,
        {
            "methods": methods,
            "variants": VARIANTS,
            "extract": {"iterations": 1},
            "report": {"pairs": [["mapex_td3_gentle", "mapex_td3"], ["interpolate_td3_shared", "interpolate_td3"]]},
        },
    )
    params = with_lists(params)
    root = make_repo(tmp_path_factory.mktemp("variants"), params)
    out = run([str(BIN / "dvc"), "repro"], root)
    # one stage per method, a variant's named for it
    assert {"train_specialist", "train_specialist_variant", *methods} <= ran(out)
    for m in methods:
        metrics = json.loads((root / "data" / "score" / m / "seed0" / "metrics.json").read_text())
        assert metrics["method"] == m
    # the variant starts from the same specialists as the method it varies, with its own params
    gentle = json.loads((root / "data" / "score" / "mapex_td3_gentle" / "seed0" / "metrics.json").read_text())
    plain = json.loads((root / "data" / "score" / "mapex_td3" / "seed0" / "metrics.json").read_text())
    assert gentle["specialists"] == plain["specialists"]
    # each front records the extract values it ran with: the variant's overrides, the file's for the method
    # (moved from the payoff harness's test: the two forms differ in their AWR phase only)
    recorded = {
        m: torch.load(root / "data" / "fronts" / m / "seed0" / "population.pt", weights_only=False)["meta"]["params"]
        for m in ("mapex_td3", "mapex_td3_gentle")
    }
    assert (recorded["mapex_td3_gentle"]["extract"]["epochs"], recorded["mapex_td3_gentle"]["extract"]["beta"]) == (
        2,
        5.0,
    )
    assert recorded["mapex_td3"]["extract"]["epochs"] == params["extract"]["epochs"]
    assert {k: v for k, v in recorded["mapex_td3_gentle"]["extract"].items() if k not in ("epochs", "beta")} == {
        k: v for k, v in recorded["mapex_td3"]["extract"].items() if k not in ("epochs", "beta")
    }
    report = (root / "data" / "report" / "report.md").read_text()
    assert "| gentle MAPEX-TD3 |" in report and "| MAPEX-TD3 |" in report
    assert any(
        f"gentle MAPEX-TD3 {verb} MAPEX-TD3 on re-evaluated hypervolume" in report
        for verb in ("beat", "lost to", "tied with")
    ), report
    assert any(
        f"interpolate_td3_shared {verb} interpolation (TD3)" in report for verb in ("beat", "lost to", "tied with")
    )
    assert "| interpolate_td3_shared specialists only |" not in report  # rows are per specialists, not method
    assert "td3_shared specialists only" in report
    assert ran(run([str(BIN / "dvc"), "repro"], root)) == set()

    # one variant's override: that variant's stage alone
    edited = merge(params, {"variants": {"mapex_td3_gentle": {"extract": {"epochs": 3}}}})
    save_params(root / "params.yaml", edited)
    assert stale_stages(root) == {"mapex_td3_gentle"}
    # a specialists variant's override: its specialists alone (what starts from them follows their outputs)
    edited = merge(params, {"variants": {"td3_shared": {"td3": {"learning_starts": 210}}}})
    save_params(root / "params.yaml", edited)
    assert stale_stages(root) == {"train_specialist_variant"}
    # a base section key reruns the method and its variant (the variant inherits it)
    edited = merge(params, {"extract": {"lr": 0.001}})
    save_params(root / "params.yaml", edited)
    assert stale_stages(root) == {"mapex_td3", "mapex_td3_gentle"}  # not warmup_only_td3: it does not read lr

    # a per-env fact (presets/envs.yaml holds one mapping per fact): only the stages that read it
    # (here, where a reproduced repository is at hand; TINY sets env.reference_point, so the score's
    # numbers would not change, but DVC tracks the fact the stage may read)
    save_params(root / "params.yaml", params)
    facts = root / "presets" / "envs.yaml"
    text = facts.read_text()
    for old, new, stale in (
        ("  mo-halfcheetah-v5: [-100.0, -4500.0]", "  mo-halfcheetah-v5: [-101.0, -4500.0]", {"score"}),
        (
            "  mo-halfcheetah-v5: [x velocity, energy efficiency]",
            "  mo-halfcheetah-v5: [speed, energy]",
            {"report", "render"},
        ),
        ("  mo-halfcheetah-v5: {epochs: 20,", "  mo-halfcheetah-v5: {epochs: 21,", {"mapex_td3", "mapex_td3_gentle"}),
    ):
        assert old in text
        facts.write_text(text.replace(old, new))
        assert stale_stages(root) == stale, old
    facts.write_text(text)
    assert stale_stages(root) == set()
