"""Log replay throughput next to the raw mcap reader's, on one simulated log.

Records a log of ``--minutes`` (default 3, about two minutes of wall time for the whole
benchmark on 2 cores; ``--minutes 60`` for the one-hour log) of UV/VU friction runs on the
virtual cell (SimCell physics on a virtual clock, so an hour takes minutes to
make): six drives and the tracker at 1 kHz, through the same recorder and
procedure engine as ``elastocal calibrate``. Then reads it back three ways and
prints messages per second:

* ``mcap StreamReader``: mcap's lowest-level reader, every record, chunks
  decompressed, payloads left as bytes;
* ``mcap make_reader().iter_messages()``: mcap's usual message iterator;
* ``elastocal load_log``: the replay ``identify`` and ``export`` use: payloads
  decoded, samples gathered, the run table built.

    python benchmarks/bench_log.py --minutes 5
"""

from __future__ import annotations

import argparse
import math
import pathlib
import tempfile
import time

from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader

from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
from elastocal.acquisition.export import load_log
from elastocal.acquisition.plan import FrictionSpec, SettleSpec, parse_plan, plan_toml
from elastocal.acquisition.procedures import run_procedures
from elastocal.identify.robot import bundled_robot
from elastocal.sims.cell import CellTruth, SimCell

Q_U = (-0.5, 0.2, -0.6, -0.3, 0.4, -0.2)
Q_V = (0.5, 0.5, -0.3, 0.3, 0.7, 0.3)
SPEED_RAD_S = 0.05  # a 1 rad path: 20 s per pass


def make_log(path: pathlib.Path, minutes: float) -> tuple[int, float]:
    robot = bundled_robot()
    pair_s = 2 * 1.0 / SPEED_RAD_S + 1.0
    repeats = max(1, math.ceil(minutes * 60.0 / pair_s))
    friction = (FrictionSpec("F1", start=Q_U, end=Q_V, speeds_rad_s=(SPEED_RAD_S,), repeats=repeats, marker="R1"),)
    plan = parse_plan(plan_toml(poses=[], loads=(), markers=(), friction=friction, speed_rad_s=1.0,
                                settle=SettleSpec(window_s=0.2)))
    io = VirtualCellIO(SimCell(robot, CellTruth()), q0=Q_U, seed=1,
                       timing=VirtualTiming(drive_rate_hz=1000.0, tracker_rate_hz=1000.0, physics_rate_hz=10.0))
    t0 = time.perf_counter()
    run_procedures(io, plan, path, overwrite=True)
    return repeats, time.perf_counter() - t0


def raw_stream(path: pathlib.Path) -> int:
    with open(path, "rb") as f:
        return sum(1 for r in StreamReader(f).records if isinstance(r, Message))


def raw_iter(path: pathlib.Path) -> int:
    with open(path, "rb") as f:
        return sum(1 for _ in make_reader(f).iter_messages(log_time_order=False))


def replay(path: pathlib.Path) -> int:
    robot, static, runs = load_log(path)
    return -1 if runs is None else len(runs)


def timed(fn, path):
    t0 = time.perf_counter()
    n = fn(path)
    return n, time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=3.0,
                        help="length of the simulated log (default 3: the benchmark finishes in about 2 min)")
    parser.add_argument("--log", help="read this log instead of making one")
    args = parser.parse_args()
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        if args.log:
            path = pathlib.Path(args.log)
            print(f"log: {path}")
        else:
            path = pathlib.Path(tmp) / "bench.mcap"
            repeats, make_s = make_log(path, args.minutes)
            print(f"made {args.minutes:g} simulated minutes ({repeats} UV/VU pairs, 6 drives + tracker at 1 kHz) "
                  f"in {make_s:.1f} s")
        size_mb = path.stat().st_size / 1e6
        n_raw, t_raw = timed(raw_stream, path)
        n_iter, t_iter = timed(raw_iter, path)
        rows, t_replay = timed(replay, path)
        assert n_raw == n_iter
        raw_rate, iter_rate, replay_rate = n_raw / t_raw, n_iter / t_iter, n_raw / t_replay
        print(f"file: {size_mb:.1f} MB, {n_raw} messages, {rows} run-table rows")
        print(f"{'reader':<42} {'seconds':>8} {'messages/s':>12}")
        print(f"{'mcap StreamReader (raw records)':<42} {t_raw:8.2f} {raw_rate:12.0f}")
        print(f"{'mcap make_reader().iter_messages()':<42} {t_iter:8.2f} {iter_rate:12.0f}")
        print(f"{'elastocal load_log (replay to tables)':<42} {t_replay:8.2f} {replay_rate:12.0f}")
        print(f"replay / StreamReader: {replay_rate / raw_rate:.2f}   replay / iter_messages: "
              f"{replay_rate / iter_rate:.2f}   (goal: replay >= 0.9 x StreamReader, same file, same run)")
    print(f"benchmark wall time: {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
