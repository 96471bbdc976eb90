"""A simulated KUKA controller running RSI over Ethernet, on 127.0.0.1 (docs/stream.md).

Every interpolation cycle (4 or 12 ms) it sends ``<Rob Type="KUKA">`` with ``<RIst X Y Z A B
C/>`` (the rigid model's tool pose of the measured axes [mm, deg], ZYX angles), ``<AIPos
A1..An/>`` (the axes [deg]), ``<ASPos .../>`` (the axes where ``RSI_ON`` found the robot: the
reference of the absolute corrections), ``<MACur .../>`` (motor currents [A]), ``<Delay
D=""/>`` (late answers so far) and ``<IPOC>`` (the cycle's time stamp [ms]). An answer
``<Sen><AKorr A1..An/><IPOC/></Sen>`` echoing this cycle's IPOC before the next cycle moves
the robot to reference + correction (``RSI_ON(#ABSOLUTE)`` with ``RSI_MOVECORR``); a
missing or late one is counted and the last correction held; ``max_late`` of them in a row
stop the robot, as the ETHERNET object's timeout does. Corrections beyond ``max_correction_deg``
stop it too (the limits of the controller's AXISCORR object).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin

from elastocal.model.robot import LOAD_FRAME
from elastocal.sims.guidance_peer import SimGuidedController

_DEG = 180.0 / math.pi


class SimRsiController(SimGuidedController):
    """The simulated RSI controller (see the module docstring)."""

    def __init__(self, robot, computer, *, cycle_s: float = 0.004, max_late: int = 100,
                 max_correction_deg: float = 90.0, **kw) -> None:
        super().__init__(robot, computer, cycle_s=cycle_s, comm_timeout_s=max_late * cycle_s, **kw)
        self.reference_deg = robot.q * _DEG
        self.max_correction_deg = float(max_correction_deg)
        self._ipoc = 0
        self._model = robot.robot.model
        self._data = self._model.createData()     # this controller's thread owns it
        self._tool = robot.robot.frame_id(LOAD_FRAME)

    def _axes(self, tag: str, values) -> ET.Element:
        return ET.Element(tag, {f"A{j}": f"{v:.6f}" for j, v in enumerate(values, start=1)})

    def _state_message(self, cycle: int, t_ns: int) -> bytes:
        q = self.robot.q
        self._ipoc = self.controller_ms(cycle)
        pin.framesForwardKinematics(self._model, self._data, self.robot.robot.theta(q))
        pose = self._data.oMf[self._tool]
        roll, pitch, yaw = pin.rpy.matrixToRpy(pose.rotation)
        root = ET.Element("Rob", {"Type": "KUKA"})
        x, y, z = pose.translation * 1e3
        root.append(ET.Element("RIst", {"X": f"{x:.4f}", "Y": f"{y:.4f}", "Z": f"{z:.4f}", "A": f"{yaw * _DEG:.4f}",
                                        "B": f"{pitch * _DEG:.4f}", "C": f"{roll * _DEG:.4f}"}))
        root.append(self._axes("AIPos", q * _DEG))
        root.append(self._axes("ASPos", self.reference_deg))
        if self.robot.has_currents:
            root.append(self._axes("MACur", self.robot.currents()))
        root.append(ET.Element("Delay", {"D": str(self.stats().late)}))
        ET.SubElement(root, "IPOC").text = str(self._ipoc)
        return ET.tostring(root)

    def _answer_target(self, data: bytes, cycle: int) -> np.ndarray | None:
        try:
            root = ET.fromstring(data)
            ipoc = int((root.find("IPOC").text or "").strip())
            korr = root.find("AKorr")
            corr = np.array([float(korr.attrib[f"A{j}"]) for j in range(1, self.robot.n_joints + 1)])
        except (ET.ParseError, AttributeError, KeyError, ValueError):
            return None                 # malformed: as good as no answer
        if root.tag != "Sen" or ipoc != self._ipoc:
            return None                 # not this cycle's answer: late
        if np.max(np.abs(corr)) > self.max_correction_deg:
            self._finish(f"AKorr {np.round(corr, 4).tolist()} deg beyond the correction limit "
                         f"{self.max_correction_deg:g} deg: the robot stopped")
            self._stop.set()
            return None
        return (self.reference_deg + corr) / _DEG
