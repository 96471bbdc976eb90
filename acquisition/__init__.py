"""elastocal.acquisition: guided calibration procedures, the MCAP recorder, export.

* :mod:`~elastocal.formats.plan`: plan.toml (docs/plan-format.md);
* :mod:`~elastocal.acquisition.procedures`: steps, settle detection, ``run_calibration``;
* :mod:`~elastocal.acquisition.cellio`: what a procedure needs from a cell, and the
  virtual cell; :mod:`~elastocal.acquisition.drivercell`: the cell through elastocal.drivers;
* :mod:`~elastocal.acquisition.ui`: progress and prompts in the terminal;
* :mod:`~elastocal.acquisition.recorder`, :mod:`~elastocal.formats.logformat`: the
  MCAP log (docs/log-format.md); :mod:`~elastocal.acquisition.export`: log -> tables.
"""
