"""The paper's baselines: MOPDERL (phase 2) and MORL/D (morl-baselines)."""
