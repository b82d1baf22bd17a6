"""Command sync-params: write the run lists derived from `methods` and `seeds` into params.gen.yaml."""

from __future__ import annotations

from pathlib import Path

import typer

from pipeline.core.artifacts import write_text_atomic
from pipeline.evaluation.preflight import preflight
from pipeline.params import EnvParams, ParamsError, RunParams, load_params, section
from pipeline.params.sync import generated_path, generated_text, run_lists, synced_text
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
    """Write the lists dvc.yaml runs its producing stages over into PARAMS' generated file.

    You list what to run once, in `methods` (e.g. [mapex_td3, warmup_only_td3, mopderl]) with
    any named `variants`; DVC cannot filter a matrix, so the producing stages each need a list of
    their own (td3_seeds, extract_from, posthoc_from, extract_variant_runs, ...). This command
    writes them to the generated file beside PARAMS (params.yaml -> params.gen.yaml, loaded by
    dvc.yaml's `vars:`), removes an older generated block from PARAMS and fills in the extract
    keys a listed stage tracks; every other line of PARAMS stays as it is. With --from, PARAMS
    becomes a copy of that file first. Every stage checks the generated file and names this
    command when it is out of date.
    """
    source = preset or params
    if not source.is_file():
        raise ParamsError(f"{source}: params file not found")
    try:
        text = synced_text(source.read_text(), str(source))
    except ValueError as exc:
        raise ParamsError(str(exc)) from None
    write_text_atomic(params, text)
    gen = generated_path(params)
    gen.unlink(missing_ok=True)  # load_params must not check the old one against the new params
    write_text_atomic(gen, generated_text(run_lists(load_params(params)), params.name))
    loaded = load_params(params)
    section(loaded, "", RunParams, params)  # the result validates
    # the env: what a later stage would refuse for it, said now (pipeline/evaluation/preflight.py)
    preflight(section(loaded, "env", EnvParams, params), params)
    typer.echo(f"{gen}: run lists written from {params}'s methods", err=True)
