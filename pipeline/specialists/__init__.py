"""Specialists: TD3 with secondary critics (stacked training) and PDERL."""
