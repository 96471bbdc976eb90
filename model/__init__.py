"""elastocal.model: the bottom layer's robot model (robot.toml / URDF -> Pinocchio), the effects' physics and words, units."""
