"""A simulated ABB controller running EGM in joint mode, on 127.0.0.1 (docs/stream.md).

It speaks the messages of ``abb_robot_client.egm.egm_pb2`` (ABB's ``egm.proto``): every
cycle an ``EgmRobot`` with ``header`` (``seqno``, ``tm`` [ms], ``MSGTYPE_DATA``),
``feedBack.joints`` and ``planned.joints`` (the axes [deg]; beyond the sixth in
``externalJoints``), ``motorState`` ``MOTORS_ON``, ``mciState`` ``MCI_RUNNING``,
``rapidExecState`` ``RAPID_RUNNING`` and ``testSignals`` carrying the motor currents [A]
(what ``TestSignDefine`` channels 1..n would carry on the real controller); the answer's
``EgmSensor.planned.joints`` [deg] moves the simulated robot. A target farther from the
robot than its joints move in a cycle stops guidance, as the real controller's speed
supervision does.
"""

from __future__ import annotations

import math

import numpy as np
from abb_robot_client.egm import egm_pb2
from google.protobuf.message import DecodeError

from elastocal.sims.guidance_peer import SimGuidedController

ROBOT_AXES = 6
_DEG = 180.0 / math.pi


class SimEgmController(SimGuidedController):
    """The simulated EGM controller (see the module docstring)."""

    def __init__(self, robot, computer, *, cycle_s: float = 0.004, max_speed_rad_s: float = 2.0, **kw) -> None:
        super().__init__(robot, computer, cycle_s=cycle_s, **kw)
        self.max_step_rad = max_speed_rad_s * cycle_s

    def _state_message(self, cycle: int, t_ns: int) -> bytes:
        msg = egm_pb2.EgmRobot()
        msg.header.seqno = (cycle + 1) & 0xFFFFFFFF
        msg.header.tm = self.controller_ms(cycle) & 0xFFFFFFFF
        msg.header.mtype = egm_pb2.EgmHeader.MSGTYPE_DATA
        deg = (self.robot.q * _DEG).tolist()
        for part in (msg.feedBack, msg.planned):
            part.joints.joints.extend(deg[:ROBOT_AXES])
            if len(deg) > ROBOT_AXES:
                part.externalJoints.joints.extend(deg[ROBOT_AXES:])
        msg.motorState.state = egm_pb2.EgmMotorState.MOTORS_ON
        msg.mciState.state = egm_pb2.EgmMCIState.MCI_RUNNING
        msg.rapidExecState.state = egm_pb2.EgmRapidCtrlExecState.RAPID_RUNNING
        if self.robot.has_currents:
            msg.testSignals.signals.extend(self.robot.currents().tolist())
        return msg.SerializeToString()

    def _answer_target(self, data: bytes, cycle: int) -> np.ndarray | None:
        msg = egm_pb2.EgmSensor()
        try:
            msg.ParseFromString(data)
        except DecodeError:
            return None                 # not an EgmSensor message: ignored, as the controller does
        deg = list(msg.planned.joints.joints) + list(msg.planned.externalJoints.joints)
        if len(deg) != self.robot.n_joints:
            return None
        target = np.asarray(deg) / _DEG
        if np.max(np.abs(target - self.robot.q)) > self.max_step_rad:
            self._finish(f"joint target {np.round(target, 5).tolist()} is beyond one cycle's motion: "
                         "speed supervision stopped the robot")
            self._stop.set()
            return None
        return target
