"""elastocal subpackage."""
