"""Helpers shared by the stage commands: error reporting, params loading, progress bars."""

from __future__ import annotations

import functools
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Generic, Iterator, NamedTuple, TypeVar

import torch
import typer
from pydantic import BaseModel
from tqdm import tqdm

from pipeline.core.artifacts import ArtifactError, disk_full_error
from pipeline.core.drive import fmt_vec  # noqa: F401  (re-exported: the stages' progress lines)
from pipeline.core.envs import EnvError
from pipeline.core.finite import TrainingDiverged
from pipeline.core.signals import EXIT_CODE as STOPPED_EXIT_CODE
from pipeline.core.signals import Stopped
from pipeline.core.workers import WorkerError, oversubscribed, run_side_by_side
from pipeline.params import EnvParams, ParamsError, RunParams, load_params, section
from pipeline.params.variants import Variant, parse_variants, with_overrides

F = TypeVar("F", bound=Callable[..., Any])
M = TypeVar("M", bound=BaseModel)

PARAMS_OPTION = typer.Option(
    Path("params.yaml"), "--params", help="params file (validated before anything is read or written)"
)
# Where a stage writes what produced its run (pipeline.core.provenance), outside its outputs:
# dvc.yaml passes data/provenance/<the out's path under data/>.json, an out of its own.
PROVENANCE_OPTION = typer.Option(
    None,
    "--provenance",
    help="JSON file to write what produced this run to (git commit, library versions, device, threads), "
    "kept out of the outputs so that they depend on inputs and params alone (default: none written)",
)


# The pipeline's input errors: one readable line and exit code 2, in a stage or in its workers.
INPUT_ERRORS = (ParamsError, ArtifactError, EnvError)
# Training that diverged (a NaN or infinity in a loss or weight, pipeline.core.finite): one line
# naming the stage, seed, objective, step and what went bad, and this exit code, distinct from
# bad input's 2 and a crash's 1. No artifact is written; the last good checkpoint stays.
DIVERGED_EXIT = 3


class Relay:
    """Shows on a stage's progress bar and stderr what its parts report (`send`):
    ("steps", n), ("returns", text: the part's latest, in the bar's postfix) and ("say", line)."""

    def __init__(self, bar: tqdm, prefix: str = "return ", on_result: Callable[[int, Any], None] | None = None) -> None:
        self.bar, self.prefix, self.returns, self.on_result = bar, prefix, {}, on_result

    def message(self, kind: str, value: Any, part: int = 0) -> None:
        if kind == "result" and self.on_result is not None:  # a part's result: to the stage
            self.on_result(part, value)
        elif kind == "steps":
            self.bar.update(value)
        elif kind == "returns":
            self.returns[part] = value
            self.bar.set_postfix_str(self.prefix + "; ".join(v for _, v in sorted(self.returns.items())), refresh=False)
        else:
            self.bar.write(value, file=sys.stderr)


def run_parts(
    fn: Callable[..., None],
    parts: list[tuple],
    bar: tqdm,
    where: Callable[[int], str],
    prefix: str = "return ",
    on_result: Callable[[int, Any], None] | None = None,
    start: str = "spawn",
) -> None:
    """Run fn(*parts[i], threads, send=...) for every part: here when there is one, else each in
    its own worker process at once (pipeline.core.workers; `start`: how they start), with this
    process's torch thread count. Progress goes to `bar` (Relay); what a part sends as
    ("result", value) goes to on_result(part, value). A worker's failure is reported as the stage would
    its own: an input error as one line and exit code 2, a TrainingDiverged as its own line
    (it names the stage, seed and objective) and exit code 3, anything else with the worker's
    traceback and exit code 1; `where(i)` names part i in the input error's line."""
    relay = Relay(bar, prefix, on_result)
    threads = torch.get_num_threads()
    if len(parts) == 1:
        fn(*parts[0], threads, send=relay.message)
        return
    warning = oversubscribed(len(parts), threads)
    if warning:
        bar.write(warning, file=sys.stderr)
    try:
        run_side_by_side(
            fn,
            [(*args, threads) for args in parts],
            lambda i, message: relay.message(*message, part=i),
            (*INPUT_ERRORS, TrainingDiverged),
            start=start,
        )
    except WorkerError as exc:
        if exc.kind is not None and issubclass(exc.kind, TrainingDiverged):
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(code=DIVERGED_EXIT) from None
        if exc.detail:
            typer.echo(exc.detail.rstrip(), err=True)
        typer.echo(f"error: {where(exc.part)}: {exc}", err=True)
        raise typer.Exit(code=2 if exc.expected else 1) from None


