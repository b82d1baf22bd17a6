"""The I/O shell: one typer command per DVC stage (stage name = module = params section)."""
