"""ABB Externally Guided Motion (EGM), joint mode: ``egm://HOST:PORT`` (docs/stream.md).

The messages are the protobuf classes ``EgmRobot`` and ``EgmSensor`` that the
``abb-robot-client`` package ships (``abb_robot_client.egm.egm_pb2``, generated from ABB's
``egm.proto``); nothing of the wire format is written here. Its ``EGM`` client class is not
used: it binds every interface (``''``), answers only ``False`` when a socket fails and
counts its sequence number up twice per message; this backend binds the URL's address,
raises typed errors and numbers its answers once each.

From the controller (``EgmRobot``, every cycle): ``header`` (``seqno``, ``tm`` [ms],
``mtype`` = ``MSGTYPE_DATA``), ``feedBack.joints`` (measured axes [deg]; axes beyond the
sixth in ``feedBack.externalJoints``), ``motorState``, ``rapidExecState``, ``mciState`` and
``testSignals.signals`` (what the RAPID program's ``TestSignDefine`` channels carry; here
channel j is axis j's motor current, in the unit ``current_scale_a`` turns into amperes).
The answer (``EgmSensor``): ``header`` (own ``seqno``, the ``tm`` echoed,
``MSGTYPE_CORRECTION``) and ``planned.joints`` (the absolute joint targets of this cycle
[deg], axes beyond the sixth in ``planned.externalJoints``), as ``EGMActJoint`` /
``EGMRunJoint`` expect.
"""

from __future__ import annotations

import math

import numpy as np
from abb_robot_client.egm import egm_pb2
from google.protobuf.message import DecodeError

from elastocal.drivers.guidance import ControllerState, Guidance, GuidanceKind
from elastocal.errors import ProtocolError

#: joints in EgmJoints of the robot itself; more go to externalJoints (ABB's 7-axis arms do so)
ROBOT_AXES = 6
_DEG = 180.0 / math.pi


def robot_message_joints(feedback, n_joints: int) -> np.ndarray:
    """The n joints [deg] of an EgmFeedBack/EgmPlanned: joints, then externalJoints."""
    values = list(feedback.joints.joints)
    if n_joints > ROBOT_AXES:
        values += list(feedback.externalJoints.joints)
    return np.asarray(values[:n_joints] if len(values) >= n_joints else values, dtype=float)


class EgmGuidance(Guidance):
    kind = GuidanceKind.EGM

    def __init__(self, url, *, n_joints: int, source: str = "url") -> None:
        super().__init__(url, n_joints=n_joints, source=source)
        self._seqno = 0

    def _decode(self, data: bytes, t_ns: int) -> ControllerState:
        msg = egm_pb2.EgmRobot()
        try:
            msg.ParseFromString(data)
        except DecodeError as exc:
            raise ProtocolError(f"{self.name}: not an EgmRobot message ({exc})") from None
        if not msg.HasField("header") or not msg.HasField("feedBack"):
            raise ProtocolError(f"{self.name}: an EgmRobot message without header or feedBack")
        if msg.header.mtype != egm_pb2.EgmHeader.MSGTYPE_DATA:
            raise ProtocolError(f"{self.name}: message type {msg.header.mtype}, expected MSGTYPE_DATA")
        q_deg = robot_message_joints(msg.feedBack, self.n_joints)
        currents = None
        if msg.HasField("testSignals") and len(msg.testSignals.signals) >= self.n_joints:
            currents = np.asarray(msg.testSignals.signals[:self.n_joints], dtype=float) * self.params.current_scale_a
        ready = (msg.motorState.state == egm_pb2.EgmMotorState.MOTORS_ON
                 and msg.rapidExecState.state == egm_pb2.EgmRapidCtrlExecState.RAPID_RUNNING
                 and msg.mciState.state != egm_pb2.EgmMCIState.MCI_ERROR)
        return ControllerState(t_ns=t_ns, sequence=int(msg.header.seqno), q=q_deg / _DEG, currents_a=currents,
                               controller_time_ms=int(msg.header.tm), ready=bool(ready))

    def _encode(self, q_target: np.ndarray, last: ControllerState) -> bytes:
        self._seqno = (self._seqno + 1) & 0xFFFFFFFF
        msg = egm_pb2.EgmSensor()
        msg.header.seqno = self._seqno
        msg.header.tm = last.controller_time_ms & 0xFFFFFFFF
        msg.header.mtype = egm_pb2.EgmHeader.MSGTYPE_CORRECTION
        deg = (q_target * _DEG).tolist()
        msg.planned.joints.joints.extend(deg[:ROBOT_AXES])
        if len(deg) > ROBOT_AXES:
            msg.planned.externalJoints.joints.extend(deg[ROBOT_AXES:])
        return msg.SerializeToString()
