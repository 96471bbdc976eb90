"""KUKA Robot Sensor Interface (RSI) over Ethernet: ``rsi://HOST:PORT?cycle_ms=4`` (docs/stream.md).

XML over UDP, parsed with the standard library's parser. Every interpolation cycle (4 ms
in IPO_FAST mode, 12 ms otherwise) the controller sends a ``<Rob Type="KUKA">`` message with
the elements its RSI Ethernet configuration declares (``DEF_...`` tags, ``INDX="INTERNAL"``):

* ``<AIPos A1=".." .. A6=".."/>``: the axes' actual positions [deg];
* ``<ASPos .../>``: the axes' setpoints [deg] (under RSI correction they stay where
  ``RSI_ON`` found the robot: the reference of the absolute corrections);
* ``<RIst X Y Z A B C/>``: the Cartesian actual pose [mm, deg] (not used here);
* ``<MACur A1 .. A6/>``: the motor currents (the unit ``current_scale_a`` turns into amperes);
* ``<Delay D=".."/>``: the controller's count of late answers;
* ``<IPOC>n</IPOC>``: the cycle's time stamp, which the answer must echo.

The answer ``<Sen Type="ImFree"><AKorr A1=".." .. A6=".."/><IPOC>n</IPOC></Sen>`` carries the
axis correction [deg]: with ``RSI_ON(#ABSOLUTE)`` and ``RSI_MOVECORR()`` it is the target minus
the reference ``ASPos`` (the first ``AIPos`` when the configuration sends no ``ASPos``). The
``Type`` is the ``SENTYPE`` of the controller's configuration (``?sen_type=``). A missing or
late answer is counted by the controller, which stops the robot once its limit is reached.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np

from elastocal.drivers.guidance import ControllerState, Guidance, GuidanceKind
from elastocal.errors import InputError, ProtocolError

#: RSI's robot axes A1..A6 (external axes E1..E6 are another element)
ROBOT_AXES = 6
_DEG = 180.0 / math.pi


def axes(element: ET.Element | None, n: int, what: str) -> np.ndarray | None:
    """The attributes A1..An of ``element`` as floats; None when the element is absent."""
    if element is None:
        return None
    try:
        return np.array([float(element.attrib[f"A{j}"]) for j in range(1, n + 1)])
    except KeyError as exc:
        raise ProtocolError(f"rsi controller: <{what}> has no attribute {exc.args[0]}") from None
    except ValueError as exc:
        raise ProtocolError(f"rsi controller: <{what}>: {exc}") from None


def sen_message(sen_type: str, correction_deg: np.ndarray, ipoc: int) -> bytes:
    """The ``<Sen>`` answer of one cycle (ElementTree escapes the type's text)."""
    root = ET.Element("Sen", {"Type": sen_type})
    ET.SubElement(root, "AKorr", {f"A{j}": f"{v:.6f}" for j, v in enumerate(correction_deg, start=1)})
    ET.SubElement(root, "IPOC").text = str(int(ipoc))
    return ET.tostring(root)


class RsiGuidance(Guidance):
    kind = GuidanceKind.RSI

    def __init__(self, url, *, n_joints: int, source: str = "url") -> None:
        super().__init__(url, n_joints=n_joints, source=source)
        self._reference_deg: np.ndarray | None = None

    def _check_joints(self) -> None:
        if self.n_joints > ROBOT_AXES:
            raise InputError(f"RSI corrects the robot axes A1..A{ROBOT_AXES}; this robot has {self.n_joints} joints "
                             "(external axes are not guided by elastocal)")

    def _decode(self, data: bytes, t_ns: int) -> ControllerState:
        try:
            root = ET.fromstring(data)
        except ET.ParseError as exc:
            raise ProtocolError(f"{self.name}: not XML ({exc})") from None
        if root.tag != "Rob":
            raise ProtocolError(f"{self.name}: <{root.tag}> where <Rob> was expected")
        ipoc_el = root.find("IPOC")
        try:
            ipoc = int((ipoc_el.text or "").strip()) if ipoc_el is not None else None
        except ValueError:
            ipoc = None
        if ipoc is None or ipoc < 0:
            raise ProtocolError(f"{self.name}: <Rob> without a valid <IPOC>")
        n = self.n_joints
        q_deg = axes(root.find("AIPos"), n, "AIPos")
        if q_deg is None:
            raise ProtocolError(f"{self.name}: <Rob> without <AIPos>; declare DEF_AIPos in the RSI configuration")
        setpoint = axes(root.find("ASPos"), n, "ASPos")
        if self._reference_deg is None:
            self._reference_deg = setpoint if setpoint is not None else q_deg.copy()
        cur = axes(root.find("MACur"), n, "MACur")
        delay = root.find("Delay")
        late = 0
        if delay is not None:
            try:
                late = int(float(delay.attrib.get("D", "0")))
            except ValueError:
                raise ProtocolError(f"{self.name}: <Delay D={delay.attrib.get('D')!r}>") from None
        return ControllerState(t_ns=t_ns, sequence=ipoc, q=q_deg / _DEG,
                               currents_a=None if cur is None else cur * self.params.current_scale_a,
                               controller_time_ms=ipoc, late_packets=late)

    @property
    def reference_q(self) -> np.ndarray | None:
        """The joint position the absolute corrections refer to [rad] (known after the first message)."""
        return None if self._reference_deg is None else self._reference_deg / _DEG

    def _encode(self, q_target: np.ndarray, last: ControllerState) -> bytes:
        return sen_message(self.params.sen_type, q_target * _DEG - self._reference_deg, last.sequence)
