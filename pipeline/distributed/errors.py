"""The sweep's exceptions, shared by its modules: GridError (a bad grid file or cell params),
SweepError (a sweep that cannot start or did not complete, with its exit code) and StageFailed
(a stage item's command failed on a worker; pickled across Ray processes)."""

from __future__ import annotations

from pipeline.params import ParamsError


class GridError(ParamsError):
    """The grid file is missing, unreadable or invalid; the message names the file and the key."""


class SweepError(RuntimeError):
    """A sweep cannot start or did not complete; `exit_code` 2 for bad input, 1 for failed stages."""

    def __init__(self, message: str, exit_code: int = 2):
        super().__init__(message)
        self.exit_code = exit_code


class StageFailed(RuntimeError):
    """A stage item's command failed on a worker (not retried: the same input fails again)."""

    def __init__(self, cell: str, item: str, message: str):
        super().__init__(f"{cell}: {item}: {message}")
        self.cell, self.item, self.detail = cell, item, message

    def __reduce__(self):  # pickled across Ray processes with its fields
        return (StageFailed, (self.cell, self.item, self.detail))
