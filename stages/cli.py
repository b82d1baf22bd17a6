"""The `mapex` command: one subcommand per DVC stage."""

from __future__ import annotations

import os

import torch
import typer

from stages.extract import extract
from stages.critic_fidelity import critic_fidelity
from stages.fit_critics import fit_critics
from stages.train_specialist import train_specialist
from stages.train_pderl import train_pderl
from stages.evaluate import evaluate
from stages.score import score
from stages.morld import morld
from stages.mopderl import mopderl
from stages.sweep import sweep
from stages.grid_report import grid_report
from stages.report import report

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
    Torch uses MAPEX_TORCH_THREADS CPU threads (default 1; see README, "Threads").
    """
    # One thread by default: at the quickstart's 64-unit widths a second thread only adds
    # synchronisation (measured 6x slower on a busy 2-core machine), and a fixed count keeps
    # CPU results bitwise reproducible across machines with different core counts.
    torch.set_num_threads(int(os.environ.get("MAPEX_TORCH_THREADS", "1")))
app.command("train-specialist")(train_specialist)
app.command("train-pderl")(train_pderl)
app.command("fit-critics")(fit_critics)
app.command("critic-fidelity")(critic_fidelity)
app.command("extract")(extract)
app.command("evaluate")(evaluate)
app.command("score")(score)
app.command("report")(report)
app.command("mopderl")(mopderl)
app.command("morld")(morld)
app.command("sweep")(sweep)
app.command("grid-report")(grid_report)


if __name__ == "__main__":
    app()
