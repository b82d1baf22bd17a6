"""Sweeps beyond one machine: stage items as Ray tasks, a shared DVC remote."""
