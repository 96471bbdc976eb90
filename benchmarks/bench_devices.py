"""Stream the simulated cell's CANopen drives at 1 kHz and the tracker at 1 kHz into an MCAP log.

Prints, per device, the samples received against the samples expected (the
rate times the streaming time, and what the stream accounts for itself:
received + recorded gaps; the difference is the edges, samples a device had not
sent yet when the stream started or was closed), what the lost samples were lost to, and the load of
the simulated 1 Mbit/s CAN bus. Everything goes through the recorder into a log
(samples, and a ``gap`` event for every loss the drivers report), which is read
back: the acceptance is that every lost sample is a recorded gap (``unrecorded``
0 on every device), and the fraction of samples kept is printed against the
fraction of 1 kHz deadlines a bare sleeper in another process met in the same
run (the machine's own limit under the load of the moment).

The simulated drives run in this process on python-can's ``virtual`` bus
(across processes, ``udp_loopback`` encodes every frame as a UDP datagram in
Python on both sides and loses far more at 1 kHz: docs/devices.md), so
the drivers and the simulated drives share one interpreter lock: the figures
are a lower bound of what the drivers do against real drives. The simulated
tracker is a TCP server on 127.0.0.1 and runs, as a real tracker would, apart:
in a child process with its own copy of the simulated world (``--tracker-sim
here`` runs it in this process too). The lost samples are broken down by cause
(a SYNC the producer could not send on time, a TPDO missing from its SYNC
cycle, a tracker line lost). The diagnostics say what the run had to work
with: the SYNC producer's punctuality, the CPU time of this process per CAN
frame and per cycle, the load average and the CPU pressure of the machine.

    python benchmarks/bench_devices.py [--duration 20] [--rate 1000] [--tracker-rate 1000]
                                       [--tracker-sim process|here] [--log PATH]
"""

from __future__ import annotations

import contextlib
import argparse
import multiprocessing
import os
import pathlib
import sys
import tempfile
from types import SimpleNamespace
import time
import uuid
from dataclasses import replace

from elastocal.acquisition.logreader import read_log
from elastocal.acquisition.recorder import Recorder
from elastocal.drivers import open_cell
from elastocal.sims.serve import SimulatedCell, example_cell_config


def _cpu_pressure() -> str:
    """``some avg10`` of /proc/pressure/cpu: the share of time a task waited for a CPU."""
    try:
        line = pathlib.Path("/proc/pressure/cpu").read_text().splitlines()[0]
    except (OSError, IndexError):
        return "n/a"
    fields = dict(f.split("=") for f in line.split()[1:])
    return f"{float(fields.get('avg10', 'nan')):.0f}%"


