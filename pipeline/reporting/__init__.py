"""The report: tables, verdicts and figures from scored runs."""
