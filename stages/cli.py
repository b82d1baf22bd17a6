"""The `mapex` command: one subcommand per DVC stage."""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path

import torch
import typer

# Subcommand -> the stages module that defines it (function of the same name, dashes as
# underscores): every module of stages/ but these, found by name, so a new stage module is a new
# subcommand with no line here. A stage run (`mapex score ...`, as dvc.yaml calls it) imports
# only its own module: importing all of them (matplotlib, zarr, ...) cost about 0.3 s more per
# stage process (`mapex score --help`: 2.0 s vs 1.7 s), about 10 s over the quickstart's 28 stages.
NOT_COMMANDS = ("__init__", "cli", "common")
# --help lists the pipeline's stages in the order they run, then the rest alphabetically.
ORDER = ("train_specialist", "train_pderl", "import_specialist", "fit_critics", "critic_fidelity", "extract")
_modules = sorted(p.stem for p in Path(__file__).parent.glob("*.py") if p.stem not in NOT_COMMANDS)
COMMANDS = {
    m.replace("_", "-"): f"stages.{m}"
    for m in sorted(_modules, key=lambda m: (ORDER.index(m) if m in ORDER else len(ORDER), m))
}

app = typer.Typer(
    help="MAPEX: extract Pareto fronts of continuous-control policies from single-objective specialists.\n\n"
    "Each subcommand is one DVC stage (see dvc.yaml); hyperparameters come from params.yaml.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)


@app.callback()
def main() -> None:
    """MAPEX: extract Pareto fronts of continuous-control policies from single-objective specialists.

    Each subcommand is one DVC stage (see dvc.yaml); hyperparameters come from params.yaml.
    Torch uses MAPEX_TORCH_THREADS CPU threads (default 1; see docs/manual.md, "Threads").
    """
    # One thread by default: at the quickstart's 64-unit widths a second thread only adds
    # synchronisation (measured 6x slower on a busy 2-core machine), and a fixed count keeps
    # CPU results bitwise reproducible across machines with different core counts.
    torch.set_num_threads(int(os.environ.get("MAPEX_TORCH_THREADS", "1")))


def _register(names) -> None:
    for name in names:
        module = importlib.import_module(COMMANDS[name])
        app.command(name)(getattr(module, name.replace("-", "_")))


# Only the subcommand being run when argv names one; every subcommand otherwise (--help, a
# typo that typer should answer with the list, or the app imported by tests).
_argv_cmd = (
    sys.argv[1] if len(sys.argv) > 1 and sys.argv[1] in COMMANDS and sys.argv[0].endswith(("mapex", "cli.py")) else None
)
_register([_argv_cmd] if _argv_cmd else list(COMMANDS))


if __name__ == "__main__":
    app()
