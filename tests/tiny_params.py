"""TINY: the whole pipeline's params at toy size (40-step episodes, 16-unit networks, 300-step
specialists, 2 children), shared by the tests that run real stage chains (DVC, sweeps, the
payoff scripts), so that they test one preset. Each test copies it before changing anything."""

TINY = {
    "env": {"id": "mo-halfcheetah-v5", "max_episode_steps": 40, "reference_point": [-100.0, -4500.0], "objective_names": None},
    "seeds": [0],
    "objectives": [0, 1],
    "pderl_seeds": [],
    "extract_from": ["td3"],
    "extract_variants": ["mapex", "warmup_only"],
    "posthoc_from": [],
    "mopderl_seeds": [],
    "morld_seeds": [],
    "methods": ["mapex_td3", "warmup_only_td3"],
    "train_specialist": {"total_steps": 300, "learning_starts": 200, "batch_size": 32, "hidden_sizes": [16, 16]},
    "fit_critics": {"steps": 20, "batch_size": 32, "hidden_sizes": [16, 16]},
    "critic_fidelity": {"episodes": 2},
    "extract": {
        "iterations": 2, "child_buffer_size": 200, "eval_episodes": 2, "warmup_steps": 10, "warmup_batch_size": 32,
        "epochs": 1, "beta": 1.0, "omega_max": 1.0, "batch_size": 32, "hidden_sizes": [16, 16],
    },
    "evaluate": {"episodes": 2},
    "score": {"distinct_tol": 0.02},
    "report": {"dpi": 60},
}
