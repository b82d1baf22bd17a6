"""Command plan: write dvc.yaml whole from params.yaml's methods, variants, seeds and objectives."""

from __future__ import annotations

from pathlib import Path

import typer

from pipeline.core.artifacts import write_text_atomic
from pipeline.evaluation.preflight import preflight
from pipeline.params import EnvParams, ParamsError, RunParams, load_params, section
from pipeline.params.plan import stage_blocks, write_plan
from pipeline.params.tracked import tidied_text
from stages.common import PARAMS_OPTION, reports_errors


@reports_errors
def plan(
    preset: Path = typer.Option(
        None,
        "--from",
        help="start from this params file (e.g. presets/paper/mo-walker2d-v5.yaml); default: PARAMS itself",
    ),
    params: Path = PARAMS_OPTION,
) -> None:
    """Plan the pipeline: write dvc.yaml (beside PARAMS) with the stages PARAMS runs.

    You list what to run once, in `methods` (e.g. [mapex_td3, warmup_only_td3, mopderl]) with
    any named `variants`, `seeds` and `objectives`. DVC cannot filter a matrix, so this command
    writes dvc.yaml whole from the stage catalogue (pipeline/params/stage_catalogue.yaml): only
    the stages that run, each matrix written out, each stage's code deps listed. It also removes
    derived lists or an older generated block from PARAMS and fills in the keys a planned stage
    tracks; every other line of PARAMS stays as it is. With --from, PARAMS becomes a copy of that
    file first. Every stage checks the plan against PARAMS and names this command when it is
    out of date; then `dvc repro` runs it.
    """
    source = preset or params
    if not source.is_file():
        raise ParamsError(f"{source}: params file not found")
    try:
        text = tidied_text(source.read_text(), str(source))
    except ValueError as exc:
        raise ParamsError(str(exc)) from None
    write_text_atomic(params, text)
    loaded = load_params(params, check_plan=False)  # the plan being replaced is not checked
    section(loaded, "", RunParams, params)  # the params validate before a plan is written
    # the env: what a later stage would refuse for it, said now (pipeline/evaluation/preflight.py)
    preflight(section(loaded, "env", EnvParams, params), params)
    try:
        out = write_plan(loaded, params)
    except ValueError as exc:
        raise ParamsError(f"{params}: {exc}") from None
    _, stages, _ = stage_blocks(out.read_text())
    typer.echo(f"{out}: planned {len(stages)} stages from {params}: {', '.join(n for n, _ in stages)}", err=True)
