"""Start every simulated device of a cell (the library behind ``elastocal sim serve``).

In Python (tests, the demo, the guided procedure)::

    from elastocal.sims.serve import SimulatedCell, example_cell_config

    with SimulatedCell(example_cell_config()).start() as sim:
        sim.config          # the cell config with the real ports and pty paths
        sim.urls            # {"drive J1": "canopen://virtual/elastocal-sim?node=1", ...}
        sim.world.set_load([0, 0, -1500, 0, 0, 0])   # the operator hangs a load
        with open_cell(sim.config) as cell: ...

CiA 402 drives become canopen ``LocalNode`` s on the config's CAN channel
(``virtual`` in-process; across processes ``udp_loopback``, multicast on the
loopback interface only, on a free UDP port of its own:
:mod:`elastocal.drivers.can_loopback`), Modbus drives and
the cell controller pymodbus servers on 127.0.0.1 (port 0: an ephemeral port)
or on a pseudo-terminal pair (``modbus+rtu``), the tracker a line server on
TCP or on a pseudo-terminal (``tracker+serial``), or an emScon server on
CESAPI's packets (``tracker+emscon``, sims/emscon_server.py). All read one
:class:`~elastocal.sims.world.SimWorld`. Everything started is stopped by
:meth:`SimulatedCell.close` (or the ``with`` block).
"""

from __future__ import annotations

import pathlib
from dataclasses import replace
from importlib import resources
from types import MappingProxyType

from elastocal.drivers.can_loopback import DEFAULT_GROUP as CAN_LOOPBACK_GROUP, INTERFACE as CAN_LOOPBACK
from elastocal.drivers.config import CellConfig, parse_cell_config
from elastocal.drivers.urls import DeviceUrl
from elastocal.errors import InputError
from elastocal.formats.textfiles import read_text_file
from elastocal.sims.canbus import BusStats
from elastocal.sims.canopen_drive import SimCanopenDrive, SimCanopenNetwork
from elastocal.sims.config import sim_config
from elastocal.sims.modbus_server import ModbusServerThread, PtyPair, SimCellController, SimModbusDrive
from elastocal.sims.load_rig import SimLoadRig, rig_identity
from elastocal.sims.tracker_server import SimTracker
from elastocal.sims.world import SimWorld

LOOPBACK = ("127.0.0.1", "localhost")
#: CAN interfaces simulated drives may use: both keep the frames on this machine (python-can's
#: udp_multicast would bind 0.0.0.0 and join on the external interface)
SIM_CAN_INTERFACES = ("virtual", CAN_LOOPBACK)


#: the packaged simulated cells, by the bundled robot they hold
EXAMPLE_CELLS = {"hh150": "sim_cell.toml", "hh150_track": "sim_cell_track.toml", "hh150_urdf": "sim_cell_urdf.toml"}


def example_cell_path(robot: str = "hh150") -> pathlib.Path:
    """The packaged simulated cell of a bundled robot (``sims/data/sim_cell.toml`` for the
    HH-150, ``sim_cell_track.toml`` for the HH-150 on a track)."""
    return pathlib.Path(str(resources.files("elastocal.sims") / "data" / EXAMPLE_CELLS[robot]))


def example_cell_config(*, can_channel: str | None = None, robot: str = "hh150", **sim_overrides) -> CellConfig:
    """The packaged simulated cell (of the bundled ``robot``); ``can_channel`` renames its virtual CAN
    channel (so several simulated cells can run in one process) and
    ``sim_overrides`` replace fields of its ``[sim]`` section."""
    path = example_cell_path(robot)
    config = parse_cell_config(read_text_file(path), source=str(path), base_dir=path.parent)
    if can_channel is not None:
        config = replace(config, drives=tuple(replace(d, url=d.url.with_path(can_channel)) if d.url.scheme == "canopen"
                                              else d for d in config.drives))
    if sim_overrides:
        config = replace(config, sim=MappingProxyType({**config.sim, **sim_overrides}))
    return config


def _endpoint(url: DeviceUrl) -> tuple:
    if url.scheme == "modbus+tcp":
        if url.host not in LOOPBACK:
            raise InputError(f"{url.text}: simulated devices listen on 127.0.0.1 only")
        return ("tcp", url.host, url.port, url.text if url.port == 0 else None)
    return ("rtu", url.path)


