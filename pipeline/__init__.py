"""MAPEX core library: algorithms, math, params models and artifact formats.

Nothing in this package reads command-line arguments, prints, or knows a path that was not
handed to it; the `stages` package is the I/O shell around it.
"""
