"""The shared core: artifact formats and atomic writes, envs, networks, replay buffers, seeding, provenance, resume."""
