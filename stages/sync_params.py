"""Command sync-params: write the run lists derived from `methods` and `seeds` into params.yaml."""

from __future__ import annotations

from pathlib import Path

import typer

from pipeline.core.artifacts import write_text_atomic
from pipeline.params import ParamsError, RunParams, load_params, section
from pipeline.params.sync import synced_text
from stages.common import PARAMS_OPTION, reports_errors


@reports_errors
def sync_params(
    preset: Path = typer.Option(
        None,
        "--from",
        help="start from this params file (e.g. presets/paper/mo-walker2d-v5.yaml); default: PARAMS itself",
    ),
    params: Path = PARAMS_OPTION,
) -> None:
    """Write the lists dvc.yaml runs its producing stages over, derived from `methods` and `seeds`.

    You list what to run once, in `methods` (e.g. [mapex_td3, warmup_only_td3, mopderl]); DVC
    cannot filter a matrix, so train_pderl, extract, fit_critics, mopderl and morld each need a
    list of their own (pderl_seeds, extract_from, extract_variants, posthoc_from,
    mopderl_seeds, morld_seeds). This command rewrites them in the generated block of PARAMS
    and leaves every other line as it is. With --from, PARAMS becomes a copy of that file first.
    Every stage checks the lists and names this command when they are out of date.
    """
    source = preset or params
    if not source.is_file():
        raise ParamsError(f"{source}: params file not found")
    try:
        text = synced_text(source.read_text(), str(source))
    except ValueError as exc:
        raise ParamsError(str(exc)) from None
    write_text_atomic(params, text)
    section(load_params(params), "", RunParams, params)  # the result validates
    typer.echo(f"{params}: run lists synced from methods", err=True)