def reports_errors(fn: F) -> F:
    """Turn the pipeline's input errors (and a full disk: ArtifactError's DiskFull, or an
    OSError of one raised outside the atomic writers) into one readable line on stderr and
    exit code 2; training that diverged into its one line (named after the stage, unless it
    names one) and exit code DIVERGED_EXIT (3); a run stopped by SIGTERM at a safe point
    (pipeline.core.signals) into its line(s) and exit code 143."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except INPUT_ERRORS as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(code=2) from None
        except TrainingDiverged as exc:
            if exc.stage is None:
                exc.within(fn.__name__)
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(code=DIVERGED_EXIT) from None
        except Stopped as exc:
            typer.echo(str(exc), err=True)
            raise typer.Exit(code=STOPPED_EXIT_CODE) from None
        except Exception as exc:
            full = disk_full_error(exc)
            if full is None:
                raise
            typer.echo(f"error: the disk is full or a quota or file-size limit was reached: {full}", err=True)
            raise typer.Exit(code=2) from None

    return wrapper  # type: ignore[return-value]


class StageParams(NamedTuple, Generic[M]):
    """What `read_params` hands a stage: the loaded params (a variant's overrides merged in), and
    the validated `env` section, stage section and top-level lists."""

    raw: dict[str, Any]
    env: EnvParams
    cfg: M
    run: RunParams


def read_params(path: Path, name: str, model: type[M], variant: str | None = None) -> StageParams[M]:
    """Load params.yaml and validate the `env` section, the top-level lists (RunParams: they must
    agree with each other) and stage section `name`, each once. With `variant` (a name in params'
    `variants`), the params are the file's with that variant's overrides merged in
    (pipeline.params.variants.with_overrides): every section read from them is the variant's."""
    raw = load_params(path)
    run = section(raw, "", RunParams, path)
    if variant is not None:
        raw = with_overrides(raw, named_variant(raw, variant, path))
        path = Path(f"{path} (with the overrides of variants.{variant})")
    return StageParams(raw, section(raw, "env", EnvParams, path), section(raw, name, model, path), run)


def method_option(base: str, sections: str) -> Any:
    """The --method option of a stage that makes fronts of method `base` (a name or a pattern
    such as 'interpolate_KIND'): run as a named variant of it, whose overrides of `sections` apply."""
    return typer.Option(
        None,
        "--method",
        help=f"run as this named variant of method {base} (params `variants`: its overrides of {sections} "
        f"apply, and the front is this method's); default: method {base} itself",
    )


def require_variant_of(raw: dict[str, Any], method: str | None, base: str, path: Path) -> str:
    """The method a run makes: `base`, or `method` where given, which must be a named variant of
    `base` (a one-line ParamsError otherwise)."""
    if method is None:
        return base
    of = named_variant(raw, method, path).of
    if of != base:
        raise ParamsError(f"--method {method}: variants.{method}.of is {of!r}, but this run is {base!r}")
    return method


def named_variant(raw: dict[str, Any], name: str, path: Path) -> Variant:
    """Variant `name` of the loaded params' `variants`; a one-line ParamsError if there is none."""
    try:
        found = parse_variants(raw.get("variants")).get(name)
    except ValueError as exc:
        raise ParamsError(f"{path}: {exc}") from None
    if found is None:
        raise ParamsError(f"{path}: variants has no entry {name!r} (names: {sorted(raw.get('variants') or {})})")
    return found


def require_every_objective(objectives: list[int], n_objectives: int, env_id: str, params: Path, who: str) -> None:
    """`objectives` of params.yaml must be every objective of the env: `who` needs one specialist each."""
    if sorted(objectives) != list(range(n_objectives)):
        raise ParamsError(
            f"{params}: objectives = {objectives}: {who} needs one specialist per objective 0..{n_objectives - 1} of {env_id}"
        )


def check_min_return(min_return: list[float | None] | None, n_objectives: int, params: Path) -> None:
    """report.weak_specialist_min_return, where set, has one entry per objective of the runs."""
    if min_return is not None and len(min_return) != n_objectives:
        raise ParamsError(
            f"{params}: report.weak_specialist_min_return = {min_return}: needs one entry per objective "
            f"({n_objectives}; null = unused)"
        )


def progress(total: int, desc: str, unit: str = "step") -> tqdm:
    """A progress bar on stderr (rate in unit/s); quiet when stderr is not a terminal and CI is set."""
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True, mininterval=0.5)


@contextmanager
def progress_send(total: int, desc: str, unit: str = "step") -> Iterator[Callable[[str, Any], None]]:
    """A progress bar (`progress`) as the `send` of pipeline.core.drive.drive (Relay's channel);
    its total grows to the units counted when a run overshoots its budget (a last generation
    that runs to its end)."""
    with progress(total, desc, unit) as bar:
        yield Relay(bar, prefix="").message
        bar.total = max(bar.total, bar.n)
