"""The `mapex` command: one subcommand per DVC stage."""

from __future__ import annotations

import typer

from stages.train_specialist import train_specialist

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


if __name__ == "__main__":
    app()
