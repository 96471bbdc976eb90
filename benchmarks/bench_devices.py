"""Stream 6 CANopen drives at 1 kHz and the tracker at 1 kHz from the simulated cell.

Prints, per device, the samples received against the samples expected (the
rate times the streaming time, and what the stream itself accounts for:
received + recorded gaps), and the load of the simulated 1 Mbit/s CAN bus.
Target: no sample lost.

    python benchmarks/bench_devices.py [--duration 60] [--rate 1000] [--tracker-rate 1000]
"""

from __future__ import annotations

import argparse
import sys
import time
import uuid

from elastocal.drivers import open_cell
from elastocal.sims.serve import SimulatedCell, example_cell_config


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=60.0, help="streaming time [s] (default 60)")
    p.add_argument("--rate", type=float, default=1000.0, help="SYNC rate of the drives [Hz] (default 1000)")
    p.add_argument("--tracker-rate", type=float, default=1000.0, help="tracker stream rate [Hz] (default 1000)")
    p.add_argument("--switch-interval", type=float, default=2e-4,
                   help="sys.setswitchinterval for this process [s] (default 2e-4; Python's is 5e-3)")
    args = p.parse_args(argv)
    sys.setswitchinterval(args.switch_interval)

    config = example_cell_config(can_channel=f"bench-{uuid.uuid4().hex[:6]}")
    with SimulatedCell(config) as sim, open_cell(sim.config) as cell:
        streams = [(d.name, d.stream(args.rate)) for d in cell.drives.values()]
        streams.append(("tracker", cell.tracker.stream(args.tracker_rate)))
        bus_name, bus = next(iter(sim.can_networks.items()))
        bus.bus.reset_stats()
        received = {name: 0 for name, _ in streams}
        started = time.monotonic()
        try:
            while time.monotonic() - started < args.duration:
                time.sleep(0.05)
                for name, s in streams:
                    received[name] += len(s.poll().samples)
        finally:
            elapsed = time.monotonic() - started
            stats = {name: s.stats() for name, s in streams}
            bus_stats = bus.stats()
            for _, s in streams:
                s.close()
        for name, s in streams:
            received[name] += len(s.poll().samples)

    print(f"{len(cell.drives)} CANopen drives at {args.rate:g} Hz, tracker at {args.tracker_rate:g} Hz, "
          f"{elapsed:.1f} s")
    print(f"{'device':<10} {'expected':>9} {'accounted':>10} {'received':>9} {'lost':>6} {'gaps':>5}  "
          f"{'rate [Hz]':>9}")
    worst = 0
    for name, _ in streams:
        st = stats[name]
        rate = args.tracker_rate if name == "tracker" else args.rate
        expected = int(round(rate * st.elapsed_s))
        lost = max(expected - st.received, 0)
        worst = max(worst, lost)
        print(f"{name:<10} {expected:>9d} {st.expected:>10d} {st.received:>9d} {lost:>6d} {st.gaps:>5d}  "
              f"{st.measured_rate_hz:>9.1f}")
    print(f"CAN bus {bus_name[0]}/{bus_name[1]}: {bus_stats.frames_per_s:,.0f} frames/s, "
          f"load {bus_stats.load:.1%} of {bus_stats.bitrate / 1e6:g} Mbit/s; TPDOs dropped: "
          f"{bus_stats.dropped_window} outside the SYNC window, {bus_stats.dropped_overrun} on overrun")
    print("result:", "no sample lost" if worst == 0 else f"samples lost (worst device: {worst})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
