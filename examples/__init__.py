"""Examples that are importable (examples.pointrunner: a small env of the project's own)."""
