"""The report: tables, verdicts and figures from scored runs (runs, tables, verdicts, figures,
report.md in report, the sweep grid's report in grid)."""
