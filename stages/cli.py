"""The `mapex` command: one subcommand per DVC stage."""

from __future__ import annotations

import typer

from stages.extract import extract
from stages.critic_fidelity import critic_fidelity
from stages.fit_critics import fit_critics
from stages.train_specialist import train_specialist
from stages.evaluate import evaluate
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
    """
app.command("train-specialist")(train_specialist)
app.command("fit-critics")(fit_critics)
app.command("critic-fidelity")(critic_fidelity)
app.command("extract")(extract)
app.command("evaluate")(evaluate)
app.command("report")(report)


if __name__ == "__main__":
    app()
