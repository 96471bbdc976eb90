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

Each reader runs ``--repeat`` times, in turn (A B C A B C ...), and the medians of the
wall and CPU times are compared, so that the ratios hold when the machine's speed
drifts; the goal is replay >= 0.9 x StreamReader's messages per second.

    python benchmarks/bench_log.py --minutes 5
"""

from __future__ import annotations

import argparse
import math
import pathlib
import statistics
import tempfile
import time

from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader

from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
from elastocal.acquisition.export import load_log
from elastocal.formats.plan import FrictionSpec, SettleSpec, parse_plan, plan_toml
from elastocal.acquisition.procedures import run_procedures
from elastocal.formats.robot_toml import bundled_robot
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


#: the goal: replay at least this fraction of StreamReader's messages per second
GOAL = 0.9


def timed(fn, path) -> tuple[int, float, float]:
    """(what ``fn`` returned, wall s, CPU s of this process)."""
    t0, c0 = time.perf_counter(), time.process_time()
    n = fn(path)
    return n, time.perf_counter() - t0, time.process_time() - c0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=3.0,
                        help="length of the simulated log (default 3: the benchmark finishes in about 2 min)")
    parser.add_argument("--log", help="read this log instead of making one")
    parser.add_argument("--repeat", type=int, default=2, help="runs of each reader, in turn (default 2)")
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
        readers = {"mcap StreamReader (raw records)": raw_stream,
                   "mcap make_reader().iter_messages()": raw_iter,
                   "elastocal load_log (replay to tables)": replay}
        runs: dict[str, list[tuple[int, float, float]]] = {name: [] for name in readers}
        for _ in range(max(1, args.repeat)):
            for name, fn in readers.items():
                runs[name].append(timed(fn, path))
        n_raw = runs["mcap StreamReader (raw records)"][0][0]
        assert n_raw == runs["mcap make_reader().iter_messages()"][0][0]
        rows = runs["elastocal load_log (replay to tables)"][0][0]
        wall = {name: statistics.median(r[1] for r in rs) for name, rs in runs.items()}
        cpu = {name: statistics.median(r[2] for r in rs) for name, rs in runs.items()}
        print(f"file: {size_mb:.1f} MB, {n_raw} messages, {rows} run-table rows; medians of {args.repeat} runs each")
        print(f"{'reader':<42} {'wall s':>8} {'cpu s':>8} {'messages/s':>12}")
        for name in readers:
            print(f"{name:<42} {wall[name]:8.2f} {cpu[name]:8.2f} {n_raw / wall[name]:12.0f}")
        raw, it, rp = readers
        print(f"replay / StreamReader: {wall[raw] / wall[rp]:.2f} (wall), {cpu[raw] / cpu[rp]:.2f} (cpu);   "
              f"replay / iter_messages: {wall[it] / wall[rp]:.2f} (wall), {cpu[it] / cpu[rp]:.2f} (cpu)")
        ratio = wall[raw] / wall[rp]
        print(f"goal: replay >= {GOAL} x StreamReader, same file, same run: {ratio:.2f} "
              f"({'met' if ratio >= GOAL else 'not met'})")
    print(f"benchmark wall time: {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
