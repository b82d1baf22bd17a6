"""Evaluation episodes and front metrics, the same for every method."""
