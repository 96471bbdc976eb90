"""Online compensation: stream corrections to the robot controller while the process force changes (docs/stream.md)."""
