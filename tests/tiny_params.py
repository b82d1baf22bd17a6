"""TINY: the whole pipeline's params at toy size (40-step episodes, 16-unit networks, 300-step
specialists, 2 children), shared by the tests that run real stage chains (DVC, sweeps, the
payoff scripts), so that they test one preset. Each test copies it before changing anything.
Their run lists are derived as `mapex sync-params` writes them (with_lists)."""

from pipeline.params.methods import derived_lists


def with_lists(params: dict) -> dict:
    """`params` with the run lists derived from its methods, seeds, imports and export methods."""
    imports = (params.get("import_specialists") or {}).get("policies", [])
    export = (params.get("export") or {}).get("methods", [])
    return {**params, **derived_lists(params["methods"], params["seeds"], imports, export)}


TINY = {
    "env": {
        "id": "mo-halfcheetah-v5",
        "max_episode_steps": 40,
        "reference_point": [-100.0, -4500.0],
        "objective_names": None,
    },
    "seeds": [0],
    "objectives": [0, 1],
    "methods": ["mapex_td3", "warmup_only_td3"],
    "td3": {"learning_starts": 200, "batch_size": 32, "hidden_sizes": [16, 16]},
    "train_specialist": {"total_steps": 300},
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
}
TINY = with_lists(TINY)

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
    **TINY,
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
    "td3": {**TINY["td3"], "buffer_size": 2000},
    "train_pderl": PDERL_TINY,
    "mopderl": MOPDERL_TINY,
    "morld": MORLD_TINY,
    "extract": {**TINY["extract"], "iterations": 1},
    "evaluate": {"episodes": 1},
}
TINY_ALL = with_lists(TINY_ALL)
