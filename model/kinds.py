"""The kinds and modes of the model and its fits, as Enums.

Every kind or mode that code branches on is one of these, never a free string.
They are ``str`` Enums: a member equals its value (``TorqueSource.CURRENT ==
"current"``) and ``json.dumps`` writes the value, so files and ``--json`` objects
keep their text (docs/formats.md, docs/cli.md) while the code names the member.
Parse a user's text with the Enum itself (``TorqueSource(text)``) at the edge.
"""

from __future__ import annotations

from enum import Enum
from typing import TypeVar

K = TypeVar("K", bound=Enum)


def expect(kind: type[K], value: object, name: str) -> K:
    """``value`` if it is a member of ``kind``, else a TypeError naming ``name``.

    A str Enum's member equals its text, so a plain ``"force"`` would pass every comparison
    below the edge and slip into a typed record unnoticed; the records and the fits' entry
    points call this so that text is parsed once, where it is read (``kind(text)``)."""
    if isinstance(value, kind):
        return value
    raise TypeError(f"{name} must be a {kind.__name__} (parse text with {kind.__name__}(text)), got {value!r}")


class JointKind(str, Enum):
    """How an actuated joint moves: ``q``, limits and offset in rad (revolute) or m (prismatic)."""

    REVOLUTE = "revolute"
    PRISMATIC = "prismatic"

    def __str__(self) -> str:
        return self.value

    @property
    def unit(self) -> str:
        """Unit of the joint coordinate."""
        return "rad" if self is JointKind.REVOLUTE else "m"

    @property
    def effort_unit(self) -> str:
        """Unit of the joint's effort (torque or force)."""
        return "N*m" if self is JointKind.REVOLUTE else "N"

    @property
    def stiffness_unit(self) -> str:
        """Unit of the joint's stiffness (effort per unit of the coordinate)."""
        return "N*m/rad" if self is JointKind.REVOLUTE else "N/m"


class TorqueSource(str, Enum):
    """Where the joint torques of a static fit come from (docs/cli.md ``--torque``)."""

    CURRENT = "current"      # motor currents: tau = xi i
    FORCE = "force"          # the wrench columns through J^T W (and the model's gravity)

    def __str__(self) -> str:
        return self.value


class KinematicForm(str, Enum):
    """How deflections are mapped to positions (docs/cli.md ``--form``)."""

    EXACT = "exact"              # kinematics at the deflected configurations
    FIRST_ORDER = "first-order"  # dP = J(q) C Gamma, as in the papers

    def __str__(self) -> str:
        return self.value


class Weighting(str, Enum):
    """How a static fit weights its residuals."""

    GLS = "gls"      # by the noise covariance of the readings (repeats, currents)
    OLS = "ols"      # every component alike

    def __str__(self) -> str:
        return self.value


class CompensatorKind(str, Enum):
    """The gravity compensator's force law (docs/physics.md)."""

    HYDROPNEUMATIC = "hydropneumatic"   # Yang: F = C / (l_c - l)
    SPRING = "spring"                   # Klimchik: a spring of stiffness K_c, free length s0

    def __str__(self) -> str:
        return self.value


class NoiseSource(str, Enum):
    """Where a static table's tracker noise level comes from, in the order the contract takes
    them (docs/cli.md, "Absolute-only tables"): repeated readings, else the readings' own
    ``u95`` or ``sx, sy, sz`` columns, else a tracker noise law named in cell.toml or
    robot.toml, else none (no floor: the verdict says so)."""

    REPEATS = "repeats"
    UNCERTAINTY_COLUMNS = "uncertainty_columns"
    TRACKER_LAW = "tracker_law"
    NONE = "none"

    def __str__(self) -> str:
        return self.value
