"""MAPEX extraction (Algorithm 1): gap identification, hybrid buffers, mixed-advantage regression."""
