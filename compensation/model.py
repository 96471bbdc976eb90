"""The static model compensation uses: joint springs, gravity, compensator, process wrench.

``CompensationModel`` is the robot description plus a calibration (docs/formats.md
§4): joint stiffness ``k1..k6`` and, optionally, the compensator parameters.
The load torque the joints carry is the full static one (docs/formats.md sign)::

    tau(theta, W) = J_f(theta)^T W - g(theta) - M(q2) e2

and the joints deflect by ``dtheta = c ⊙ tau`` (``c = 1/k``), so a command
``q`` puts the links at the fixed point ``theta = q + offset + c ⊙ tau(theta, W)``.

Gravity ``g`` needs the link masses of robot.toml; the compensator torque
``M`` needs them too (alone it would be a large unbalanced torque, so it is
used only together with gravity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from elastocal.errors import InputError
from elastocal.identify.calibration import Calibration
from elastocal.identify.robot import LOAD_FRAME, Robot

#: fixed-point tolerance on the joint angles [rad]
FIXED_POINT_TOL_RAD = 1e-13
MAX_FIXED_POINT_ITER = 100


@dataclass(frozen=True, eq=False)
class CompensationModel:
    """Robot and calibrated parameters; immutable."""

    robot: Robot
    stiffness: np.ndarray                          # (6,) k [N·m/rad]
    compensator: tuple[float, float] | None = None  # (C, l_c) or (K_c, s0)
    #: the drawing's robot when ``robot`` carries a geometric calibration (kinematic_errors):
    #: a path planned on the drawing means the pose the drawing gives (reference "nominal")
    nominal: Robot | None = None
    #: the frame the path positions: the load point, or a marker (a tool the tracker sees)
    tool: str = LOAD_FRAME

    def __post_init__(self) -> None:
        k = np.asarray(self.stiffness, dtype=float).reshape(-1)
        if k.shape != (6,) or not np.all(np.isfinite(k)) or np.any(k <= 0):
            raise InputError("joint stiffness k1..k6 must be 6 positive finite values")
        object.__setattr__(self, "stiffness", k)
        if self.compensator is not None:
            if self.robot.compensator is None:
                raise InputError("compensator parameters given but the robot description has no [compensator]",
                                 source=self.robot.source)
            object.__setattr__(self, "compensator", (float(self.compensator[0]), float(self.compensator[1])))

    @property
    def compliance(self) -> np.ndarray:
        return 1.0 / self.stiffness

    @property
    def uses_gravity(self) -> bool:
        return self.robot.has_masses

    @property
    def uses_compensator(self) -> bool:
        return self.uses_gravity and self.compensator is not None and self.robot.compensator is not None

    @classmethod
    def from_calibration(cls, robot: Robot, cal: Calibration, *, source: str = "calibration") -> "CompensationModel":
        """Stiffness and compensator from a calibration file; the compensator
        falls back to the robot description's nominal values when the
        calibration does not hold them."""
        if cal.robot and cal.robot != robot.name:
            raise InputError(f"the calibration is for robot {cal.robot!r}, the description is {robot.name!r}",
                             source=source, column="robot")
        params = cal.parameters
        missing = [f"k{j}" for j in range(1, 7) if f"k{j}" not in params]
        if missing:
            raise InputError(f"missing joint stiffness {', '.join(missing)}", source=source, column="parameters")
        k = np.array([float(params[f"k{j}"]["value"]) for j in range(1, 7)])
        bad = np.flatnonzero(~(k > 0))
        if bad.size:
            raise InputError(f"stiffness must be positive, got {k[bad[0]]}", source=source,
                             column=f"parameters.k{bad[0] + 1}")
        comp = None
        spec = robot.compensator
        if spec is not None:
            names = spec.parameter_names
            if all(n in params for n in names):
                comp = tuple(float(params[n]["value"]) for n in names)
            elif any(n in params for n in names):
                raise InputError(f"give both compensator parameters {' and '.join(names)}", source=source,
                                 column="parameters")
            else:
                nominal = spec.nominal_parameters()
                comp = None if nominal is None else (float(nominal[0]), float(nominal[1]))
            other = ("K_c", "s0") if spec.kind == "hydropneumatic" else ("C", "l_c")
            if any(n in params for n in other):
                raise InputError(f"compensator parameters {', '.join(other)} do not fit the robot's "
                                 f"{spec.kind} compensator", source=source, column="parameters")
        if "kinematic_errors" in cal.model:        # the real geometry (issue 12, part 7)
            from elastocal.identify.accuracy import calibrated_robot

            return cls(robot=calibrated_robot(robot, cal), stiffness=k, compensator=comp, nominal=robot)
        return cls(robot=robot, stiffness=k, compensator=comp)

    def with_tool(self, tool: str) -> "CompensationModel":
        """The same model positioning ``tool`` (the load point or a marker name)."""
        from dataclasses import replace

        self.robot.frame_id(tool)
        return replace(self, tool=tool)


#: calibration effects compensation models, and those that move no tool point of a planned path
#: (measurement-side session effects, and friction: a torque, not a deflection at rest)
MODELLED_EFFECTS = ("joint_stiffness", "compensator", "gravity", "kinematic_errors")
NO_PATH_DEFLECTION = ("thermal_drift", "tracker_frame", "coulomb_friction", "viscous_friction",
                      "load_dependent_friction")


def unmodelled_effects(cal: Calibration) -> dict[str, list[str]]:
    """Effects of the calibration that deflect the robot but compensation leaves out, with
    the calibration's parameters of each (cal.json names them; docs/cli.md's effect table)."""
    from elastocal.identify.effects import get_effect

    out = {}
    for name in cal.model:
        if name in MODELLED_EFFECTS or name in NO_PATH_DEFLECTION:
            continue
        names = get_effect(name).parameters
        out[name] = [p for p in cal.parameters if p in names] or [p for p in names if p in cal.parameters]
    return out


class StaticKernel:
    """Work buffers (one Pinocchio Data) for the static model, evaluated over
    arrays of configurations (n, 6). Pinocchio is called per configuration;
    the compensator and the fixed-point updates are vectorised."""

    def __init__(self, model: CompensationModel) -> None:
        self.m = model
        self.pmodel = model.robot.model
        self.data = self.pmodel.createData()
        self.fid = model.robot.frame_id(LOAD_FRAME)
        self.tool_fid = model.robot.frame_id(model.tool)
        self.offsets = model.robot.offsets
        self.offset2 = float(model.robot.joints[1].offset)
        self.c = model.compliance
        self.spec = model.robot.compensator
        self.gravity = model.uses_gravity
        self.with_compensator = model.uses_compensator

    def jacobians(self, theta: np.ndarray) -> np.ndarray:
        """Load-point Jacobians (n, 6, 6), LOCAL_WORLD_ALIGNED."""
        out = np.empty((len(theta), 6, 6))
        for i, th in enumerate(theta):
            out[i] = pin.computeFrameJacobian(self.pmodel, self.data, th, self.fid, pin.LOCAL_WORLD_ALIGNED)
        return out

    def positions(self, theta: np.ndarray) -> np.ndarray:
        """Tool-point positions (n, 3) in the base frame (the load point unless the model names a tool)."""
        out = np.empty((len(theta), 3))
        for i, th in enumerate(theta):
            pin.forwardKinematics(self.pmodel, self.data, th)
            out[i] = pin.updateFramePlacement(self.pmodel, self.data, self.tool_fid).translation
        return out

    def nominal_targets(self, q: np.ndarray, *, tol: float = 1e-12, max_iter: int = 50) -> np.ndarray:
        """Link angles (n, 6) at which the calibrated robot's tool frame has the
        pose the drawing's robot gives it at ``q`` (Newton on the SE(3) error)."""
        nominal = self.m.nominal if self.m.nominal is not None else self.m.robot
        nmodel = nominal.model
        ndata = nmodel.createData()
        nfid = nominal.frame_id(self.m.tool)
        out = np.empty((len(q), 6))
        theta = q[0] + self.offsets if len(q) else None
        for i, qi in enumerate(q):
            pin.framesForwardKinematics(nmodel, ndata, qi + nominal.offsets)
            target = ndata.oMf[nfid].copy()
            theta = qi + self.offsets if i == 0 else theta
            for _ in range(max_iter):
                pin.framesForwardKinematics(self.pmodel, self.data, theta)
                err = pin.log6(self.data.oMf[self.tool_fid].actInv(target)).vector
                if np.max(np.abs(err)) < tol:
                    break
                jac = pin.computeFrameJacobian(self.pmodel, self.data, theta, self.tool_fid, pin.LOCAL)
                theta = theta + np.linalg.solve(jac, err)
            else:
                raise InputError(f"no configuration of the calibrated robot reaches point {i + 1} of the path "
                                 "as the drawing does (singular or out of reach)")
            out[i] = theta
        return out

    def passive_torque(self, theta: np.ndarray) -> np.ndarray:
        """``-g(theta) - M e2`` (n, 6): the load torque without external wrench."""
        tau = np.zeros((len(theta), 6))
        if self.gravity:
            for i, th in enumerate(theta):
                tau[i] = -pin.computeGeneralizedGravity(self.pmodel, self.data, th)
        if self.with_compensator:
            tau[:, 1] -= self.spec.torque(theta[:, 1] - self.offset2, self.m.compensator)
        return tau

    def torque(self, theta: np.ndarray, wrench: np.ndarray) -> np.ndarray:
        """Full static load torque ``J^T W - g - M e2`` (n, 6)."""
        tau = self.passive_torque(theta)
        loaded = np.any(wrench != 0.0, axis=1)
        if np.any(loaded):
            jac = self.jacobians(theta[loaded])
            tau[loaded] += np.einsum("nij,ni->nj", jac, wrench[loaded])
        return tau

    def equilibrium(self, q: np.ndarray, wrench: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
        """Link angles (n, 6) at the fixed points ``theta = q + offset + c ⊙ tau(theta, W)``."""
        base = q + self.offsets
        theta = base.copy() if start is None else np.array(start, dtype=float)
        if not self.gravity and not np.any(wrench):
            return base
        active = np.arange(len(q))
        for _ in range(MAX_FIXED_POINT_ITER):
            with np.errstate(all="ignore"):
                new = base[active] + self.c * self.torque(theta[active], wrench[active])
            diverged = ~np.all(np.isfinite(new), axis=1) | np.any(np.abs(new) > 1e3, axis=1)
            if np.any(diverged):
                raise NotConverged(int(active[np.argmax(diverged)]))
            step = np.max(np.abs(new - theta[active]), axis=1)
            theta[active] = new
            active = active[step >= FIXED_POINT_TOL_RAD]
            if active.size == 0:
                return theta
        raise NotConverged(int(active[0]))


class NotConverged(InputError):
    """The loaded equilibrium of sample ``sample`` (0-based) has no fixed point: the load is too
    large for the stiffness. The command names the file, line and column of the sample."""

    def __init__(self, sample: int) -> None:
        self.sample = sample
        super().__init__(f"the static model does not converge at sample {sample + 1} of the path "
                         "(stiffness too low for the load?)")
