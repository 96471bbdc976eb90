"""The gravity compensator of a robot description: its geometry and force law.

Two kinds (docs/physics.md): Yang's hydro-pneumatic cylinder (geometry ``a, b, h``
[m], parameters ``C`` [N·m] and ``l_c`` [m]) and Klimchik's spring (geometry ``a,
L`` [m] and ``alpha`` [rad], parameters ``K_c`` [N/m] and ``s0`` [m]). The
compensator acts on one revolute joint, ``joint`` (joint 2 of an industrial arm;
the joint of the arm's shoulder on a robot with a track or a torso). Its formulas
take that joint's coordinate ``q`` (not ``q + offset``).

The torque is the balancing torque ``M`` of the papers (Y32: ``M = tau^0 - xi i``
on the compensated joint): it relieves the joint, so the load torque the joint
carries is ``xi i = tau^0 - M``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.errors import InputError
from elastocal.model.kinds import CompensatorKind, expect

HYDRO_PARAMS = ("C", "l_c")
SPRING_PARAMS = ("K_c", "s0")
HYDRO_UNITS = {"C": "N*m", "l_c": "m"}
SPRING_UNITS = {"K_c": "N/m", "s0": "m"}
#: geometry keys of each kind, in the order robot.toml lists them
GEOMETRY_KEYS = {CompensatorKind.HYDROPNEUMATIC: ("a", "b", "h"), CompensatorKind.SPRING: ("a", "L", "alpha")}
PARAMETER_NAMES = {CompensatorKind.HYDROPNEUMATIC: HYDRO_PARAMS, CompensatorKind.SPRING: SPRING_PARAMS}


@dataclass(frozen=True)
class CompensatorSpec:
    """A gravity compensator acting on joint ``joint`` (1-based).

    ``nominal`` optionally holds known parameter values (an elastocal extension of
    docs/formats.md: keys ``C``/``l_c`` or ``K_c``/``s0`` in the table).
    """

    kind: CompensatorKind
    joint: int
    geometry: tuple[tuple[str, float], ...]
    nominal: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        expect(CompensatorKind, self.kind, "kind")     # robot.toml's text is parsed by its reader
        if isinstance(self.joint, bool) or not isinstance(self.joint, int) or self.joint < 1:
            raise InputError(f"compensator joint must be a joint number (1, 2, ...), got {self.joint!r}")

    @property
    def index(self) -> int:
        """0-based index of the compensated joint in ``q``."""
        return self.joint - 1

    @property
    def parameter_names(self) -> tuple[str, str]:
        return PARAMETER_NAMES[self.kind]

    @property
    def parameter_units(self) -> dict[str, str]:
        return dict(HYDRO_UNITS if self.kind is CompensatorKind.HYDROPNEUMATIC else SPRING_UNITS)

    def geo(self, key: str) -> float:
        return dict(self.geometry)[key]

    def nominal_parameters(self) -> np.ndarray | None:
        nom = dict(self.nominal)
        names = self.parameter_names
        if all(n in nom for n in names):
            return np.array([nom[n] for n in names], dtype=float)
        return None

    def torque(self, q: np.ndarray | float, params: Sequence[float]) -> np.ndarray:
        """Balancing torque M(q) [N·m] for parameters (C, l_c) or (K_c, s0)."""
        q = np.asarray(q, dtype=float)
        p0, p1 = float(params[0]), float(params[1])
        if self.kind is CompensatorKind.HYDROPNEUMATIC:
            a, b, h = self.geo("a"), self.geo("b"), self.geo("h")
            r = math.hypot(a, h)
            alpha = math.atan2(a, h)
            length = self.hydro_length(q)
            return p0 * b * r * np.cos(alpha - q) / (length * (p1 - length))
        a, big_l, alpha = self.geo("a"), self.geo("L"), self.geo("alpha")
        s = self.spring_length(q)
        return p0 * (1.0 - p1 / s) * a * big_l * np.sin(alpha - q)

    def torque_derivatives(self, q: np.ndarray | float, params: Sequence[float]) -> np.ndarray:
        """d M / d params, shape (len(q), 2), analytic."""
        q = np.atleast_1d(np.asarray(q, dtype=float))
        p0, p1 = float(params[0]), float(params[1])
        if self.kind is CompensatorKind.HYDROPNEUMATIC:
            a, b, h = self.geo("a"), self.geo("b"), self.geo("h")
            r = math.hypot(a, h)
            alpha = math.atan2(a, h)
            length = self.hydro_length(q)
            g = b * r * np.cos(alpha - q) / length
            return np.column_stack([g / (p1 - length), -p0 * g / (p1 - length) ** 2])
        a, big_l, alpha = self.geo("a"), self.geo("L"), self.geo("alpha")
        s = self.spring_length(q)
        g = a * big_l * np.sin(alpha - q)
        return np.column_stack([(1.0 - p1 / s) * g, -p0 / s * g])

    def stiffness(self, q: np.ndarray | float, params: Sequence[float], step: float = 1e-6) -> np.ndarray:
        """Equivalent stiffness k_b = dM/dq [N·m/rad] (Y12); it adds to the joint's
        stiffness in the force-based model."""
        q = np.asarray(q, dtype=float)
        return (self.torque(q + step, params) - self.torque(q - step, params)) / (2 * step)

    def hydro_length(self, q: np.ndarray) -> np.ndarray:
        a, b, h = self.geo("a"), self.geo("b"), self.geo("h")
        r = math.hypot(a, h)
        alpha = math.atan2(a, h)
        return np.sqrt(b * b + r * r - 2.0 * b * r * np.sin(alpha - q))

    def spring_length(self, q: np.ndarray) -> np.ndarray:
        a, big_l, alpha = self.geo("a"), self.geo("L"), self.geo("alpha")
        return np.sqrt(a * a + big_l * big_l + 2.0 * a * big_l * np.cos(alpha - q))
