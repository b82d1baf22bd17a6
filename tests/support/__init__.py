"""Helpers of the test suite, imported by the tests as `support.<module>` (tests/ is on sys.path
under pytest): not test files themselves, so pytest collects nothing here.

- `tiny_params`: the toy params presets the tests run.
- `dvc_repo`: a temporary git + DVC copy of the repository, and running commands in it.
- `reference_child`: a frozen copy of the pre-batching MAPEX child, the K = 1 reference.
"""
