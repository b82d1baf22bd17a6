"""Helpers shared by the stage commands: error reporting, params loading, progress bars."""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import Any, Callable, TypeVar

import typer
from pydantic import BaseModel
from tqdm import tqdm

from pipeline.core.artifacts import ArtifactError
from pipeline.core.envs import EnvError
from pipeline.params import EnvParams, ParamsError, RunParams, load_params, section

F = TypeVar("F", bound=Callable[..., Any])
M = TypeVar("M", bound=BaseModel)

PARAMS_OPTION = typer.Option(Path("params.yaml"), "--params", help="params file (validated before anything is read or written)")


# The pipeline's input errors: one readable line and exit code 2, in a stage or in its workers.
INPUT_ERRORS = (ParamsError, ArtifactError, EnvError)


def worker_failed(exc, where: str) -> typer.Exit:
    """Report a stage worker's failure (pipeline.core.workers.WorkerError) as the stage would
    its own: an input error as one line and exit code 2, anything else with the worker's
    traceback and exit code 1. Returns the Exit to raise."""
    if exc.detail:
        typer.echo(exc.detail.rstrip(), err=True)
    typer.echo(f"error: {where}: {exc}", err=True)
    return typer.Exit(code=2 if exc.expected else 1)


def reports_errors(fn: F) -> F:
    """Turn the pipeline's input errors into one readable line on stderr and exit code 2."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except INPUT_ERRORS as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(code=2) from None

    return wrapper  # type: ignore[return-value]


def read_params(path: Path, name: str, model: type[M]) -> tuple[dict[str, Any], EnvParams, M]:
    """Load params.yaml and validate the `env` section, the top-level lists (RunParams: they must
    agree with each other) and stage section `name`."""
    raw = load_params(path)
    section(raw, "", RunParams, path)
    return raw, section(raw, "env", EnvParams, path), section(raw, name, model, path)


def progress(total: int, desc: str, unit: str = "step") -> tqdm:
    """A progress bar on stderr (rate in unit/s); quiet when stderr is not a terminal and CI is set."""
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True, mininterval=0.5)


def fmt_vec(v) -> str:
    return "[" + ", ".join(f"{x:.1f}" for x in v) + "]"
