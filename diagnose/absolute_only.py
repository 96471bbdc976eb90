"""Diagnosis of a table without loads (docs/cli.md, "Absolute-only tables").

A geometric calibration table holds only absolute positions: the model is
compared with them (diagnose/absolute.py: the registration always in) and the
effects such data can show are tested stepwise: the geometry
(``kinematic_errors``), the joints' twist under the robot's own weight
(``joint_stiffness``, when the description has the masses), the play of a joint
whose weight torque changes sign across the poses (``backlash``, the masses too;
listed as not testable, with why, when no joint's torque does), a thermal drift
(when the readings have times). Whether the final model is complete is a comparison
with the noise floor; without one (no repeated readings, no uncertainty
columns, no tracker noise model) the verdict is null and says that no floor is
known, never "at the floor".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from elastocal.diagnose.absolute import AbsoluteDiagnosis, diagnose_absolute
from elastocal.diagnose.stepwise import FLOOR_RATIO
from elastocal.diagnose.verdict import NotTestable
from elastocal.model.effects import ABSOLUTE_ONLY_POOL, absolute_only_untested, get_effect, having
from elastocal.model.robot import Robot
from elastocal.identify.static import StaticDataset

NO_FLOOR = ("no noise floor is known (no repeated readings, no u95 or sx,sy,sz columns, no tracker noise model): "
            "whether anything is missing cannot be said; the residual is not compared with noise")


@dataclass(frozen=True, eq=False)
class AbsoluteOnlyDiagnosis:
    """What ``elastocal diagnose`` finds on a table without loads."""

    model: tuple[str, ...]
    absolute: AbsoluteDiagnosis
    not_testable: tuple[NotTestable, ...]
    outliers: tuple = ()

    @property
    def floor(self) -> float | None:
        return self.absolute.final.noise_floor

    @property
    def at_floor(self) -> bool:
        f = self.absolute.final
        return f.noise_floor is not None and f.rms <= FLOOR_RATIO * f.noise_floor

    @property
    def verdict(self) -> str | None:
        """The first step, only when the final model sits at a known floor."""
        steps = self.absolute.steps
        return steps[0].effect if steps and self.at_floor else None

    def unexplained(self) -> tuple[str, ...]:
        f = self.absolute.final
        if f.noise_floor is None:
            return (NO_FLOOR,)
        if self.at_floor:
            return ()
        added = " after " + ", ".join(s.effect for s in self.absolute.steps) if self.absolute.steps else ""
        return (f"absolute positions stay {f.rms / f.noise_floor:.2f}x their noise floor{added} "
                f"({f.rms * 1e6:.1f} µm rms, floor {f.noise_floor * 1e6:.1f} µm): no effect of this table explains "
                "the rest",)

    def to_json(self) -> dict:
        a = self.absolute
        b, f = a.base, a.final
        return {"model": list(self.model), "torque": b.static.torque, "form": b.static.form,
                "residual": {"rms": b.rms, "max": b.max, "n": b.n, "unit": "m"},
                "noise_floor": b.noise_floor,
                "candidates": [c.to_json() for c in a.candidates],
                "verdict": self.verdict,
                "not_testable": [{"effect": n.effect, "reason": n.reason} for n in self.not_testable],
                "steps": [{"effect": s.effect, "residual": {"rms": s.rms_after, "max": s.max_after, "n": b.n,
                                                            "unit": "m"},
                           "noise_floor": s.noise_floor_after, "delta_bic": s.delta_bic, "p_value": s.p_value}
                          for s in a.steps],
                "final": {"model": list(f.model), "residual": {"rms": f.rms, "max": f.max, "n": f.n, "unit": "m"},
                          "noise_floor": f.noise_floor},
                "unexplained": {"sentences": list(self.unexplained())} if self.unexplained() else None,
                "outliers": [o.to_json() for o in self.outliers],
                **a.to_json()}

    def text(self) -> str:
        a = self.absolute
        b, f = a.base, a.final

        def um(x):
            return "-" if x is None else f"{x * 1e6:.1f} µm"

        lines = [f"  a table without loads: {', '.join(self.model)} against the absolute positions",
                 f"  residual {um(b.rms)} rms (max {um(b.max)}), noise floor {um(b.noise_floor)}"]
        for c in a.candidates:
            mark = "significant" if c.significant else "not significant"
            lines.append(f"  candidate {c.effect}: {um(c.rms_after)} rms after, delta BIC {c.delta_bic:.1f}, "
                         f"p {c.p_value:.1g} ({mark}): {c.evidence}")
        for s in a.steps:
            lines.append(f"  step: add {s.effect} -> {um(s.rms_after)} rms")
        lines.append(f"  final {', '.join(f.model)}: {um(f.rms)} rms, floor {um(f.noise_floor)}")
        lines.append(f"  verdict: {self.verdict or 'none'}")
        lines += [f"  {s}" for s in self.unexplained()]
        lines += [f"  not tested: {n.effect}: {n.reason}" for n in self.not_testable]
        return "\n".join(lines)


def diagnose_absolute_only(robot: Robot, ds: StaticDataset, model: Sequence[str], *,
                           tracker_prior: Sequence[float] | None = None) -> AbsoluteOnlyDiagnosis:
    """The stepwise diagnosis of a table without loads (module docstring)."""
    # the effects such a table can show, each unless its module says why this table cannot test it;
    # then those such tables never test, with their modules' reasons
    pool, skipped = [], []
    for name in (e for e in ABSOLUTE_ONLY_POOL if e not in model):
        reason = get_effect(name).absolute_only_refusal(robot, ds)
        if reason is None:
            pool.append(name)
        else:
            skipped.append((name, reason))
    skipped += [(name, get_effect(name).absolute_only_refusal(robot, ds)) for name in absolute_only_untested()]
    diag = diagnose_absolute(robot, ds, tuple(model), pool=tuple(pool), tracker_prior=tracker_prior)
    skipped += list(diag.refused)             # what the poses cannot show (no joint's torque changes sign)
    return AbsoluteOnlyDiagnosis(model=tuple(dict.fromkeys([*model, *having("registration")])), absolute=diag,
                                 not_testable=tuple(NotTestable(e, r) for e, r in skipped),
                                 outliers=tuple(ds.outliers))