def _probe(conn, rate_hz: float) -> None:
    """Child process: a bare thread sleeping to absolute deadlines at ``rate_hz``
    (nothing else in its interpreter) from the parent's "go" to its "stop".
    Reports how late the machine woke it: the floor under what the SYNC
    producer can do."""
    period_ns = int(round(1e9 / rate_hz))
    lateness = []
    conn.send("ready")
    conn.recv()
    next_ns = time.monotonic_ns() + period_ns
    while not conn.poll():
        now = time.monotonic_ns()
        if now < next_ns:
            time.sleep((next_ns - now) / 1e9)
            now = time.monotonic_ns()
        late = now - next_ns
        lateness.append(late)
        next_ns += period_ns * (1 + late // period_ns)     # deadlines more than a period late are skipped
    lateness.sort()
    n = len(lateness)
    missed = sum(late // period_ns for late in lateness)
    conn.send((n, missed, lateness[n // 2] if n else 0, lateness[int(n * 0.99)] if n else 0,
               lateness[-1] if n else 0))


def _serve_tracker(conn, channel: str) -> None:
    """Child process: the simulated tracker (and nothing else) of the example cell."""
    cfg = example_cell_config(can_channel=channel)
    with SimulatedCell(replace(cfg, drives=(), controller=None)) as sim:
        conn.send(sim.config.tracker)
        with contextlib.suppress(EOFError):    # EOF: the parent went away, which also means stop
            conn.recv()                        # the parent says stop
        conn.send(time.process_time())


class _Sims:
    """The simulated cell: drives (and controller) here, the tracker here or in a child process."""

    def __init__(self, tracker_sim: str) -> None:
        channel = f"bench-{uuid.uuid4().hex[:6]}"
        cfg = example_cell_config(can_channel=channel)
        self._child = self._conn = None
        if tracker_sim == "process":
            ctx = multiprocessing.get_context("spawn")
            self._conn, child_end = ctx.Pipe()
            self._child = ctx.Process(target=_serve_tracker, args=(child_end, channel), daemon=True,
                                      name="sim-tracker")
            self._child.start()
            while not self._conn.poll(0.2):
                if not self._child.is_alive():
                    raise RuntimeError(f"the simulated tracker process exited (code {self._child.exitcode})")
            tracker = self._conn.recv()
            self.sim = SimulatedCell(replace(cfg, tracker=None)).start()
            self.config = replace(self.sim.config, tracker=tracker)
        else:
            self.sim = SimulatedCell(cfg).start()
            self.config = self.sim.config
        (iface, channel), self.net = next(iter(self.sim.can_networks.items()))
        self.name = f"{iface}/{channel}"
        self.child_cpu_s: float | None = None

    def reset(self) -> None:
        self.net.bus.reset_stats()

    def stats(self):
        return self.net.stats()

    def close(self) -> None:
        try:
            self.sim.close()
        finally:
            if self._child is not None:
                with contextlib.suppress(OSError, EOFError):   # a child already gone has no CPU figure
                    self._conn.send("stop")
                    if self._conn.poll(10.0):
                        self.child_cpu_s = self._conn.recv()
                self._child.join(timeout=10.0)
                if self._child.is_alive():
                    self._child.kill()


def _report(args: argparse.Namespace, sims, run: SimpleNamespace) -> int:
    """Print what the run measured; 0 when every lost sample is a recorded gap."""
    where = ("simulated drives in this process, simulated tracker in a child process"
             if args.tracker_sim == "process" else "simulated devices in this process")
    print(f"{run.n_drives} CANopen drives at {args.rate:g} Hz, tracker at {args.tracker_rate:g} Hz, "
          f"{args.duration:g} s, {where}")
    print(f"{'device':<10} {'expected':>9} {'accounted':>10} {'received':>9} {'lost':>6} {'gaps':>5} "
          f"{'in log':>8} {'gap in log':>10} {'unrecorded':>10} {'kept':>7}")
    worst = 0
    unrecorded_all = 0
    kept = []
    for name in run.names:
        st = run.stats[name]
        rate = args.tracker_rate if name == "tracker" else args.rate
        expected = int(round(rate * st.elapsed_s))
        in_flight = int(rate * 0.01)      # samples on their way when the stream was closed (10 ms)
        lost = st.missing + max(0, expected - st.expected - in_flight)
        worst = max(worst, lost)
        in_log, gap_in_log = run.logged[name]
        # lost without a gap event saying so: what the stream accounts for (received + the gaps it
        # reported: SYNC cycles for the drives, sequence numbers for the tracker) against the log
        unrecorded = max(0, st.expected - in_log - gap_in_log)
        unrecorded_all += unrecorded
        kept.append(in_log / max(expected, 1))
        print(f"{name:<10} {expected:>9d} {st.expected:>10d} {st.received:>9d} {lost:>6d} {st.gaps:>5d} "
              f"{in_log:>8d} {gap_in_log:>10d} {unrecorded:>10d} {kept[-1]:>7.2%}"
              + (f"  {run.errors[name]}" if name in run.errors else ""))
    for reason, n in sorted(run.reasons.items(), key=lambda kv: -kv[1]):
        print(f"  lost to: {n:6d}  {reason}")
    bus, sync, cpu_s, wall_s = run.bus, run.sync, run.cpu_s, run.wall_s
    print(f"CAN bus {sims.name}: {bus.frames_per_s:,.0f} frames/s, load {bus.load:.1%} of "
          f"{bus.bitrate / 1e6:g} Mbit/s; TPDOs dropped: {bus.dropped_window} outside the SYNC window, "
          f"{bus.dropped_overrun} on overrun")
    print(f"SYNC: {sync.sent} sent, {sync.not_sent} not sent (producer more than a period late), "
          f"{sync.late} sent more than a tenth of a period late; lateness mean "
          f"{sync.mean_lateness_s * 1e6:.0f} us, max {sync.max_lateness_s * 1e3:.2f} ms")
    cycles = max(sync.sent, 1)
    print(f"CPU: this process {cpu_s:.1f} s in {wall_s:.1f} s ({cpu_s / wall_s:.0%} of a core), "
          f"{cpu_s / cycles * 1e6:.0f} us per SYNC cycle, {cpu_s / max(bus.frames, 1) * 1e6:.0f} us per CAN frame"
          + (f"; tracker process {sims.child_cpu_s:.1f} s in all" if sims.child_cpu_s is not None else ""))
    if run.woke is not None:
        n, missed, p50, p99, worst_ns = run.woke
        print(f"wake-up probe (a bare thread in another process sleeping to the same deadlines): "
              f"{missed} of {n + missed} deadlines missed by more than a period ({missed / max(n + missed, 1):.2%}); "
              f"lateness median {p50 / 1e3:.0f} us, 99th percentile {p99 / 1e3:.0f} us, max {worst_ns / 1e6:.1f} ms")
    print(f"machine: {os.cpu_count()} CPUs, load average {run.load_before[0]:.2f} -> {run.load_after[0]:.2f}, "
          f"CPU pressure (time some task waited for a CPU, last 10 s) {run.pressure}")
    if run.woke is not None:
        met = n / max(n + missed, 1)
        print(f"kept against the bare sleeper: worst device {min(kept):.2%} of its samples in the log, the sleeper "
              f"met {met:.2%} of its deadlines: ratio {min(kept) / max(met, 1e-9):.3f} (1.000: as good as this "
              "machine allowed a thread that does nothing else)")
    print("result:", "no sample lost" if worst == 0 else f"samples lost (worst device: {worst})",
          "; every lost sample is a recorded gap" if unrecorded_all == 0 else
          f"; {unrecorded_all} samples lost WITHOUT a recorded gap")
    return 0 if unrecorded_all == 0 else 1


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=20.0, help="streaming time [s] (default 20)")
    p.add_argument("--rate", type=float, default=1000.0, help="SYNC rate of the drives [Hz] (default 1000)")
    p.add_argument("--tracker-rate", type=float, default=1000.0, help="tracker stream rate [Hz] (default 1000)")
    p.add_argument("--tracker-sim", choices=("process", "here"), default="process",
                   help="run the simulated tracker in a child process (default) or in this process")
    p.add_argument("--no-probe", dest="probe", action="store_false",
                   help="do not run the wake-up probe (a bare 1 kHz sleeper in a child process that "
                        "measures how late this machine wakes threads during the run)")
    p.add_argument("--log", help="the MCAP log to record into (default: a temporary file, removed)")
    p.add_argument("--switch-interval", type=float, default=2e-4,
                   help="sys.setswitchinterval of this process [s] (default 2e-4; Python's is 5e-3)")
    args = p.parse_args(argv)
    return args


def _start_probe(rate: float):
    """(process, pipe) of the wake-up probe, started first so that its imports are done before streaming."""
    ctx = multiprocessing.get_context("spawn")
    probe_conn, child_end = ctx.Pipe()
    probe = ctx.Process(target=_probe, args=(child_end, rate), daemon=True, name="wake-probe")
    probe.start()
    probe_conn.recv()
    return probe, probe_conn


def main(argv: list[str] | None = None) -> int:
    args = _arguments(argv)
    sys.setswitchinterval(args.switch_interval)

    woke = None
    probe, probe_conn = _start_probe(args.rate) if args.probe else (None, None)
    sims = _Sims(args.tracker_sim)
    tmp = None
    if args.log is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench-devices-")
    log_path = pathlib.Path(args.log) if args.log else pathlib.Path(tmp.name) / "bench.mcap"
    try:
        with open_cell(sims.config) as cell, Recorder(log_path, overwrite=True) as rec:
            link = next(iter(cell.drives.values())).link
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
                for x in batch.samples:
                    if name == "tracker":
                        rec.tracker_sample(x.t_ns, x.marker, x.tracker_p_marker)
                    else:
                        rec.drive_sample(x.joint, x.t_ns, x.position_rad, x.velocity_rad_s, x.current_a, x.status)
                for g in batch.gaps:
                    reasons[g.reason] = reasons.get(g.reason, 0) + g.missing
                    rec.event("gap", device=name, window_ns=[g.start_ns, g.end_ns], missing=g.missing, text=g.reason)

            if probe is not None:
                probe_conn.send("go")
            load_before = os.getloadavg()
            cpu_before = time.process_time()
            started = time.monotonic()
            try:
                while time.monotonic() - started < args.duration:
                    time.sleep(0.05)
                    for name, s in streams:
                        take(name, s)
            finally:
                cpu_s = time.process_time() - cpu_before
                wall_s = time.monotonic() - started
                load_after = os.getloadavg()
                pressure = _cpu_pressure()
                bus = sims.stats()
                sync = link.sync_stats()
                if probe is not None:
                    probe_conn.send("stop")
                    woke = probe_conn.recv() if probe_conn.poll(10.0) else None
                    probe.join(timeout=10.0)
                for _, s in streams:
                    s.close()
                for name, s in streams:
                    take(name, s)
                stats = {name: s.stats() for name, s in streams}
        logged = _logged(log_path, [name for name, _ in streams])
    finally:
        try:
            sims.close()
        finally:
            if probe is not None and probe.is_alive():
                probe.kill()
            if tmp is not None:
                tmp.cleanup()

    run = SimpleNamespace(n_drives=len(cell.drives), names=[name for name, _ in streams], stats=stats, logged=logged,
                          errors=errors, reasons=reasons, bus=bus, sync=sync, cpu_s=cpu_s, wall_s=wall_s,
                          woke=woke if probe is not None else None, load_before=load_before, load_after=load_after,
                          pressure=pressure)
    return _report(args, sims, run)


def _logged(path: pathlib.Path, names: list[str]) -> dict[str, tuple[int, int]]:
    """Per device: (samples in the log, samples its gap events say were lost)."""
    contents = read_log(path)
    out = {}
    for name in names:
        if name == "tracker":
            n = sum(len(m.t_ns) for m in contents.markers.values())
        else:
            n = len(contents.drives[int(name.removeprefix("drive J")) - 1].t_ns)
        gaps = sum(int(e.get("missing", 0)) for e in contents.events if e["kind"] == "gap" and e.get("device") == name)
        out[name] = (n, gaps)
    return out


if __name__ == "__main__":
    raise SystemExit(main())
