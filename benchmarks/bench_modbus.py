"""Modbus poll rate of a drive over TCP (127.0.0.1) and over a pty pair (RTU).

For each link: back-to-back reads for ``--duration`` seconds (polls per second
and the latency of one poll), then a stream at ``--rate`` (samples received
against expected). The drive's register map is one contiguous block (current
and position, int32 each), so one poll is one Modbus transaction.

    python benchmarks/bench_modbus.py [--duration 5] [--rate 200] [--baud 115200]
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import replace

import numpy as np

from elastocal.drivers import open_drive
from elastocal.drivers.config import parse_cell_config
from elastocal.drivers.urls import parse_device_url
from elastocal.sims.config import SimConfig
from elastocal.formats.robot_toml import bundled_robot
from elastocal.sims.modbus_server import ModbusServerThread, PtyPair, SimModbusDrive
from elastocal.sims.world import SimWorld

CELL = """
[cell]
robot = "hh150"
[[drive]]
joint = 2
url = "modbus+tcp://127.0.0.1:0?unit=1"
timeout_s = 0.5
[drive.registers]
current  = { address = 0, type = "int32", scale = 0.001, unit = "A" }
position = { address = 2, type = "int32", scale = 1e-6, unit = "rad" }
"""


def measure(drive, duration_s: float, rate_hz: float) -> dict:
    latencies = []
    end = time.monotonic() + duration_s
    while time.monotonic() < end:
        t0 = time.perf_counter()
        drive.read()
        latencies.append(time.perf_counter() - t0)
    lat = np.array(latencies)
    with drive.stream(rate_hz) as stream:
        stream.read_for(duration_s)
    st = stream.stats()
    return {"polls_per_s": len(lat) / duration_s, "p50_ms": np.percentile(lat, 50) * 1e3,
            "p99_ms": np.percentile(lat, 99) * 1e3, "expected": st.expected,
            "received": st.received, "missing": st.missing, "gaps": st.gaps}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=5.0, help="seconds per measurement (default 5)")
    p.add_argument("--rate", type=float, default=200.0, help="stream rate [Hz] (default 200)")
    p.add_argument("--baud", type=int, default=115200, help="baud rate of the RTU line (default 115200)")
    args = p.parse_args(argv)
    logging.getLogger("pymodbus").addHandler(logging.NullHandler())   # its retries are counted below
    logging.getLogger("pymodbus").propagate = False

    config = parse_cell_config(CELL, source="<bench>").drives[0]
    world = SimWorld.from_config(bundled_robot(), SimConfig())
    sim = SimModbusDrive(config, world)
    rows = []

    server = ModbusServerThread([sim.device], tcp=("127.0.0.1", 0)).start()
    try:
        drive = open_drive(replace(config, url=config.url.with_port(server.port)))
        try:
            rows.append(("modbus+tcp 127.0.0.1", measure(drive, args.duration, args.rate)))
        finally:
            drive.close()
    finally:
        server.close()

    pair = PtyPair()
    server = ModbusServerThread([sim.device], serial=pair.device_end, baudrate=args.baud).start()
    try:
        url = parse_device_url(f"modbus+rtu://{pair.host_end}?baud={args.baud}&unit=1")
        drive = open_drive(replace(config, url=url))
        try:
            rows.append((f"modbus+rtu pty {args.baud} baud", measure(drive, args.duration, args.rate)))
        finally:
            drive.close()
    finally:
        server.close()
        pair.close()

    print(f"{'link':<28} {'polls/s':>8} {'p50 [ms]':>9} {'p99 [ms]':>9}   stream at {args.rate:g} Hz")
    for name, r in rows:
        print(f"{name:<28} {r['polls_per_s']:>8.0f} {r['p50_ms']:>9.2f} {r['p99_ms']:>9.2f}   "
              f"{r['received']} of {r['expected']} samples ({r['missing']} missing in {r['gaps']} gap(s))")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
