"""Safety on the shop floor: what the app writes to the
cell controller, where the simulated devices listen, prompts in a real
terminal, refused load data, device faults and the end of the procedure."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from elastocal.formats.plan import FrictionSpec, LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.acquisition.procedures import run_calibration
from elastocal.drivers import open_controller
from elastocal.drivers.config import PathSpec, parse_cell_config
from elastocal.errors import InputError
from elastocal.sims.modbus_server import ModbusServerThread, SimCellController
from elastocal.sims.serve import SimulatedCell, example_cell_config, example_cell_path
from elastocal.sims.world import SimWorld
from elastocal.sims.config import sim_config
from elastocal.model.kinds import TorqueSource

#: Modbus function codes that change a device's data
WRITE_FUNCTIONS = {5, 6, 15, 16, 22, 23}


def _controller_only_reads_undeclared(text: str) -> str:
    """The packaged cell with ``access = "write"`` kept only where the procedure needs it (not on ``pose``)."""
    line = 'pose     = { address = 2, type = "uint16", access = "write" }'
    assert line in text
    return text.replace(line, 'pose     = { address = 2, type = "uint16" }')


# ------------------------------------------------------------------ item 2: controller registers
def test_controller_registers_are_read_unless_declared_writable():
    text = (example_cell_path().read_text(encoding="utf-8")
            .replace(', access = "write" }', " }"))          # nothing declared writable
    config = parse_cell_config(text, source="cell.toml", base_dir=example_cell_path().parent)
    assert {r.name: r.access for r in config.controller.registers} == {
        name: "read" for name in ("command", "sequence", "pose", "path", "speed", "target", "ack", "status",
                                  "error", "q")}
    # the written config says so again, and reads back the same
    again = parse_cell_config(config.to_toml(), source="again.toml", base_dir=example_cell_path().parent)
    assert again.controller.registers == config.controller.registers

    world = SimWorld.from_config(config.load_robot(), sim_config(config))
    sim = SimCellController(config.controller, world)
    server = ModbusServerThread([sim.device], tcp=("127.0.0.1", 0)).start()
    controller = open_controller(replace(config.controller, url=config.controller.url.with_port(server.port)))
    try:
        assert controller.status().in_position
        for request in (lambda: controller.move_to_pose(2), lambda: controller.move_joints([0.0] * 6),
                        lambda: controller.run(1, "UV")):
            with pytest.raises(InputError, match="not declared writable"):
                request()
        assert sim.writes == []
        assert server.requests and not [r for r in server.requests if r[1] in WRITE_FUNCTIONS]
    finally:
        controller.close()
        server.close()
        sim.close()


def test_a_full_procedure_writes_only_the_registers_declared_writable(tmp_path):
    text = _controller_only_reads_undeclared(example_cell_path().read_text(encoding="utf-8"))
    config = parse_cell_config(text.replace("elastocal-sim", "safety-writes"), source="cell.toml",
                               base_dir=example_cell_path().parent)
    config = replace(config, sim={**config.sim, "move_speed_rad_s": 2.0})
    u, v = (0.1, 0.3, -0.4, 0.0, 0.6, 0.0), (0.25, 0.4, -0.35, 0.05, 0.65, 0.05)
    config = replace(config, controller=replace(config.controller, paths=(PathSpec(1, u, v, 0.1),)))
    controller = config.controller
    assert controller.register("pose").access == "read"
    writable = {a: r.name for r in controller.registers if r.access == "write"
                for a in range(r.address, r.address + r.n_registers)}
    plan = parse_plan(plan_toml(poses=[(0.1, 0.3, -0.4, 0.2, 1.0, 0.1)], loads=(LoadSpec("L1", mass_kg=50.0),),
                                markers=("R1",), repeats=1, reading_s=0.05,
                                friction=(FrictionSpec("F1", start=u, end=v, speeds_rad_s=(0.1,), loads=("0",),
                                                       marker="R1"),),
                                settle=SettleSpec(spread_m=20e-6, window_s=0.15, timeout_s=10.0)))
    with SimulatedCell(config) as sim:
        out = run_calibration(sim.config, plan, tmp_path / "log.mcap", yes=True, world=sim.world)
        assert out.status == "completed"
        (server,) = sim.modbus_servers.values()
        requests = list(server.requests)
    unit = controller.url.int_param("unit", 1)
    writes = [r for r in requests if r[1] in WRITE_FUNCTIONS]
    assert writes and all(r[0] == unit for r in writes)
    written = {writable.get(a, f"undeclared register {a}") for _, _, first, n in writes
               for a in range(first, first + n)}
    # joint moves (target) and the taught path (path, speed), each strobed by command and sequence
    assert written == {"command", "sequence", "target", "path", "speed"}, written


# ------------------------------------------------------------------ item 3: simulated CAN on loopback
def _hex_address(field: str) -> tuple[str, int]:
    """``0100007F:1F90`` of /proc/net/{udp,tcp} -> ("127.0.0.1", 8080)."""
    import socket
    import struct

    addr, port = field.split(":")
    return socket.inet_ntoa(struct.pack("<I", int(addr, 16))), int(port, 16)


def _bound_addresses(pid: int) -> dict[str, list[tuple[str, int]]]:
    """Local addresses of the sockets process ``pid`` holds, per /proc/net table."""
    import os
    import pathlib

    inodes = set()
    for fd in pathlib.Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    found: dict[str, list[tuple[str, int]]] = {}
    for table in ("udp", "tcp", "udp6", "tcp6"):
        for line in pathlib.Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
            fields = line.split()
            if fields[9] in inodes:
                local = _hex_address(fields[1]) if not table.endswith("6") else (fields[1], 0)
                found.setdefault(table, []).append(local)
    return found


def _igmp_groups() -> dict[str, set[str]]:
    """Multicast groups joined per interface (/proc/net/igmp)."""
    import pathlib
    import socket
    import struct

    groups: dict[str, set[str]] = {}
    device = None
    for line in pathlib.Path("/proc/net/igmp").read_text().splitlines()[1:]:
        if not line.startswith((" ", "\t")):
            device = line.split()[1]
            groups.setdefault(device, set())
        else:
            groups[device].add(socket.inet_ntoa(struct.pack("<I", int(line.split()[0], 16))))
    return groups


def test_loopback_can_bus_binds_the_group_joins_on_lo_and_takes_a_free_port():
    import socket

    import can

    from elastocal.drivers.can_loopback import DEFAULT_GROUP, LoopbackUdpBus

    a = LoopbackUdpBus(port=0)
    b = LoopbackUdpBus(port=a.port)
    c = LoopbackUdpBus(port=0)
    try:
        assert a.local_address() == (DEFAULT_GROUP, a.port) and a.port not in (0, 43113)
        assert c.port != a.port                              # another cell: a port of its own
        sock = a._multicast._socket
        assert socket.inet_ntoa(sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, 4)) == "127.0.0.1"
        assert sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 0
        assert DEFAULT_GROUP in _igmp_groups()["lo"]
        assert not [dev for dev, groups in _igmp_groups().items() if dev != "lo" and DEFAULT_GROUP in groups]
        msg = can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False)
        a.send(msg)
        got = b.recv(2.0)
        assert got is not None and got.arbitration_id == 0x181 and bytes(got.data) == b"\x01\x02"
        assert c.recv(0.2) is None                           # the other cell's bus hears nothing
        # a datagram sent to the port on an address of the machine is not delivered
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(b"\x00" * 16, ("127.0.0.1", a.port))
        assert b.recv(0.2) is None
    finally:
        for bus in (a, b, c):
            bus.shutdown()


def test_sim_serve_listens_on_loopback_only_on_ports_of_its_own(tmp_path):
    import os
    import subprocess
    import sys
    import time

    from elastocal.drivers.can_loopback import DEFAULT_GROUP
    from elastocal.drivers.config import load_cell_config

    procs, cells = [], []
    try:
        for i in range(2):
            cell = tmp_path / f"served{i}.toml"
            cells.append(cell)
            procs.append(subprocess.Popen([sys.executable, "-m", "elastocal", "sim", "serve", "--write-cell",
                                           str(cell), "--duration", "60"], stdout=subprocess.PIPE,
                                          stderr=subprocess.PIPE, text=True))
        for p, cell in zip(procs, cells):
            deadline = time.monotonic() + 60
            while not cell.exists() and time.monotonic() < deadline and p.poll() is None:
                time.sleep(0.1)
            assert cell.exists(), p.stderr.read() if p.poll() is not None else "no cell written"
        time.sleep(0.5)
        ports = []
        for p, cell in zip(procs, cells):
            config = load_cell_config(cell)
            urls = {d.url.can_interface for d in config.drives}
            assert urls == {"udp_loopback"}, urls
            # the rate and stall timeout the packaged cell ships (item 5), written into the served config
            assert {(d.rate_hz, d.timeout_s) for d in config.drives} == {(SHIPPED_RATE_HZ, SHIPPED_STALL_S)}
            port = {d.url.int_param("port", 0) for d in config.drives}
            assert len(port) == 1 and port != {0} and port != {43113}
            ports.append(port.pop())
            bound = _bound_addresses(p.pid)
            assert not bound.get("udp6") and not bound.get("tcp6"), bound
            assert bound["udp"] and bound["tcp"], bound
            assert {a for a, _ in bound["tcp"]} == {"127.0.0.1"}, bound
            assert set(bound["udp"]) <= {(DEFAULT_GROUP, ports[-1])}, bound       # never 0.0.0.0
            assert os.path.exists(f"/proc/{p.pid}")
        assert ports[0] != ports[1]
        groups = _igmp_groups()
        assert DEFAULT_GROUP in groups["lo"]
        assert not [dev for dev, g in groups.items() if dev != "lo" and DEFAULT_GROUP in g], groups
        # another process reaches the served drives through the written config
        out = subprocess.run([sys.executable, "-m", "elastocal", "devices", "--cell", str(cells[0]), "--json",
                              "--duration", "1.0"], capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        import json

        streams = {s["device"]: s for s in json.loads(out.stdout)["streams"]}
        assert streams["drive J1"]["received"] > 0
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()


# ------------------------------------------------------------------ item 1: prompts in a real terminal
PROMPT_CHILD = r"""
import sys, threading, time
from elastocal.acquisition.ui import TerminalUI
ui = TerminalUI(sys.stderr)
print("MOVING", file=sys.stderr, flush=True)
time.sleep(1.5)                       # the robot moves; the operator types ahead
def tick():                           # output while the prompt waits (a progress update)
    time.sleep(1.0)
    ui.progress(2, 12, "static pose P3", 70.0, 300.0)
