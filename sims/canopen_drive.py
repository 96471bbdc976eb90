"""Simulated CiA 402 drives: canopen ``LocalNode`` s on a timed CAN bus.

Each :class:`SimCanopenDrive` is a ``canopen.LocalNode`` built from the
packaged EDS (``elastocal_drive.eds``): it answers SDO with the live values of
its joint (position 0x6064, velocity 0x606C, torque 0x6077, current 0x6078,
statusword 0x6041, error code 0x603F), runs the CiA 402 state machine on
controlword 0x6040 writes, sends EMCY on a fault, and on every SYNC transmits
its enabled synchronous TPDOs (canopen's LocalNode does not do that by itself:
:class:`SimCanopenNetwork` subscribes to SYNC, takes one
:meth:`~elastocal.sims.world.SimWorld.sample` of the world per SYNC and calls
``PdoMap.transmit()`` for each node).

Units on the wire, as a real drive: position in encoder increments
(0x608F increments per motor revolution, 0x6091 motor revolutions per joint
revolution), velocity in increments/s, current in per-mille of the rated
current 0x6075 (mA), torque in per-mille of the rated motor torque 0x6076 (mN·m).

Fault injection (tests): :meth:`SimCanopenDrive.go_silent`,
:meth:`~SimCanopenDrive.fault`, :meth:`~SimCanopenDrive.send_malformed`,
:meth:`~SimCanopenDrive.disable`.
"""

from __future__ import annotations

import math
import pathlib
import threading
import time
from importlib import resources
from typing import Sequence

import canopen

from elastocal.drivers.can_loopback import INTERFACE as CAN_LOOPBACK, open_can_bus
from elastocal.sims.canbus import BusStats, SimCanBus
from elastocal.sims.world import SimWorld, WorldSample

#: a SYNC's bus time older than this is not taken for the world's clock (a world on another clock)
SYNC_AGE_NS = 50_000_000

#: python-can interfaces that carry frames between processes as UDP datagrams (stamped on arrival,
#: our own frames looped back)
UDP_INTERFACES = ("udp_multicast", CAN_LOOPBACK)

SW_SWITCH_ON_DISABLED = 0x0250
SW_READY_TO_SWITCH_ON = 0x0231
SW_SWITCHED_ON = 0x0233
SW_OPERATION_ENABLED = 0x0237
SW_FAULT = 0x0218


def eds_path() -> pathlib.Path:
    """The packaged EDS file of the simulated drive."""
    return pathlib.Path(str(resources.files("elastocal.sims") / "elastocal_drive.eds"))


