"""link_compliance: compliance located at the base or at the distal end of a link.

Klimchik's virtual-joint model with 6-D springs (docs/physics.md, "Effects beyond
the seeds' joint springs"): a rotational spring at location ``l`` turns the
whole chain beyond it by ``dphi_l = C_l M_l``, ``M_l`` the moment the structure
carries there. Locations: ``l = 0`` the base (its origin and axes: the base
tilting under the overturning moment), ``l = 1..5`` the distal end of link
``l`` (the frame of joint ``l+1`` before its rotation).
Components: the rotations about the two axes ``x, y`` normal to the axis of
the joint there (a rotation about that axis is the joint's own spring).
Parameters ``cl<l><axis>`` [rad/(N·m)]; ``cl2x, cl2y, cl3x, cl3y`` are the
classic torsion and bending springs at the ends of links 2 and 3 (exact, through
the link model's passive joints), the others enter to first order in their
small rotation: the marker moves by ``dphi x (p_marker - o_l)``.

The moments come from the change of the external wrench (with currents,
recovered from the joint torques, ``W = J_f^{-T} Gamma``). Absolute positions
(identify/absolute.py) see the whole moment each state puts on a location: the
gravity of the links beyond it (the robot description's masses) and the whole
external wrench, so an unloaded pose sags and its base tilts under the robot's
own weight too (:func:`_absolute_basis`). The compensator's force is internal
to the base and acts on link 2 in the plane of joint 2's motion, so it adds no
moment about the normal axes at link 1's end either. The effect is
``selectable``: a fit keeps only the components the data support (forward
selection with the diagnosis' own test, identify/selection.py), and the answer
says where the compliance is.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Mapping

import numpy as np
import pinocchio as pin

from elastocal.model.effects.base import (
    AbsoluteBasis,
    Effect,
    StaticBasis,
    StaticContext,
    strongest,
    wrong_sign,
)
from elastocal.model.robot import LOAD_FRAME, MARKER_PREFIX

#: the springs a six-axis arm's link model holds (links 2 and 3), for the table without a robot
_CLASSIC_SPRINGS = ("cl2x", "cl2y", "cl3x", "cl3y")


def locations(robot) -> tuple[int, ...]:
    """0 the base, 1..N-1 the distal ends of links 1..N-1 (the flange coincides with the
    last joint's frame of a DH robot, so a spring there would be the last joint springs over again)."""
    return tuple(range(6 if robot is None else robot.n_joints))


def parameters(robot) -> tuple[str, ...]:
    return tuple(f"cl{l}{a}" for l in locations(robot) for a in "xy")


def _in_link_model(robot) -> dict[str, int]:
    """The components that are passive joints of the link model (exact), with their index there."""
    names = _CLASSIC_SPRINGS if robot is None else robot.link_spring_names
    return {name: k for k, name in enumerate(names)}


#: the six-axis arm's table (docs/cli.md)
PARAMETERS = parameters(None)


def _normal_axes(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from elastocal.model.robot import normal_axes as normal

    return normal(axis)


def location_frames(robot, theta: np.ndarray, data=None) -> tuple[np.ndarray, np.ndarray, Mapping[str, np.ndarray]]:
    """Origins (L, 3) and component axes (L, 2, 3) of the locations in base axes
    at joint angles ``theta``, and the positions of the load point and markers (read-only),
    on the caller's work buffers ``data`` (``robot.create_data()``; a new one when None),
    which keep them for the rest of the computation (every fit of a pose asks again)."""
    data = robot.create_data() if data is None else data
    theta = np.asarray(theta, dtype=float)
    return data.reuse((location_frames, theta.tobytes()), lambda: _frames_at(robot, theta, data.rigid))


def _frames_at(robot, theta: np.ndarray, pdata) -> tuple[np.ndarray, np.ndarray, Mapping[str, np.ndarray]]:
    model = robot.model
    pin.computeJointJacobians(model, pdata, theta)
    pin.updateFramePlacements(model, pdata)
    origins = np.zeros((robot.n_joints, 3))
    axes = np.zeros((robot.n_joints, 2, 3))
    for l in locations(robot):
        # the axis of joint l+1 in base axes: its rotation axis, a prismatic joint's direction of travel
        axis_world = pdata.J[:3, l] if robot.prismatic[l] else pdata.J[3:, l]
        frame = pin.SE3.Identity() if l == 0 else pdata.oMi[l] * model.jointPlacements[l + 1]
        axis_local = frame.rotation.T @ axis_world
        u, v = _normal_axes(axis_local / np.linalg.norm(axis_local))
        origins[l] = frame.translation
        axes[l, 0] = frame.rotation @ u
        axes[l, 1] = frame.rotation @ v
    points = {name: pdata.oMf[model.getFrameId(name)].translation.copy()
              for name in [LOAD_FRAME, *(MARKER_PREFIX + m for m in robot.marker_names)]}
    for a in (origins, axes, *points.values()):
        a.setflags(write=False)
    return origins, axes, MappingProxyType(points)


def _basis(ctx: StaticContext) -> StaticBasis:
    robot, ds = ctx.robot, ctx.dataset
    names, exact = parameters(robot), _in_link_model(robot)
    p = len(names)
    links = np.zeros((len(ctx.tau), ctx.delta_link_moment.shape[1], p))
    add = np.zeros((ctx.n_deflections, 3, p))
    for name, k in exact.items():
        links[:, k, names.index(name)] = ctx.delta_link_moment[:, k]
    if robot is None or ds is None or ctx.delta_wrench is None:
        return StaticBasis(links=links, add=add)
    located = [k for k, name in enumerate(names) if name not in exact]
    loc_of = np.array([int(names[k][2:-1]) for k in located])
    axis_of = np.array(["xy".index(names[k][-1]) for k in located])
    defl_pose = ds.state_pose[ds.defl_state]
    data = ctx.data if ctx.data is not None else robot.create_data()
    for pi in range(len(ds.pose_ids)):
        defl = np.flatnonzero(defl_pose == pi)
        if defl.size == 0:
            continue
        origins, axes, points = location_frames(robot, robot.theta(ds.q[pi]), data)
        o = origins[loc_of]                                   # (K, 3)
        u = axes[loc_of, axis_of]                             # (K, 3)
        dw = ctx.delta_wrench[ds.defl_state[defl]]            # (n, 6)
        lever = points[LOAD_FRAME][None, :] - o               # (K, 3)
        # moment about each location's axis: u . (m + lever x f)  -> (n, K)
        m_axis = dw[:, 3:] @ u.T + dw[:, :3] @ np.cross(u, lever).T
        p_m = np.array([points[MARKER_PREFIX + ds.markers[k]] for k in ds.defl_marker[defl]])  # (n, 3)
        arm = np.cross(u[None, :, :], p_m[:, None, :] - o[None, :, :])                       # (n, K, 3)
        add[np.ix_(defl, np.arange(3), located)] = np.transpose(arm * m_axis[:, :, None], (0, 2, 1))
    return StaticBasis(links=links, add=add)


def gravity_moments(robot, theta: np.ndarray, origins: np.ndarray, data=None) -> np.ndarray:
    """(L, 3) moment of the weight of everything beyond each location about its
    origin, base axes [N·m] (the subtree of joint ``l + 1``; zero without masses), on the
    caller's work buffers ``data`` (a new one when None)."""
    out = np.zeros((robot.n_joints, 3))
    if not robot.has_masses:
        return out
    model = robot.model
    data = (robot.create_data() if data is None else data).rigid
    pin.centerOfMass(model, data, np.asarray(theta, dtype=float), True)     # subtree CoMs in their joint's frame
    g = np.array(robot.gravity)
    for l in locations(robot):
        com = data.oMi[l + 1].act(data.com[l + 1])
        out[l] = np.cross(com - origins[l], data.mass[l + 1] * g)
    return out


def _absolute_basis(ctx: StaticContext) -> AbsoluteBasis:
    """Per state: the link springs' angles and the located rotations' marker motions
    under the whole moment at each location (module docstring), at the commanded pose."""
    robot, ds = ctx.robot, ctx.dataset
    names, exact = parameters(robot), _in_link_model(robot)
    p = len(names)
    n_states, n_markers = len(ctx.tau), len(ds.markers)
    links = np.zeros((n_states, len(robot.springs_in_link_model), p))
    add = np.zeros((n_states, n_markers, 3, p))
    located = [k for k, name in enumerate(names) if name not in exact]
    loc_of = np.array([int(names[k][2:-1]) for k in located])
    axis_of = np.array(["xy".index(names[k][-1]) for k in located])
    spring_cols = [names.index(name) for name in robot.link_spring_names]
    n_springs = len(spring_cols)
    data = ctx.data if ctx.data is not None else robot.create_data()
    for pi in range(len(ds.pose_ids)):
        states = np.flatnonzero(ds.state_pose == pi)
        theta = robot.theta(ds.q[pi])
        th10 = robot.theta_links(theta)
        j_spr = robot.jacobians(th10, [LOAD_FRAME], links=True, data=data)[0][:, robot.springs_in_link_model]
        g_spr = (robot.gravity_torque(th10, links=True, data=data)[robot.springs_in_link_model] if robot.has_masses
                 else np.zeros(n_springs))
        w = ctx.wrench[states]                                          # (n, 6)
        # the load torque of each spring, J^T W - g (docs/formats.md's sign)
        links[np.ix_(states, np.arange(n_springs), spring_cols)] = (w @ j_spr - g_spr)[:, :, None] * np.eye(n_springs)[None]
        origins, axes, points = location_frames(robot, theta, data)
        o, u = origins[loc_of], axes[loc_of, axis_of]                    # (K, 3)
        lever = points[LOAD_FRAME][None, :] - o
        m_axis = w[:, 3:] @ u.T + w[:, :3] @ np.cross(u, lever).T        # (n, K): the load's moment
        m_axis = m_axis + np.sum(u * gravity_moments(robot, theta, origins, data)[loc_of], axis=1)[None, :]
        p_m = np.array([points[MARKER_PREFIX + m] for m in ds.markers])  # (M, 3)
        arm = np.cross(u[None, :, :], p_m[:, None, :] - o[None, :, :])   # (M, K, 3)
        add[np.ix_(states, np.arange(n_markers), np.arange(3), located)] = np.einsum("mkc,sk->smck", arm, m_axis)
    return AbsoluteBasis(links=links, add=add)


_PLACE = {0: "the base"}


def place(location: int) -> str:
    return _PLACE.get(location, f"the distal end of link {location}")


def _describe(names: tuple[str, ...], values: np.ndarray, stds: np.ndarray) -> str:
    by_place: dict[int, list[tuple[str, float]]] = {}
    for n, v in zip(names, values):
        by_place.setdefault(int(n[2:-1]), []).append((n[-1], v))
    k = strongest(names, values, stds)
    parts = []
    for loc, comps in sorted(by_place.items()):
        verb = "tilting" if loc == 0 else "bending"
        axes = " and ".join(a for a, _ in comps)
        sizes = ", ".join(f"{v:.2g}" for _, v in comps)
        parts.append(f"{place(loc)} ({verb} about {axes}, {sizes} rad/(N*m))")
    return (f"compliance located at {'; '.join(parts)}; strongest {names[k]} "
            f"({abs(values[k]) / stds[k]:.0f} std)")


def _plausibility(names: tuple[str, ...], values: np.ndarray, stds: np.ndarray) -> str | None:
    return wrong_sign(names, values, stds, "a compliance")


#: the smallest located compliance worth finding: 1e-7 rad/(N·m) turns a 1 kN·m moment
#: into 0.1 mrad, 100 µm at 1 m (a cast link or a base on a floor plate: 1e-7 to 1e-6)
DESIGN_COMPLIANCE = 1e-7


def make(robot=None) -> Effect:
    """The effect for ``robot``'s links (a six-axis arm's without one)."""
    return Effect(
        name="link_compliance",
        parameters=parameters(robot),
        units=("rad/(N*m)",) * len(parameters(robot)),
        seen_in=("static",),
        explanation="the structure gives way at the base or in the links, which no joint spring can mimic",
        evidence="lateral deflection follows the moment the load puts on the base or on a link",
        static_basis=_basis,
        absolute_basis=_absolute_basis,
        describe=_describe,
        plausibility=_plausibility,
        selectable=True,
        # the classic springs first: at a spherical wrist the distal ends of links 3, 4 and 5 are one
        # point, where link 4's and 5's bending equal joint springs plus link 3's (I - a4 a4' =
        # a5 a5' + w4 w4'); they count only for what the joint springs and cl2x..cl3y leave
        priority=tuple(0 if name in _in_link_model(robot) else 1 for name in parameters(robot)),
        sized=make,
        design_size=lambda c, n=len(parameters(robot)): np.full(n, DESIGN_COMPLIANCE),
        static_model="rotations about the two axes normal to the joint axis at the base and at the distal end of "
                     "each link, cl times the moment of the load change there; the data choose the components",
        run_model="not in the torque model: link springs change positions, not joint torques",
    )


EFFECT = make()
