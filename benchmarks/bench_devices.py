"""Stream 6 CANopen drives at 1 kHz and the tracker at 1 kHz from the simulated cell.

Prints, per device, the samples received against the samples expected (the
rate times the streaming time, and what the stream accounts for itself:
received + recorded gaps), what the lost samples were lost to, and the load of
the simulated 1 Mbit/s CAN bus. Target: no sample lost.

The simulated devices run in this process on python-can's ``virtual`` bus,
so the drivers and the simulated devices share one interpreter lock: the
figures are a lower bound of what the drivers do against real devices. The
lost samples are broken down by cause (a SYNC the producer could not send on
time, a TPDO missing from its SYNC cycle, a tracker line lost).

    python benchmarks/bench_devices.py [--duration 60] [--rate 1000] [--tracker-rate 1000]
"""

from __future__ import annotations

import argparse
import sys
import time
import uuid

from elastocal.drivers import open_cell
from elastocal.sims.serve import SimulatedCell, example_cell_config

class _Local:
    def __init__(self) -> None:
        self.sim = SimulatedCell(example_cell_config(can_channel=f"bench-{uuid.uuid4().hex[:6]}")).start()
        self.config = self.sim.config
        (iface, channel), self.net = next(iter(self.sim.can_networks.items()))
        self.name = f"{iface}/{channel}"

    def reset(self) -> None:
        self.net.bus.reset_stats()

    def stats(self):
        return self.net.stats()

    def close(self) -> None:
        self.sim.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=60.0, help="streaming time [s] (default 60)")
    p.add_argument("--rate", type=float, default=1000.0, help="SYNC rate of the drives [Hz] (default 1000)")
    p.add_argument("--tracker-rate", type=float, default=1000.0, help="tracker stream rate [Hz] (default 1000)")
    p.add_argument("--switch-interval", type=float, default=2e-4,
                   help="sys.setswitchinterval of this process [s] (default 2e-4; Python's is 5e-3)")
    args = p.parse_args(argv)
    sys.setswitchinterval(args.switch_interval)

    sims = _Local()
    try:
        with open_cell(sims.config) as cell:
            streams = [(d.name, d.stream(args.rate)) for d in cell.drives.values()]
            streams.append(("tracker", cell.tracker.stream(args.tracker_rate)))
            sims.reset()
            received = {name: 0 for name, _ in streams}
            reasons: dict[str, int] = {}
            errors: dict[str, str] = {}

            def take(name, stream):
                try:
                    batch = stream.poll()
                except Exception as exc:  # noqa: BLE001 - reported below
                    errors.setdefault(name, f"{type(exc).__name__}: {exc}")
                    return
                received[name] += len(batch.samples)
                for g in batch.gaps:
                    reasons[g.reason] = reasons.get(g.reason, 0) + g.missing

            started = time.monotonic()
            try:
                while time.monotonic() - started < args.duration:
                    time.sleep(0.05)
                    for name, s in streams:
                        take(name, s)
            finally:
                bus = sims.stats()
                for _, s in streams:
                    s.close()
                for name, s in streams:
                    take(name, s)
                stats = {name: s.stats() for name, s in streams}
    finally:
        sims.close()

    print(f"{len(cell.drives)} CANopen drives at {args.rate:g} Hz, tracker at {args.tracker_rate:g} Hz, "
          f"{args.duration:g} s, simulated devices in this process")
    print(f"{'device':<10} {'expected':>9} {'accounted':>10} {'received':>9} {'lost':>6} {'gaps':>5}")
    worst = 0
    for name, _ in streams:
        st = stats[name]
        rate = args.tracker_rate if name == "tracker" else args.rate
        expected = int(round(rate * st.elapsed_s))
        in_flight = int(rate * 0.01)      # samples on their way when the stream was closed (10 ms)
        lost = st.missing + max(0, expected - st.expected - in_flight)
        worst = max(worst, lost)
        print(f"{name:<10} {expected:>9d} {st.expected:>10d} {st.received:>9d} {lost:>6d} {st.gaps:>5d}"
              + (f"  {errors[name]}" if name in errors else ""))
    for reason, n in sorted(reasons.items(), key=lambda kv: -kv[1]):
        print(f"  lost to: {n:6d}  {reason}")
    print(f"CAN bus {sims.name}: {bus.frames_per_s:,.0f} frames/s, load {bus.load:.1%} of "
          f"{bus.bitrate / 1e6:g} Mbit/s; TPDOs dropped: {bus.dropped_window} outside the SYNC window, "
          f"{bus.dropped_overrun} on overrun")
    print("result:", "no sample lost" if worst == 0 else f"samples lost (worst device: {worst})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