threading.Thread(target=tick, daemon=True).start()
text = "hang load L1, 20 kg, on the load point; step out of the cell"
if sys.argv[1] == "load":
    ui.confirm_load(text, "L1")
else:
    ui.confirm(text)
print("ANSWERED", file=sys.stderr, flush=True)
"""


@pytest.mark.parametrize("mode, answer", [("plain", "yes"), ("load", "L1")])
def test_a_key_pressed_before_the_prompt_never_answers_it(mode, answer, Terminal):
    import sys

    term = Terminal([sys.executable, "-c", PROMPT_CHILD, mode])
    try:
        term.wait_for("MOVING", 60)
        term.type("\n")                       # Enter while the robot moves ...
        term.type(f"{answer}\n")              # ... even the right answer, typed ahead
        at = term.wait_for(">>> hang load L1", 60)
        term.read(2.0)                        # the progress update comes while the prompt waits
        assert "ANSWERED" not in term.screen, term.screen
        progress = term.screen.index("2/12  static pose P3", at)
        assert ">>> hang load L1" in term.screen[progress:], term.screen   # drawn again below the progress
        term.type("\n")                       # a bare Enter after the prompt: not a deliberate answer
        term.wait_for("to go on, or 'a' to abort", 30, progress)
        term.read(0.5)
        assert "ANSWERED" not in term.screen
        term.type(f"{answer}\n")              # the deliberate answer, after the prompt appeared
        term.wait_for("ANSWERED", 30)
        assert term.proc.wait(30) == 0
    finally:
        term.close()


# ------------------------------------------------------------------ item 5: rate, end of the procedure, resume
#: what the packaged simulated cell streams at and how long a drive may stay silent (measured:
#: sims/data/sim_cell.toml); the benchmark keeps 1 kHz
SHIPPED_RATE_HZ, SHIPPED_STALL_S = 250.0, 2.0


def test_the_packaged_cell_ships_a_rate_that_holds_and_the_benchmark_keeps_1khz():
    import pathlib
    import re

    config = example_cell_config()
    assert {(d.rate_hz, d.timeout_s) for d in config.drives} == {(SHIPPED_RATE_HZ, SHIPPED_STALL_S)}
    bench = (pathlib.Path(__file__).parents[1] / "benchmarks" / "bench_devices.py").read_text(encoding="utf-8")
    assert re.search(r'"--rate", type=float, default=1000\.0', bench)

def _virtual_static(n_poses: int = 4):
    import numpy as np

    from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
    from elastocal.formats.robot_toml import bundled_robot
    from elastocal.sims.cell import CellTruth, SimCell
    from elastocal.sims.static import random_poses

    robot = bundled_robot()
    poses = random_poses(robot, n_poses, np.random.default_rng(11))
    plan = parse_plan(plan_toml(poses=poses, loads=(LoadSpec("L1", mass_kg=60.0), LoadSpec("L2", mass_kg=110.0)),
                                markers=("R1", "R2"), repeats=2, reading_s=0.04, speed_rad_s=0.6,
                                settle=SettleSpec(speed_rad_s=2e-3, spread_m=20e-6, window_s=0.15, timeout_s=20.0)),
                      source="plan.toml")

    def io(seed=5):
        return VirtualCellIO(SimCell(robot, CellTruth()), seed=seed,
                             timing=VirtualTiming(drive_rate_hz=250.0, tracker_rate_hz=250.0))

    return plan, io


class _Recording:
    """An automatic operator that records prompts and progress, and may abort at prompt ``abort_at``."""

    def __new__(cls, abort_at=None):
        from elastocal.acquisition.ui import Aborted, AutoUI

        class Recording(AutoUI):
            def __init__(self):
                super().__init__(quiet=True)
                self.shown = []

            def progress(self, done, total, label, elapsed_s, left_s):
                self.shown.append((done, label, elapsed_s, left_s))

            def confirm(self, text):
                super().confirm(text)
                if abort_at is not None and len(self.prompts) == abort_at:
                    raise Aborted(f"aborted by the operator at: {text}")
                return "yes"

        return Recording()


def test_the_procedure_ends_by_asking_to_remove_the_last_load(tmp_path):
    from elastocal.acquisition.logreader import read_log
    from elastocal.acquisition.procedures import run_procedures

    plan, io = _virtual_static(2)
    ui = _Recording()
    cell = io()
    hung = []
    world = cell.world()
    original = world.hang
    world.hang = lambda wrench: (hung.append(wrench), original(wrench))[1]
    cell.world = lambda: world
    assert run_procedures(cell, plan, tmp_path / "log.mcap", ui=ui).status == "completed"
    assert ui.prompts[-1] == "remove load L2 from the load point; step out of the cell"
    assert hung[-1] is None                                  # taken off the simulated world too
    kinds = [(e["kind"], e.get("load"), e.get("text")) for e in read_log(tmp_path / "log.mcap").events]
    last_step = max(i for i, k in enumerate(kinds) if k[0] == "step_done")
    assert [k[0] for k in kinds[last_step + 1:]] == ["standstill", "prompt", "answer", "load", "procedure_end"], \
        kinds[last_step:]
    assert kinds[last_step + 4][1] == "0"


def test_time_left_on_resume_counts_the_steps_already_done(tmp_path):
    from elastocal.acquisition.procedures import run_procedures
    from elastocal.acquisition.steps import build_steps

    plan, io = _virtual_static(4)
    first = _Recording(abort_at=1 + 3 * 2 + 2)              # while hanging L1 at the third pose
    assert run_procedures(io(), plan, tmp_path / "a.mcap", ui=first).status == "aborted"
    left_before = next(left for done, label, _, left in first.shown if done == 2)   # third step begins
    second = _Recording()
    out = run_procedures(io(), plan, tmp_path / "b.mcap", ui=second, resume_from=tmp_path / "a.mcap")
    assert out.status == "completed" and out.steps_resumed == 2
    # before the first step: the resumed steps count as done while it waits for standstill (STANDSTILL_S)
    assert {done for done, label, _, _ in second.shown if label == "starting"} <= {2}
    done, label, elapsed, left_resumed = next(x for x in second.shown if x[1] != "starting")
    assert (done, label) == (2, "static pose P3") and elapsed == pytest.approx(0.0, abs=1.0)
    nominal = sum(s.estimate_s for s in build_steps(plan, ("static",), person_s=0.0)[2:])
    # the steps done before corrected the plan's estimate; the resumed session starts from that correction
    assert left_before < 0.85 * nominal
    assert left_resumed == pytest.approx(left_before, rel=0.1), (left_resumed, left_before, nominal)


def test_a_device_fault_prints_the_log_and_how_to_resume(tmp_path, capsys):
    from elastocal.acquisition.logreader import read_log
    from elastocal.cli import main

    cell = tmp_path / "cell.toml"
    # the tracker drifts (the world's noise holds still within a reading): a cell that never settles this well
    cell.write_text(example_cell_config(can_channel="safety-fault", move_speed_rad_s=2.0,
                                        hidden="thermal_drift").to_toml())
    plan = tmp_path / "plan.toml"       # the settle times out
    plan.write_text(plan_toml(poses=[(0.1, 0.3, -0.4, 0.2, 1.0, 0.1)], loads=(LoadSpec("L1", mass_kg=50.0),),
                              markers=("R1",), settle=SettleSpec(spread_m=1e-12, window_s=0.1, timeout_s=0.5)))
    log = tmp_path / "cal.mcap"
    for extra in ([], ["--json"]):
        rc = main(["calibrate", "--cell", str(cell), "--plan", str(plan), "--out", str(log), "--sim", "--yes",
                   "--force", *extra])
        captured = capsys.readouterr()
        assert rc == 1
        err = captured.err.strip().splitlines()
        if extra:
            obj = json.loads(captured.out)
            assert (obj["log"], obj["status"], obj["steps"], obj["steps_done"]) == (str(log), "failed", 1, 0)
            assert len(err) == 1, err                       # one line, nothing else
        else:
            assert captured.out.strip() == f"log: {log} (0/1 steps, failed)"
        assert err[-1].startswith("elastocal calibrate: DeviceTimeout: the cell did not settle"), err
        assert err[-1].endswith(f"; resume with --resume {log} and a new --out"), err
        contents = read_log(log)
        assert contents.complete and [e["kind"] for e in contents.events][-2:] == ["fault", "procedure_end"]


# ------------------------------------------------------------------ item 4: loads that changed nothing, undetermined k
def _not_hung(table, seed):
    """``table``'s experiment as a cell nobody could load records it: the plan's wrenches in the
    table, the unloaded cell in the measurements."""
    import numpy as np

    from elastocal.formats.robot_toml import bundled_robot
    from elastocal.sims.cell import CellTruth
    from elastocal.sims.static import StaticPlan, simulate_static

    poses = np.array([table.q[table.pose == p][0] for p in dict.fromkeys(table.pose)])
    n_loads = len(set(table.load)) - 1
    empty = simulate_static(bundled_robot(), CellTruth(), seed=seed, poses=poses,
                            wrenches=[np.zeros((n_loads, 6))] * len(poses),
                            plan=StaticPlan(n_poses=len(poses), n_loads=n_loads, repeats=2))
    return replace(empty, wrench=table.wrench)


def test_loads_that_changed_nothing_are_refused_and_real_loads_never(tmp_path, capsys):
    import numpy as np

    from elastocal.cli import main
    from elastocal.identify.evidence import LOADS_ALPHA, load_evidence
    from elastocal.formats.robot_toml import bundled_robot
    from elastocal.identify.static import build_dataset, identify_static
    from elastocal.formats.tables import write_static_table
    from elastocal.sims.cell import CellTruth
    from elastocal.sims.static import StaticPlan, simulate_static

    robot = bundled_robot()
    plan = StaticPlan(n_poses=4, n_loads=2, repeats=2)
    seeds = range(40)
    hung = [simulate_static(robot, CellTruth(), seed=s, plan=plan) for s in seeds]
    refused_real = [s for s, t in zip(seeds, hung) if not load_evidence(build_dataset(t)).changed]
    evidence = [load_evidence(build_dataset(_not_hung(t, 1000 + s))) for s, t in zip(seeds, hung)]
    passed_empty = [s for s, e in zip(seeds, evidence) if e.changed]
    assert refused_real == []                           # real loads: tens of standard deviations
    assert min(load_evidence(build_dataset(t)).max_z for t in hung) > 50
    # no load hung: refused but for the 1 % the chi-square test lets through (binomial, 40 seeds)
    assert len(passed_empty) <= 3, (passed_empty, LOADS_ALPHA)
    assert all(e.quantity == "current" and e.decided and e.n == 4 * 2 * 6 for e in evidence)

    # force-based data without currents: judged by the deflections against the tracker's repeatability
    no_currents = replace(_not_hung(hung[0], 7), currents=np.full_like(hung[0].currents, np.nan))
    ev = load_evidence(build_dataset(no_currents))
    assert ev.quantity == "deflection" and not ev.changed
    with pytest.raises(InputError, match="were they hung"):
        identify_static(robot, no_currents, torque=TorqueSource.FORCE)

    # the command: one line naming the file, exit 2, nothing written
    write_static_table(tmp_path / "static.csv", _not_hung(hung[1], 3))
    (tmp_path / "robot.toml").write_text(robot.to_toml())
    rc = main(["identify", "--robot", str(tmp_path / "robot.toml"), "--static", str(tmp_path / "static.csv"),
               "--out", str(tmp_path / "cal.json")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert f"{tmp_path / 'static.csv'}: the loads did not change the joint torques: were they hung?" in err[0]
    assert not (tmp_path / "cal.json").exists()


def test_a_procedure_whose_loads_nobody_hung_is_refused_by_identify(tmp_path, capsys):
    from elastocal.acquisition.procedures import run_procedures
    from elastocal.cli import main

    plan, io = _virtual_static(3)
    cell = io()
    cell.world = lambda: None                        # nobody can hang a load in this cell
    assert run_procedures(cell, plan, tmp_path / "log.mcap").status == "completed"
    rc = main(["identify", str(tmp_path / "log.mcap")])
    err = capsys.readouterr().err
    assert rc == 2 and "the loads did not change the joint torques: were they hung?" in err, err


def test_a_stiffness_the_data_do_not_determine_is_marked_never_a_finding(tmp_path, capsys):
    from elastocal.cli import main
    from elastocal.formats.calibration import read_calibration
    from elastocal.identify.evidence import stiffness_problem

    assert stiffness_problem(-2e6, 3e6).startswith("negative")
    assert stiffness_problem(2.5e6, 6.2e6).startswith("not determined: its standard deviation is 248 %")
    assert stiffness_problem(559000.0, 500.0) is None
    # two vertical loads per pose cannot load joint 1 (its axis is vertical): k1 is not determined
    assert main(["sim", "static", "--seed", "3", "--poses", "6", "--loads", "2", "--repeats", "2", "--out",
                 str(tmp_path), "--json"]) == 0
    capsys.readouterr()
    tables = ["--robot", str(tmp_path / "robot.toml"), "--static", str(tmp_path / "static.csv")]
    assert main(["identify", *tables, "--json"]) == 0
    params = json.loads(capsys.readouterr().out)["parameters"]
    assert params["k1"]["determined"] is False and "not determined" in params["k1"]["note"]
    assert all("determined" not in params[f"k{j}"] for j in range(2, 7))
    assert main(["identify", *tables]) == 0
    text = capsys.readouterr().out
    k1_line = next(line for line in text.splitlines() if line.strip().startswith("k1"))
    assert "NOT DETERMINED" in k1_line and "k1 not determined by these data: this is not a calibration" in text
    assert f"{params['k1']['value']:.6g}" not in k1_line.split("[")[0]      # no value in the value column
    assert main(["identify", *tables, "--out", str(tmp_path / "cal.json")]) == 0
    captured = capsys.readouterr()
    assert "k1 not determined by these data, marked" in captured.err
    cal = read_calibration(tmp_path / "cal.json")
    assert cal.find("k1").determined is False and cal.find("k2").determined is None
    assert cal.undetermined() == ("k1",) and not cal.find("k1").is_result and cal.find("k2").is_result
    # a compensation with it says so
    from elastocal.compensation.files import write_path
    from elastocal.compensation.ik import yang_path
    from elastocal.formats.robot_toml import load_robot

    write_path(tmp_path / "path.csv", yang_path(load_robot(tmp_path / "robot.toml"), step_m=0.1))
    assert main(["compensate", "--robot", str(tmp_path / "robot.toml"), "--calibration", str(tmp_path / "cal.json"),
                 "--path", str(tmp_path / "path.csv"), "--wrench", "0,0,-1500,0,0,0", "--out",
                 str(tmp_path / "out.csv")]) == 0
    assert f"note: k1 in {tmp_path / 'cal.json'} not determined by the calibration's data" in capsys.readouterr().err


@pytest.mark.heavy
def test_served_cell_rehearsal_calibrates_the_true_stiffness(tmp_path, capsys):
    """The documented rehearsal: `elastocal sim serve --write-cell` in one process, `elastocal
    calibrate` against the written cell in another; the loads confirmed at the prompts hang in the
    served world through its load rig, and the log identifies the simulated cell's stiffness."""
    import subprocess
    import sys
    import time

    import numpy as np

    from elastocal.cli import main
    from elastocal.formats.robot_toml import bundled_robot
    from elastocal.sims.cell import CellTruth
    from elastocal.sims.static import random_poses

    robot = bundled_robot()
    plan = tmp_path / "plan.toml"
    plan.write_text(plan_toml(poses=random_poses(robot, 5, np.random.default_rng(2)),
                              loads=(LoadSpec("L1", mass_kg=110.0), LoadSpec("L2", force_n=(650.0, -300.0, -400.0))),
                              markers=("R1", "R2", "R3"), repeats=2, reading_s=0.05,
                              settle=SettleSpec(spread_m=20e-6, window_s=0.15, timeout_s=20.0)))
    cell = tmp_path / "served.toml"
    serve = subprocess.Popen([sys.executable, "-m", "elastocal", "sim", "serve", "--write-cell", str(cell),
                              "--duration", "600"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not cell.exists() and time.monotonic() < deadline and serve.poll() is None:
            time.sleep(0.1)
        assert cell.exists(), serve.stderr.read() if serve.poll() is not None else "no cell written"
        time.sleep(0.5)
        log = tmp_path / "cal.mcap"
        rc = main(["calibrate", "--cell", str(cell), "--plan", str(plan), "--out", str(log), "--yes", "--json"])
        captured = capsys.readouterr()
        assert rc == 0, captured.err
        assert json.loads(captured.out)["status"] == "completed"
    finally:
        serve.terminate()
        serve.wait(30)
    assert main(["identify", str(log), "--json"]) == 0
    fit = json.loads(capsys.readouterr().out)
    k = np.array([fit["parameters"][f"k{j}"]["value"] for j in range(1, 7)])
    truth = np.array(CellTruth().stiffness)
    err = np.abs(k - truth) / truth
    assert np.all(err[:3] < 0.02) and np.all(err[3:] < 0.05), err
    assert all("determined" not in fit["parameters"][f"k{j}"] for j in range(1, 7))
    assert fit["residual"]["rms"] <= 1.5 * fit["noise_floor"], fit


@pytest.mark.slow
def test_the_operator_rehearses_in_a_terminal_and_stray_keys_answer_nothing(tmp_path, Terminal):
    """`elastocal calibrate` on a terminal against `elastocal sim serve`: an Enter pressed while the
    robot moves never answers the next prompt; typing the load's name (or yes) after it appeared
    does, and the load it names hangs in the served world."""
    import subprocess
    import sys
    import time

    from elastocal.acquisition.logreader import read_log

    plan = tmp_path / "plan.toml"
    plan.write_text(plan_toml(poses=[(0.1, 0.3, -0.4, 0.2, 1.0, 0.1), (0.4, 0.5, -0.3, 0.4, 0.9, 0.3)],
                              loads=(LoadSpec("L1", mass_kg=110.0),), markers=("R1",), repeats=2, reading_s=0.05,
                              settle=SettleSpec(spread_m=20e-6, window_s=0.15, timeout_s=20.0)))
    cell = tmp_path / "served.toml"
    serve = subprocess.Popen([sys.executable, "-m", "elastocal", "sim", "serve", "--write-cell", str(cell),
                              "--duration", "600"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    term = None
    try:
        deadline = time.monotonic() + 60
        while not cell.exists() and time.monotonic() < deadline and serve.poll() is None:
            time.sleep(0.1)
        assert cell.exists()
        log = tmp_path / "rehearsal.mcap"
        term = Terminal([sys.executable, "-m", "elastocal", "calibrate", "--cell", str(cell), "--plan", str(plan),
                         "--out", str(log)])
        answered = 0
        at = 0
        while True:
            try:
                shown = term.wait_for(">>> ", 120, at)
            except AssertionError:
                break                                   # no more prompts: the procedure ended
            if term.proc.poll() is not None:
                break
            end = term.wait_for("(a + Enter aborts): ", 30, shown)
            prompt = term.screen[shown:end]
            term.read(1.0)                              # the prompt waits: nothing moves on
            later = term.screen[end:]
            assert term.proc.poll() is None and "log:" not in later, later
            assert all(p.startswith(prompt[4:]) for p in later.split(">>> ")[1:]), later   # only redrawn
            before = term.screen.count("to go on, or 'a' to abort")
            term.type("\n")                             # a bare Enter: asked again
            deadline = time.monotonic() + 30
            while term.screen.count("to go on, or 'a' to abort") == before and time.monotonic() < deadline:
                term.read(0.1)
            asked = term.screen.rindex("to go on, or 'a' to abort")
            term.wait_for(prompt, 30, asked)                # drawn again
            answer = "L1" if "'L1'" in prompt else "yes"
            term.type(answer + "\n")
            at = term.wait_for(answer + "\r\n", 30, asked) + len(answer) + 2
            answered += 1
            term.type("\n")                             # a stray Enter while the robot moves on
        assert term.proc.wait(120) == 0, term.screen[-2000:]
        assert f"log: {log} (2/2 steps, completed)" in term.screen
    finally:
        if term is not None:
            term.close()
        serve.terminate()
        serve.wait(30)
    events = read_log(log).events
    prompts = [e["text"] for e in events if e["kind"] == "prompt"]
    assert answered == len(prompts) == 1 + 2 * 2 + 1, prompts     # clear; per pose unload + hang; unload at the end
    assert prompts[-1] == "remove load L1 from the load point; step out of the cell"
    assert all(e["answer"] == "yes" and e["automatic"] is False for e in events if e["kind"] == "answer")
