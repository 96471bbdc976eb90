"""Safety on the shop floor (issue 13, items 1-5): what the app writes to the
cell controller, where the simulated devices listen, prompts in a real
terminal, refused load data, device faults and the end of the procedure."""

from __future__ import annotations

from dataclasses import replace

import pytest

from elastocal.acquisition.plan import FrictionSpec, LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.acquisition.procedures import run_calibration
from elastocal.drivers import open_controller
from elastocal.drivers.config import PathSpec, parse_cell_config
from elastocal.errors import InputError
from elastocal.sims.modbus_server import ModbusServerThread, SimCellController
from elastocal.sims.serve import SimulatedCell, example_cell_config, example_cell_path
from elastocal.sims.world import SimWorld

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

    world = SimWorld.from_config(config.load_robot(), config.sim)
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
    config = replace(config, sim=replace(config.sim, move_speed_rad_s=2.0))
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
