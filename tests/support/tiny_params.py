"""The tests' one toy preset, TINY, and the variants the tests build from it by overrides.

- `TINY`: params small enough that a specialist trains in a few seconds (the `write_params` and
  `tiny_params` fixtures of tests/conftest.py write it, with a test's overrides merged in).
- `merge(base, overrides)`: a deep copy of `base` with `overrides` merged in, section by section
  (`DELETE` as a value removes that key).
- `TINY_CHAIN`: TINY with the overrides of the tests that run real stage chains (DVC, sweeps, the
  payoff scripts, `dvc repro` from imported specialists): every stage's section at toy size
  (40-step episodes, 16-unit networks, 300-step specialists, 2 children) and the run lists
  derived (`with_lists`: what `mapex plan` plans from).
- `PDERL_TINY`, `MOPDERL_TINY`, `MORLD_TINY`: those methods' sections at toy size, and `TINY_ALL`:
  TINY_CHAIN with every method of the pipeline at once.

Each test copies a preset (merge, or a dict literal) before changing anything.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import yaml

from pipeline.params.common import DERIVED_KEYS
from pipeline.params.extract import WARMUP_ONLY_KEYS, ExtractParams
from pipeline.params.interpolate import INTERPOLATE_EXTRACT_KEYS
from pipeline.params.planned import with_tracked_env, without_derived
from pipeline.params.runlists import derived_lists
from pipeline.params.td3 import AGENT_KEYS, TD3Params

# HalfCheetah never terminates, so with a 100-step cap every episode is cut by the cap: 350 steps
# = 3 truncated episodes + 1 still running. Updates start at step 260 (90 updates, 45 actor
# updates), so a run takes a few seconds.
TINY: dict[str, Any] = {
    "env": {"id": "mo-halfcheetah-v5", "max_episode_steps": 100},
    "seeds": [0],
    "objectives": [0, 1],
    "td3": {
        "learning_starts": 260,
        "buffer_size": 1000,
        "batch_size": 64,
        "hidden_sizes": [32, 32],
        "secondary_critics": True,
    },
    "train_specialist": {"total_steps": 350, "device": "cpu"},
}

DELETE = object()  # an override value that removes the key from the preset


def merge(base: dict[str, Any], overrides: dict[str, Any] | None) -> dict[str, Any]:
    """A deep copy of `base` with `overrides` merged in, section by section (DELETE removes a key)."""
    out = copy.deepcopy(base)
    for key, value in (overrides or {}).items():
        if value is DELETE:
            out.pop(key, None)
        elif isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def with_lists(params: dict) -> dict:
    """`params` with the run lists derived from its methods, seeds, imports and export methods,
    a render section where none, the extract keys stages warmup_only and interpolate track at their defaults where
    missing and an interpolate section where one is needed (as `mapex plan` fills them in: DVC refuses a listed
    param that is not in the file)."""
    imports = (params.get("import_specialists") or {}).get("policies", [])
    export = (params.get("export") or {}).get("methods", [])
    objectives = params.get("objectives", [0, 1])
    lists = derived_lists(params["methods"], params["seeds"], imports, export, objectives, params.get("variants"))
    out = {**params, **lists}
    out.setdefault("render", {"methods": []})  # stage render tracks the section (no clips unless asked)
    templates = {run["stage"] for run in out["method_runs"]}
    tracked = (WARMUP_ONLY_KEYS if "warmup_only" in templates else ()) + (
        INTERPOLATE_EXTRACT_KEYS if "interpolate" in templates else ()
    )
    if tracked:
        fields = ExtractParams.model_fields
        out["extract"] = {k: fields[k].default for k in tracked} | (params.get("extract") or {})
    if "interpolate" in templates:
        out.setdefault("interpolate", {"policies": None, "eval_episodes": None})
    if out["pderl_seeds"]:  # stages train_pderl and mopderl list the td3 keys their agents read
        fields = TD3Params.model_fields
        out["td3"] = {k: fields[k].default for k in AGENT_KEYS} | (params.get("td3") or {})
    return out


# A chain runs every stage on two specialists, so its episodes and networks are smaller still.
# Its specialists keep the library's defaults for the replay capacity, secondary critics and
# device (TINY pins them), as these tests always have.
TINY_CHAIN = merge(
    TINY,
    {
        "env": {
            "max_episode_steps": 40,
            "reference_point": [-100.0, -4500.0],
            "objective_names": None,
        },
        "methods": ["mapex_td3", "warmup_only_td3"],
        "td3": {
            "learning_starts": 200,
            "buffer_size": DELETE,
            "batch_size": 32,
            "hidden_sizes": [16, 16],
            "secondary_critics": DELETE,
        },
        "train_specialist": {"total_steps": 300, "device": DELETE},
        "fit_critics": {"steps": 20, "batch_size": 32, "hidden_sizes": [16, 16]},
        "critic_fidelity": {"episodes": 2},
        "extract": {
            "iterations": 2,
            "child_buffer_size": 200,
            "eval_episodes": 2,
            "warmup_steps": 10,
            "warmup_batch_size": 32,
            "epochs": 1,
            "beta": 1.0,
            "omega_max": 1.0,
            "batch_size": 32,
            "hidden_sizes": [16, 16],
        },
        "evaluate": {"episodes": 2},
        "score": {"distinct_tol": 0.02},
        "report": {"dpi": 60},
    },
)
TINY_CHAIN = with_lists(TINY_CHAIN)

# The tiny sizes of the PDERL specialists and the two baselines, and TINY_ALL: every method of
# the pipeline at once (TD3 and PDERL specialists, post-hoc critics from both, MOPDERL, MORL/D),
# used by the one-chain test and by benchmarks/tiny_repro.sh (artifacts before/after a refactor).
PDERL_TINY = {
    "total_frames": 240,
    "population_size": 3,
    "mini_buffer_size": 200,
    "crossover_transitions": 64,
    "crossover_batch_size": 32,
    "crossover_epochs": 2,
    "mutation_states": 32,
    "device": "cpu",
}
MOPDERL_TINY = {
    "total_frames": 400,
    "population_size": 4,
    "children": 3,
    "eval_episodes": 1,
    "mini_buffer_size": 200,
    "crossover_transitions": 64,
    "crossover_batch_size": 32,
    "crossover_epochs": 2,
    "mutation_states": 32,
    "rl_updates_per_frame": 0.1,
    "device": "cpu",
}
MORLD_TINY = {
    "total_frames": 160,
    "exchange_every": 80,
    "pop_size": 2,
    "hidden_sizes": [16, 16],
    "batch_size": 32,
    "learning_starts": 40,
    "buffer_size": 1000,
    "update_passes": 1,
    "front_eval_episodes": 1,
    "eval_episodes": 1,
    "device": "cpu",
}
TINY_ALL = {
    **TINY_CHAIN,
    "methods": [
        "mapex_td3",
        "warmup_only_td3",
        "mapex_pderl",
        "warmup_only_pderl",
        "mapex_posthoc_td3",
        "mapex_posthoc_pderl",
        "mopderl",
        "morld",
    ],
    "td3": {**TINY_CHAIN["td3"], "buffer_size": 2000},
    "train_pderl": PDERL_TINY,
    "mopderl": MOPDERL_TINY,
    "morld": MORLD_TINY,
    "extract": {**TINY_CHAIN["extract"], "iterations": 1},
    "evaluate": {"episodes": 1},
}
TINY_ALL = with_lists(TINY_ALL)


def save_params(path: Path, params: dict[str, Any], **dump: Any) -> Path:
    """Write `params` at `path` as the tests' params file. A dict of `with_lists` (it carries the
    derived run lists) is written as `mapex plan` leaves a repository: without the lists (derived
    again wherever the file is read or planned) and with env.reward_terms present (every planned
    stage tracks it); any other dict as it is."""
    if any(k in params for k in DERIVED_KEYS):
        params = with_tracked_env(without_derived(params))
    path.write_text(yaml.safe_dump(params, **dump))
    return path


# Params that plan every stage of the catalogue (pipeline/params/stage_catalogue.yaml): TINY_ALL's
# methods, the interpolation baseline, a specialists variant, method variants of MAPEX, of the
# interpolation (one with a label), of MAPEX-PostHoc and of MORL/D, two imported objectives (one collects its buffer, one brings
# it; the third objective is trained here) and an export. For the plan only: nothing runs them.
EVERY_STAGE = with_lists(
    merge(
        TINY_ALL,
        {
            "objectives": [0, 1, 2],
            "methods": [
                *TINY_ALL["methods"],
                "interpolate_td3",
                "mapex_posthoc_imported",
                "mapex_td3_wide",
                "interpolate_td3_halfway",
                "mapex_posthoc_td3_gentle",
                "morld_small",
            ],
            "variants": {
                "td3_wide": {"of": "td3", "td3": {"hidden_sizes": [24, 24]}},
                "mapex_td3_wide": {"of": "mapex_td3", "specialists": "td3_wide"},
                "interpolate_td3_halfway": {
                    "of": "interpolate_td3",
                    "label": "halfway",
                    "interpolate": {"policies": 3},
                },
                # variants of the bases that had no variant stage before the plan wrote one per method
                "mapex_posthoc_td3_gentle": {"of": "mapex_posthoc_td3", "extract": {"beta": 0.5}},
                "morld_small": {"of": "morld", "label": "MORL/D, 2 agents", "morld": {"pop_size": 2}},
            },
            "import_specialists": {
                "policies": [
                    {"objective": 0, "file": "models/obj0.zip", "format": "sb3"},
                    {"objective": 1, "file": "models/obj1.zip", "format": "sb3", "buffer": "models/obj1.zarr"},
                ]
            },
            "export": {"methods": ["mapex_td3"]},
        },
    )
)
