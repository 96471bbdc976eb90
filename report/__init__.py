"""elastocal.report: presentation: the HTML report, the 3-D view, plots."""
