"""Effects that static before/after-load differences cannot show.

They are identified from run data (joint-2 sweeps, UV/VU runs, absolute
positions); see identify/compensator.py and identify/friction.py. Each carries
the reason static data are refused.
"""

from __future__ import annotations

from elastocal.identify.effects.base import Effect, StaticContext


def _refuse(reason: str):
    def refusal(ctx: StaticContext) -> str:
        return reason
    return refusal


EFFECTS = {
    "compensator": Effect(
        name="compensator", parameters=("C", "l_c"), units=("N*m", "m"), seen_in=("runs",),
        explanation="the gravity compensator on joint 2 pushes with a force that changes with q2",
        evidence="joint-2 torque residual that follows q2",
        static_refusal=_refuse("static differences do not separate the compensator from k2; "
                               "identify C, l_c (or K_c, s0) from a joint-2 sweep in the run table"),
    ),
    "gravity": Effect(
        name="gravity", parameters=("mass moments",), units=("kg*m",), seen_in=("runs",),
        explanation="the weight of the links loads the joints",
        evidence="torque residual that follows the arm's posture",
        static_refusal=_refuse("gravity cancels in before/after-load differences; it shows in run torques"),
    ),
    "coulomb_friction": Effect(
        name="coulomb_friction", parameters=tuple(f"fc{j}" for j in range(1, 7)), units=("N*m",) * 6,
        seen_in=("runs",), explanation="friction of constant size opposes every motion",
        evidence="UV and VU currents differ by a constant",
        static_refusal=_refuse("friction acts during motion; static data hold no motion (use UV/VU runs)"),
    ),
    "viscous_friction": Effect(
        name="viscous_friction", parameters=tuple(f"fv{j}" for j in range(1, 7)), units=("N*m*s/rad",) * 6,
        seen_in=("runs",), explanation="friction grows with speed",
        evidence="the UV/VU current difference grows with speed",
        static_refusal=_refuse("friction acts during motion; static data hold no motion (use runs at two speeds)"),
    ),
    "load_dependent_friction": Effect(
        name="load_dependent_friction", parameters=tuple(f"fl{j}" for j in range(1, 7)), units=("1",) * 6,
        seen_in=("runs",), explanation="friction grows with the load the gear carries",
        evidence="the UV/VU current difference grows with the load",
        static_refusal=_refuse("friction acts during motion; static data hold no motion (use runs at two loads)"),
    ),
    "tracker_frame": Effect(
        name="tracker_frame", parameters=("rx", "ry", "rz", "tx", "ty", "tz"), units=("rad",) * 3 + ("m",) * 3,
        seen_in=("runs",), explanation="the tracker frame is registered to the robot base with an error",
        evidence="absolute positions off by a rigid motion",
        static_refusal=_refuse("a rigid registration error cancels in deflections; it needs absolute positions"),
    ),
    "kinematic_errors": Effect(
        name="kinematic_errors", parameters=("joint offsets", "link lengths"), units=("rad", "m"),
        seen_in=("runs",), explanation="the real link lengths and joint zeros differ from the drawing",
        evidence="absolute position errors that follow the pose",
        static_refusal=_refuse("geometric errors barely change deflections; they need absolute positions"),
    ),
}