class SimCanopenDrive:
    """One simulated CiA 402 drive (node ``node_id``) for joint ``joint`` of ``world``."""

    def __init__(self, node_id: int, joint: int, world: SimWorld, *, gear_ratio: float = 100.0,
                 rated_current_ma: int = 10000, rated_torque_mnm: int = 20000,
                 encoder_increments: int = 2**20, serial: int = 0, tpdo2: bool = False) -> None:
        self.node_id = node_id
        self.joint = joint
        self.world = world
        self.node = canopen.LocalNode(node_id, str(eds_path()))
        self._lock = threading.Lock()
        self._state = SW_OPERATION_ENABLED
        self._error_code = 0
        self._silent_cycles = 0           # SYNCs still to leave unanswered (math.inf: until resume)
        self._malformed = 0
        self._last_controlword = 0
        self.gear_num = int(round(gear_ratio * 100))
        self.gear_den = 100
        self.rated_current_ma = int(rated_current_ma)
        self.rated_torque_mnm = int(rated_torque_mnm)
        self.encoder_increments = int(encoder_increments)
        self.counts_per_rad = self.encoder_increments * self.gear_num / self.gear_den / (2 * math.pi)
        self.gear_ratio = self.gear_num / self.gear_den
        xi = float(world.robot.torque_constants[joint - 1])
        self.torque_constant = xi
        store = self.node.set_data
        store(0x1018, 4, int(serial).to_bytes(4, "little"))
        store(0x6091, 1, self.gear_num.to_bytes(4, "little"))
        store(0x6091, 2, self.gear_den.to_bytes(4, "little"))
        store(0x6075, 0, self.rated_current_ma.to_bytes(4, "little"))
        store(0x6076, 0, self.rated_torque_mnm.to_bytes(4, "little"))
        store(0x608F, 1, self.encoder_increments.to_bytes(4, "little"))
        if tpdo2:
            store(0x1801, 1, (0x280 + node_id).to_bytes(4, "little"))
        self._units = DriveUnits([self])
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)

    # ------------------------------------------------------ fault injection
    def go_silent(self, cycles: int | None = None) -> None:
        """Stop answering SYNC and SDO for the next ``cycles`` SYNCs the drive receives (None:
        until :meth:`resume`). Counted in SYNCs, not seconds: the silence is the same number
        of bus cycles however late a loaded machine runs the threads."""
        with self._lock:
            self._silent_cycles = math.inf if cycles is None else int(cycles)

    def resume(self) -> None:
        with self._lock:
            self._silent_cycles = 0

    def silent(self) -> bool:
        with self._lock:
            return self._silent_cycles > 0

    def fault(self, code: int = 0x2310) -> None:
        """Go to the Fault state and send EMCY ``code`` (0x2310: continuous over-current)."""
        with self._lock:
            self._state = SW_FAULT
            self._error_code = code
        if self.node.has_network():
            self.node.emcy.send(code, 0x01 | 0x02)

    def disable(self) -> None:
        """Leave Operation enabled (as a controller switching the drive off would)."""
        with self._lock:
            self._state = SW_SWITCHED_ON

    def send_malformed(self, count: int = 1) -> None:
        """Truncate the next ``count`` TPDOs to 3 bytes."""
        with self._lock:
            self._malformed += count

    @property
    def statusword(self) -> int:
        with self._lock:
            return self._state

    # ------------------------------------------------------------- values
    def raw_values(self, s: WorldSample) -> dict[int, int]:
        """Object values in drive units for a world sample."""
        values = self._units(s)[0]
        values[STATUS_SLOT] = self.statusword
        return dict(zip(PDO_OBJECTS, values))

    def _on_read(self, index: int, subindex: int, od) -> int | None:
        if index in (0x6041, 0x6064, 0x606C, 0x6077, 0x6078):
            return self.raw_values(self.world.sample())[index]
        if index == 0x603F:
            with self._lock:
                return self._error_code
        return None

    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        if index != 0x6040:
            return
        cw = int.from_bytes(data, "little")
        with self._lock:
            rising_reset = bool(cw & 0x80) and not (self._last_controlword & 0x80)
            self._last_controlword = cw
            if self._state == SW_FAULT:
                if rising_reset:
                    self._state = SW_SWITCH_ON_DISABLED
                    self._error_code = 0
                return
            if cw & 0x82 == 0x00:                      # disable voltage
                self._state = SW_SWITCH_ON_DISABLED
            elif cw & 0x87 == 0x06:                    # shutdown
                self._state = SW_READY_TO_SWITCH_ON
            elif cw & 0x8F == 0x07:                    # switch on / disable operation
                self._state = SW_SWITCHED_ON
            elif cw & 0x8F == 0x0F and self._state in (SW_SWITCHED_ON, SW_OPERATION_ENABLED):
                self._state = SW_OPERATION_ENABLED

    # --------------------------------------------------------------- SYNC
    def prepare_sync(self) -> None:
        """Lay out the enabled synchronous TPDOs as configured (after ``node.tpdo.read()``):
        which value goes to which bytes of ``PdoMap.data``, packed with the
        object's own ``struct`` from the object dictionary."""
        plan = []
        for pdo in self.node.tpdo.map.values():
            if not pdo.enabled or pdo.trans_type is None or not 1 <= pdo.trans_type <= 240:
                continue
            fields = []
            for var in pdo.map:
                if var.index not in _SLOTS:
                    continue                      # left as the PDO's data holds it
                if var.offset % 8 or var.length % 8:
                    raise ValueError(f"node {self.node_id}: TPDO 0x{pdo.cob_id:03X} maps 0x{var.index:04X} "
                                     "off a byte boundary")
                fields.append((_SLOTS[var.index], var.od.STRUCT_TYPES[var.od.data_type].pack_into, var.offset // 8))
            plan.append((pdo, tuple(fields)))
        self._sync_plan = tuple(plan)

    _sync_plan: tuple = ()

    def latch(self, values: list[int]) -> bool:
        """Latch ``values`` (:data:`PDO_OBJECTS` order, from :class:`DriveUnits`;
        the statusword slot is filled here) into the synchronous TPDOs at a
        SYNC; False (nothing latched) while the drive is silent."""
        with self._lock:
            if self._silent_cycles > 0:
                self._silent_cycles -= 1
                return False
            values[STATUS_SLOT] = self._state
        for pdo, fields in self._sync_plan:
            data = pdo.data
            for slot, pack_into, offset in fields:
                pack_into(data, offset, values[slot])
        return True

    def transmit(self, pdo) -> None:
        """Send a latched TPDO (truncated to 3 bytes while :meth:`send_malformed` asks so)."""
        if self._malformed:
            with self._lock:
                truncate = self._malformed > 0
                if truncate:
                    self._malformed -= 1
            if truncate:
                self.node.network.send_message(pdo.cob_id, bytes(pdo.data[:3]))
                return
        pdo.transmit()


#: the objects a synchronous TPDO may carry, in the order of :class:`DriveUnits`
PDO_OBJECTS = (0x6041, 0x6064, 0x606C, 0x6077, 0x6078)
STATUS_SLOT = 0
_SLOTS = {index: slot for slot, index in enumerate(PDO_OBJECTS)}


class DriveUnits:
    """Object values in drive units for world samples, for several drives in one pass.

    ``DriveUnits(drives)(sample)`` gives one list per drive in
    :data:`PDO_OBJECTS` order (statusword 0: the caller fills it): position
    and velocity in increments (/s), torque and current in per-mille of the
    rated values, clamped to int16. (Plain floats: for six drives cheaper than
    numpy's per-call overhead.)"""

    def __init__(self, drives: Sequence[SimCanopenDrive]) -> None:
        self._drives = tuple((d.joint - 1, d.counts_per_rad, d.torque_constant, d.gear_ratio,
                              d.rated_torque_mnm, d.rated_current_ma) for d in drives)

    def __call__(self, s: WorldSample) -> list[list[int]]:
        q, dq, currents = s.q.tolist(), s.dq.tolist(), s.currents_a.tolist()
        rows = []
        for j, counts, xi, gear, rated_torque, rated_current in self._drives:
            current_a = currents[j]
            motor_torque_mnm = xi * current_a / gear * 1000.0
            rows.append([0, round(q[j] * counts), round(dq[j] * counts),
                         max(-32768, min(32767, round(motor_torque_mnm / rated_torque * 1000.0))),
                         max(-32768, min(32767, round(current_a * 1000.0 / rated_current * 1000.0)))])
        return rows


class SimCanopenNetwork:
    """The simulated drives sharing one CAN channel, on a :class:`SimCanBus`."""

    def __init__(self, interface: str, channel: str, drives: Sequence[SimCanopenDrive], *,
                 bitrate: int = 1_000_000, reply_delay_s: float = 50e-6, **bus_kwargs) -> None:
        self.interface = interface
        self.channel = channel
        self.drives = {d.node_id: d for d in drives}
        if len(self.drives) != len(drives):
            raise ValueError("two simulated drives share a node id")
        self.world = drives[0].world if drives else None
        #: wall clock minus the world's clock [s]: CAN timestamps are wall seconds
        self._wall_offset_s = time.time() - time.monotonic()
        if interface == "virtual":
            bus_kwargs.setdefault("preserve_timestamps", True)
        inner = open_can_bus(interface, channel, **bus_kwargs)
        #: the UDP port of a bus across processes (``udp_loopback`` opened with port 0: the kernel's choice)
        self.port: int | None = getattr(inner, "port", bus_kwargs.get("port"))
        delays = {d.node_id: reply_delay_s for d in drives}
        udp = interface in UDP_INTERFACES
        self.bus = SimCanBus(inner, bitrate=bitrate, reply_delay_s=lambda n: delays.get(n, reply_delay_s),
                             filter_own=udp,
                             # over UDP frames are stamped on arrival: deliver each burst as it ends
                             delivery_interval_s=0.0 if udp else SimCanBus.DELIVERY_INTERVAL_S)
        self.network = canopen.Network(self.bus)
        self.network.NOTIFIER_CYCLE = 0.1     # so that closing does not wait a second
        try:
            for d in drives:
                self.network.add_node(d.node)
                d.node.tpdo.read()   # the node's own object values (data store, then EDS)
                d.prepare_sync()
                self._guard_sdo(d)
            self._sync_drives = [d for d in drives if d._sync_plan]
            self._sync_units = DriveUnits(self._sync_drives)
            self._sync_tpdos = sorted(((d, pdo) for d in self._sync_drives for pdo, _ in d._sync_plan),
                                      key=lambda dp: dp[1].cob_id)
            self.network.subscribe(0x80, self._on_sync)
            self.network.connect()
        except BaseException:
            self.bus.shutdown()
            raise

    @staticmethod
    def _guard_sdo(drive: SimCanopenDrive) -> None:
        """Make the SDO server of a silent node drop requests instead of answering."""
        server = drive.node.sdo
        original = server.on_request

        def on_request(can_id, data, timestamp):
            if drive.silent():
                return
            original(can_id, data, timestamp)

        drive.node.network.unsubscribe(server.rx_cobid, original)
        drive.node.network.subscribe(server.rx_cobid, on_request)

    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self.world is None:
            return
        # one world sample and one unit conversion per SYNC for all drives, at the SYNC's time on the bus (the
        # host stamps its cycle just before it): which reading a sample belongs to does not hang on how late
        # this thread runs
        now_ns = self.world.now_ns()
        sync_ns = int(round((timestamp - self._wall_offset_s) * 1e9)) if timestamp else now_ns
        t_ns = sync_ns if 0 <= now_ns - sync_ns < SYNC_AGE_NS else now_ns   # else: not the world's clock
        latched = {d.node_id for d, values in zip(self._sync_drives, self._sync_units(self.world.sample(t_ns)))
                   if d.latch(values)}
        for d, pdo in self._sync_tpdos:          # lowest COB-ID first, as arbitration orders them
            if d.node_id in latched:
                d.transmit(pdo)

    def stats(self) -> BusStats:
        return self.bus.stats()

    def close(self) -> None:
        self.network.disconnect()
