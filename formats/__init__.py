"""elastocal.formats: the bottom layer's file formats: tables, calibration JSON, the MCAP log schema, plan files, reading a user's text file."""
