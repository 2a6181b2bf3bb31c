"""Reports: metrics against truth, plots and the summary."""
