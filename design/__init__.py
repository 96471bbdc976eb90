"""elastocal.design: experiment design (poses and loads for precision, the plan pipeline)."""
