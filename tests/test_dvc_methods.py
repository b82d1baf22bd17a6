"""Every method through one evaluate -> score -> report chain, in a temporary git + DVC copy of
the repository: TD3 and PDERL specialists, the extraction variants from both, post-hoc critics
and the baselines (MORL/D when its optional extra is installed); then an edit to MAPEX's code
leaves everything but extraction up to date, and params edits rerun only the stages that read
them."""

from __future__ import annotations

import json
import os
import re
import subprocess

import pytest
from support.dvc_repo import BIN, make_repo, ran, run
from support.tiny_params import MOPDERL_TINY, MORLD_TINY, PDERL_TINY, save_params, with_lists
from support.tiny_params import TINY_CHAIN as TINY

# Every method's stages through one DVC chain: `make test-fast` leaves this file out.
pytestmark = pytest.mark.integration


# Every method through one evaluate -> score -> report chain: TD3 and PDERL specialists, the
# extraction variants from both, and the baselines (MORL/D when its optional extra is installed).
@pytest.mark.slow  # every method's stages through DVC: `make test-slow` (CI runs it)
def test_every_method_is_scored_by_one_chain(tmp_path_factory):
    try:
        import morl_baselines  # noqa: F401

        baselines = ["mopderl", "morld"]
    except ImportError:  # the optional extra is not installed: the chain without MORL/D
        baselines = ["mopderl"]
    methods = ["mapex_td3", "mapex_posthoc_td3", "mapex_pderl", "mapex_posthoc_pderl", *baselines]
    methods += ["warmup_only_td3", "warmup_only_pderl", "interpolate_td3", "interpolate_pderl"]
    # a variant of MAPEX-PostHoc, added by params alone: the plan writes it a stage of its own
    methods += ["posthoc_gentle"]
    # the hybrid, a built-in variant: no variants entry, its definition is METHODS'
    methods += ["hybrid_td3"]
    params = {
        **TINY,
        "methods": methods,
        "variants": {"posthoc_gentle": {"of": "mapex_posthoc_td3", "extract": {"beta": 0.5}}},
        "td3": {**TINY["td3"], "buffer_size": 2000},
        "train_pderl": PDERL_TINY,
        "mopderl": MOPDERL_TINY,
        "morld": MORLD_TINY,
        "extract": {**TINY["extract"], "iterations": 1},
        "evaluate": {"episodes": 1},
    }
    params = with_lists(params)
    root = make_repo(tmp_path_factory.mktemp("methods"), params)
    out = run([str(BIN / "dvc"), "repro"], root)
    assert {"train_pderl", "mopderl", "mapex_td3", "posthoc_gentle", "evaluate", "score", "report"} <= ran(out)
    for m in methods:
        metrics = json.loads((root / "data" / "score" / m / "seed0" / "metrics.json").read_text())
        assert metrics["method"] == m and metrics["front"]["cardinality"] >= 1
    # the hybrid ran with its keys (interpolated starts, the population seeded with the grid) and
    # the report names it with its label, against the method it varies
    hybrid = json.loads((root / "data" / "score" / "hybrid_td3" / "seed0" / "metrics.json").read_text())
    assert "init_fallbacks" in hybrid and "seed_interpolation" in hybrid, sorted(hybrid)
    assert "hybrid (interpolated start)" in (root / "data" / "report" / "report.md").read_text()
    # PDERL's policy sets start the PDERL methods (population + RL actor per objective); TD3 one each
    assert (
        json.loads((root / "data" / "score" / "mapex_pderl" / "seed0" / "metrics.json").read_text())[
            "starting_policies"
        ]
        == 8
    )
    # interpolation starts from the same policy sets, then mixes one per objective
    interp = json.loads((root / "data" / "score" / "interpolate_pderl" / "seed0" / "metrics.json").read_text())
    assert interp["starting_policies"] == 8 and interp["children"] == 1  # 1 iteration x 1 child
    assert (
        json.loads((root / "data" / "score" / "mapex_td3" / "seed0" / "metrics.json").read_text())["starting_policies"]
        == 2
    )
    report = (root / "data" / "report" / "report.md").read_text()
    for name in (
        "| MAPEX |",
        "| MAPEX-PostHoc |",
        "| MAPEX-TD3 |",
        "| MOPDERL |",
        "| PDERL specialists only |",
        "| TD3 specialists only |",
        "MAPEX (PDERL specialists)",
        "Sample efficiency",
        "| MAPEX | MOPDERL |",
        "| interpolation (PDERL) |",
        "| interpolation (TD3) |",
    ):
        assert name in report, name
    assert re.search(r"MAPEX-TD3 (beat|lost to|tied with) interpolation \(TD3\)", report)
    if "morld" in baselines:
        assert "| MORL/D |" in report
    assert ran(run([str(BIN / "dvc"), "repro"], root)) == set()

    # an edit to MAPEX's code (pipeline/extraction/) leaves the specialists, the post-hoc
    # critics and the baselines up to date: only extraction and what reads its fronts rerun
    with open(root / "pipeline" / "extraction" / "mapex.py", "a") as fh:
        fh.write("\n# an edit\n")
    stale = stale_stages(root)
    assert {"mapex_td3", "mapex_posthoc_pderl", "warmup_only_td3", "posthoc_gentle"} <= stale, stale
    untouched = {
        "train_specialist",
        "train_pderl",
        "fit_critics",
        "mopderl",
        "morld",
        "critic_fidelity",
        "interpolate_td3",
    }
    assert not stale & untouched, stale

    # DVC params are exact: the specialists' run length and keep-best schedule are
    # train_specialist's alone (PDERL and MOPDERL read the td3 section), and the warm-up-only
    # ablation lists only the extract keys it reads, not the advantage-weighted ones
    run(["git", "checkout", "--", "pipeline/extraction/mapex.py"], root)
    assert stale_stages(root) == set()
    edited = {
        **params,
        "train_specialist": {**params["train_specialist"], "total_steps": 320, "keep_best_every": 100},
        "extract": {**params["extract"], "beta": 0.5},
    }
    save_params(root / "params.yaml", edited)
    stale = stale_stages(root)
    assert {"train_specialist", "mapex_td3", "mapex_pderl"} <= stale, stale
    assert not stale & {
        "train_pderl",
        "mopderl",
        "warmup_only_td3",
        "warmup_only_pderl",
        "morld",
        "interpolate_pderl",
    }, stale


def stale_stages(root) -> set[str]:
    """The stages `dvc status` calls changed (names without their matrix item)."""
    status = json.loads(
        subprocess.run(
            [str(BIN / "dvc"), "status", "--json"],
            cwd=root,
            capture_output=True,
            text=True,
            env={**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"},
        ).stdout
    )
    return {name.split("@")[0] for name in status}