class SimulatedCell:
    """All simulated devices of ``config`` (see the module docstring)."""

    def __init__(self, config: CellConfig, *, robot=None, tpdo2: bool = False, load_rig: bool = False) -> None:
        self.source_config = config
        self._with_rig = load_rig          # serve the load rig (sims/load_rig.py): loads from other processes
        self.load_rig: SimLoadRig | None = None
        self._rig_server: ModbusServerThread | None = None
        self.robot = robot if robot is not None else config.load_robot()
        markers = config.tracker.markers if config.tracker is not None else None
        self.sim = sim_config(config)
        self.world = SimWorld.from_config(self.robot, self.sim, markers)
        self._tpdo2 = tpdo2
        self.canopen_drives: dict[int, SimCanopenDrive] = {}
        self.can_networks: dict[tuple[str, str], SimCanopenNetwork] = {}
        self.modbus_drives: dict[int, SimModbusDrive] = {}
        self.modbus_servers: dict[tuple, ModbusServerThread] = {}
        self.controller: SimCellController | None = None
        self.tracker = None             # SimTracker, or SimEmscon for tracker+emscon
        self._ptys: list[PtyPair] = []
        self.config: CellConfig = config
        self._started = False

    # ------------------------------------------------------------- start
    def start(self) -> "SimulatedCell":
        if self._started:
            return self
        self._started = True
        try:
            self._start()
        except BaseException:
            self.close()
            raise
        return self

    def _start(self) -> None:
        cfg = self.source_config
        resolved_drives = {d.joint: d for d in cfg.drives}     # each drive's URL, its ports resolved
        self._start_canopen(resolved_drives)
        controller = self._start_modbus(resolved_drives)
        tracker_cfg = self._start_tracker()

        sim_table = cfg.sim
        if self._with_rig:
            self.load_rig = SimLoadRig(self.world)
            self._rig_server = ModbusServerThread([self.load_rig.device], tcp=("127.0.0.1", 0),
                                                  identity=rig_identity()).start()
            sim_table = MappingProxyType({**cfg.sim, "load_url": f"modbus+tcp://127.0.0.1:{self._rig_server.port}"
                                                                 f"?unit={self.load_rig.unit}"})
        self.config = replace(cfg, drives=tuple(resolved_drives[d.joint] for d in cfg.drives),
                              tracker=tracker_cfg, controller=controller, sim=sim_table)

    def _start_canopen(self, resolved_drives: dict) -> None:
        """The CANopen drives, one network per channel (a loopback's free port into ``resolved_drives``)."""
        cfg = self.source_config
        sim = self.sim
        groups: dict[tuple[str, str, int], list[SimCanopenDrive]] = {}
        for d in cfg.drives:
            if d.url.scheme != "canopen":
                continue
            iface = d.url.can_interface
            if iface not in SIM_CAN_INTERFACES:
                raise InputError(f"{d.url.text}: simulated drives run on {' or '.join(SIM_CAN_INTERFACES)} "
                                 f"(both stay on this machine), not {iface!r}")
            params = d.url.settings         # drivers.url_params.CanopenParams, parsed with the URL
            drive = SimCanopenDrive(params.node, d.joint, self.world, gear_ratio=sim.gear_ratios[d.joint - 1],
                                    serial=1000 + d.joint, tpdo2=self._tpdo2)
            self.canopen_drives[d.joint] = drive
            groups.setdefault((iface, d.url.can_channel, params.bitrate), []).append(drive)
        for (iface, channel, bitrate), drives in groups.items():
            kwargs = {}
            if iface == CAN_LOOPBACK:    # port 0 or none: a free port, written into the resolved URLs
                kwargs["port"] = next((d.url.settings.port for d in cfg.drives
                                       if d.url.scheme == "canopen" and d.url.can_channel == channel
                                       and d.url.settings.port), 0)
            network = SimCanopenNetwork(iface, channel, drives, bitrate=bitrate,
                                        reply_delay_s=sim.can_reply_delay_s, **kwargs)
            self.can_networks[(iface, channel)] = network
            if iface == CAN_LOOPBACK:
                for d in drives:
                    resolved_drives[d.joint] = replace(resolved_drives[d.joint],
                                                       url=resolved_drives[d.joint].url.with_param("port",
                                                                                                   network.port))

    def _start_modbus(self, resolved_drives: dict):
        """The Modbus drives and controller, one server per endpoint (ports and pty paths into
        ``resolved_drives``); the controller's configuration, its URL resolved."""
        cfg = self.source_config
        sim = self.sim
        endpoints: dict[tuple, list] = {}
        for d in cfg.drives:
            if d.url.scheme.startswith("modbus"):
                sd = SimModbusDrive(d, self.world, reply_delay_s=sim.modbus_reply_delay_s)
                self.modbus_drives[d.joint] = sd
                endpoints.setdefault(_endpoint(d.url), []).append(("drive", d.joint, sd.device, d.url))
        if cfg.controller is not None:
            self.controller = SimCellController(cfg.controller, self.world, reply_delay_s=sim.modbus_reply_delay_s)
            endpoints.setdefault(_endpoint(cfg.controller.url), []).append(
                ("controller", 0, self.controller.device, cfg.controller.url))
        new_urls: dict[tuple[str, int], DeviceUrl] = {}
        for key, members in endpoints.items():
            units = [m[2].id for m in members]
            if len(set(units)) != len(units):
                raise InputError(f"two simulated Modbus devices on {members[0][3].text} use one unit id")
            if key[0] == "tcp":
                server = ModbusServerThread([m[2] for m in members], tcp=(key[1], key[2])).start()
                for kind, joint, _, url in members:
                    new_urls[(kind, joint)] = url.with_port(server.port)
            else:
                pair = PtyPair()
                self._ptys.append(pair)
                baud = members[0][3].settings.baud      # ModbusRtuParams, parsed with the URL
                server = ModbusServerThread([m[2] for m in members], serial=pair.device_end, baudrate=baud).start()
                for kind, joint, _, url in members:
                    new_urls[(kind, joint)] = url.with_path(pair.host_end)
            self.modbus_servers[key] = server
        for (kind, joint), url in new_urls.items():
            if kind == "drive":
                resolved_drives[joint] = replace(resolved_drives[joint], url=url)
        controller = cfg.controller
        if controller is not None and ("controller", 0) in new_urls:
            controller = replace(controller, url=new_urls[("controller", 0)])
        return controller

    def _start_tracker(self):
        """The simulated tracker; its configuration, the URL resolved."""
        cfg = self.source_config
        sim = self.sim
        tracker_cfg = cfg.tracker
        if tracker_cfg is not None and tracker_cfg.url.scheme == "tracker+emscon":
            url = tracker_cfg.url
            if url.host not in LOOPBACK:
                raise InputError(f"{url.text}: simulated devices listen on 127.0.0.1 only")
            from elastocal.sims.emscon_server import SimEmscon

            self.tracker = SimEmscon(self.world)
            port = self.tracker.serve_tcp(url.host, url.port or 0)
            tracker_cfg = replace(tracker_cfg, url=url.with_port(port))
        elif tracker_cfg is not None and tracker_cfg.url.scheme not in ("tracker+tcp", "tracker+serial"):
            raise InputError(f"{tracker_cfg.url.text}: the simulated cell serves tracker+tcp, tracker+serial and "
                             "tracker+emscon trackers only")
        elif tracker_cfg is not None:
            self.tracker = SimTracker(self.world, reply_delay_s=sim.tracker_reply_delay_s)
            url = tracker_cfg.url
            if url.scheme == "tracker+tcp":
                if url.host not in LOOPBACK:
                    raise InputError(f"{url.text}: simulated devices listen on 127.0.0.1 only")
                port = self.tracker.serve_tcp(url.host, url.port)
                tracker_cfg = replace(tracker_cfg, url=url.with_port(port))
            else:
                path = self.tracker.serve_pty()
                tracker_cfg = replace(tracker_cfg, url=url.with_path(path))
        return tracker_cfg

    # ------------------------------------------------------------- info
    @property
    def urls(self) -> dict[str, str]:
        """Device name -> resolved URL."""
        out = {d.name: d.url.text for d in self.config.drives}
        if self.config.tracker is not None:
            out["tracker"] = self.config.tracker.url.text
        if self.config.controller is not None:
            out["controller"] = self.config.controller.url.text
        if self._rig_server is not None:
            out["load rig"] = self.config.sim["load_url"]
        return out

    def can_stats(self) -> dict[str, BusStats]:
        """Frames, bits and load of each simulated CAN bus, by ``interface/channel``."""
        return {f"{i}/{c}": n.stats() for (i, c), n in self.can_networks.items()}

    # ------------------------------------------------------------- stop
    def close(self) -> None:
        errors = []
        for closer in ([n.close for n in self.can_networks.values()]
                       + [s.close for s in self.modbus_servers.values()]
                       + ([self._rig_server.close] if self._rig_server is not None else [])
                       + ([self.controller.close] if self.controller is not None else [])
                       + ([self.tracker.close] if self.tracker is not None else [])
                       + [p.close for p in self._ptys]):
            try:
                closer()
            except Exception as exc:  # noqa: BLE001 - re-raised below
                errors.append(exc)
        self.can_networks.clear()
        self.modbus_servers.clear()
        self._rig_server = None
        self._ptys.clear()
        self.controller = None
        self.tracker = None
        if errors:
            raise errors[0]

    def __enter__(self) -> "SimulatedCell":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


# -------------------------------------------------------- across processes
def to_loopback_can(config: CellConfig) -> CellConfig:
    """``config`` with its virtual CAN channels moved to ``udp_loopback``
    (multicast on the loopback interface only, a free UDP port per channel
    chosen when the simulated drives start), so that other processes on this
    machine reach the simulated drives and nothing else does."""
    drives = []
    for d in config.drives:
        if d.url.scheme == "canopen" and d.url.can_interface == "virtual":
            d = replace(d, url=d.url.with_host(CAN_LOOPBACK).with_path(CAN_LOOPBACK_GROUP).with_param("port", 0))
        drives.append(d)
    return replace(config, drives=tuple(drives))
