"""Kinds are Enums below the edge: text is parsed where it is read, and a plain string handed to a
fit or a typed record is refused, because a str Enum's member equals its text and would let the
string through every comparison unnoticed."""

import dataclasses
import json

import numpy as np
import pytest

from elastocal.compensation.trajectory import CompensatedPath
from elastocal.formats.calibration import Calibration
from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.dataset import build_dataset
from elastocal.identify.static import identify_static
from elastocal.identify.staticmodel import Problem
from elastocal.model.effects.base import StaticContext
from elastocal.model.kinds import CompensatorKind, KinematicForm, NoiseSource, TorqueSource, Weighting, expect
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static

ROBOT = bundled_robot()


@pytest.mark.parametrize("kind", [TorqueSource, KinematicForm, Weighting, CompensatorKind, NoiseSource])
def test_a_member_reads_and_writes_as_its_text(kind):
    for member in kind:
        assert kind(member.value) is member
        assert str(member) == f"{member}" == member.value
        assert json.dumps({"k": member}) == json.dumps({"k": member.value})


def test_expect_takes_a_member_and_refuses_its_text():
    assert expect(TorqueSource, TorqueSource.FORCE, "torque") is TorqueSource.FORCE
    with pytest.raises(TypeError, match=r"torque must be a TorqueSource .*TorqueSource\(text\).*'force'"):
        expect(TorqueSource, "force", "torque")
    with pytest.raises(TypeError, match="form must be a KinematicForm"):
        expect(KinematicForm, TorqueSource.FORCE, "form")      # another Enum's member is no better


@pytest.fixture(scope="module")
def table():
    return simulate_static(ROBOT, CellTruth(), seed=3, plan=StaticPlan(n_poses=6, n_loads=1, repeats=1))


@pytest.mark.parametrize("keyword,text", [("torque", "force"), ("form", "first-order"), ("weighting", "ols")])
def test_the_fit_refuses_text_for_a_kind(table, keyword, text):
    with pytest.raises(TypeError, match=f"{keyword} must be a"):
        identify_static(ROBOT, table, **{keyword: text})


def test_the_typed_records_refuse_text(table):
    ds = build_dataset(table)
    with pytest.raises(TypeError, match="torque must be a TorqueSource"):
        Problem(ROBOT, ds, (), "current", KinematicForm.EXACT, ())
    with pytest.raises(TypeError, match="form must be a KinematicForm"):
        Problem(ROBOT, ds, (), TorqueSource.CURRENT, "exact", ())
    fit = identify_static(ROBOT, table, form=KinematicForm.FIRST_ORDER)
    assert fit.torque is TorqueSource.CURRENT and fit.form is KinematicForm.FIRST_ORDER
    with pytest.raises(TypeError, match="torque must be a TorqueSource"):
        dataclasses.replace(fit, torque="current")
    ctx = fit.absolute_model[2]
    assert ctx.torque_source is TorqueSource.CURRENT and ctx.form is KinematicForm.FIRST_ORDER
    with pytest.raises(TypeError, match="torque_source must be a TorqueSource"):
        StaticContext(tau=ctx.tau, delta_tau=ctx.delta_tau, delta_link_moment=ctx.delta_link_moment,
                      state_is_reference=ctx.state_is_reference, deflection_dt=ctx.deflection_dt,
                      n_deflections=ctx.n_deflections, torque_source="current")
    with pytest.raises(TypeError, match="torque must be a TorqueSource"):
        Calibration(robot="HH-150", created="2026-01-05T08:00:00Z", model=("joint_stiffness",), torque="current",
                    parameters=())
    with pytest.raises(TypeError, match="form must be a KinematicForm"):
        CompensatedPath(form="exact", reference="unloaded", q_planned=np.zeros((1, 6)), wrench=np.zeros((1, 6)),
                        q_command=np.zeros((1, 6)), theta_target=np.zeros((1, 6)), tcp_deflection=np.zeros((1, 3)))


def test_the_compensator_takes_its_kind_parsed():
    from elastocal.model.compensator import CompensatorSpec

    spec = ROBOT.compensator
    assert spec.kind is CompensatorKind.HYDROPNEUMATIC       # robot.toml's text, parsed by its reader
    with pytest.raises(TypeError, match="kind must be a CompensatorKind"):
        CompensatorSpec(kind="hydropneumatic", joint=spec.joint, geometry=spec.geometry)
