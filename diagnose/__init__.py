"""elastocal.diagnose: stepwise diagnosis of missing effects, where the model fails, the calibration check."""
