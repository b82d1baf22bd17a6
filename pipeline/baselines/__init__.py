"""The baselines: the paper's MOPDERL (phase 2) and MORL/D (morl-baselines), and weight-space interpolation (not in the paper)."""
