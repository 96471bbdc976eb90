"""Contract suite of the laser-tracker interface, run against both tracker backends:
the line-protocol tracker (``tracker+tcp``, against sims/tracker_server.py) and the
Leica emScon tracker (``tracker+emscon``, against sims/emscon_server.py on CESAPI's
packets). Tests of one protocol's own bytes (checksums, the pty line, lost lines of
a sequence-numbered stream) run on that backend only; tests/test_drivers_emscon.py
holds the emScon-only ones."""

from __future__ import annotations

import functools
import socket
import time

import numpy as np
import pytest

from elastocal.drivers import open_tracker
from elastocal.drivers.config import TrackerConfig
from elastocal.drivers.urls import parse_device_url
from elastocal.sims.config import SimConfig
from elastocal.drivers.samples import Batch
from elastocal.drivers.tracker_protocol import Measurement, decode_line, encode_line, parse_measurement
from elastocal.errors import DeviceDisconnected, DeviceFault, DeviceTimeout, InputError, ProtocolError
from elastocal.sims.emscon_server import SimEmscon
from elastocal.sims.tracker_server import SimTracker
from elastocal.sims.world import SimWorld
from stream_reading import read_samples

#: these tests run simulated devices in wall-clock time (tests/conftest.py)
pytestmark = pytest.mark.slow

MARKERS = ("R1", "R2", "R3")


@pytest.fixture
def world(robot):
    return SimWorld.from_config(robot, SimConfig(tracker_noise_m=0.0, seed=2), MARKERS)


class Backend:
    """What differs between the backends: the simulator, the URL, who the tracker says it is,
    a stream rate the backend keeps on a loaded machine, the word for a silent stream."""

    def __init__(self, name, make, scheme, identity, rate_hz, silence):
        self.name, self.make, self.scheme = name, make, scheme
        self.identity, self.rate_hz, self.silence = identity, rate_hz, silence

    def url(self, sim):
        return f"{self.scheme}://127.0.0.1:{sim.tcp_port}"


BACKENDS = {
    "line": Backend("line", lambda w: SimTracker(w, serial="SN42"), "tracker+tcp",
                    ("elastocal", "SimTracker", "SN42"), 200.0, "no line"),
    # emScon streams are repeated stationary measurements on the host's clock (drivers/emscon.py)
    "emscon": Backend("emscon", lambda w: SimEmscon(w, serial=42), "tracker+emscon",
                      ("Leica Geosystems (emScon)", "SimAT401", "42"), 100.0, "no result"),
}


@pytest.fixture(params=sorted(BACKENDS))
def backend(request):
    return BACKENDS[request.param]


@pytest.fixture
def sim(world, backend):
    t = backend.make(world)
    t.serve_tcp()
    yield t
    t.close()


@pytest.fixture
def line_sim(world):
    t = BACKENDS["line"].make(world)
    t.serve_tcp()
    yield t
    t.close()


def tracker_for(url: str, **kw):
    cfg = TrackerConfig(url=parse_device_url(url), markers=MARKERS, timeout_s=kw.pop("timeout_s", 0.3),
                        retries=kw.pop("retries", 2), **kw)
    return open_tracker(cfg)


@pytest.fixture
def tracker(sim, backend):
    t = tracker_for(backend.url(sim))
    yield t
    t.close()


@pytest.fixture
def line_tracker(line_sim):
    t = tracker_for(f"tracker+tcp://127.0.0.1:{line_sim.tcp_port}")
    yield t
    t.close()


def xor(body: bytes) -> str:
    return f"{functools.reduce(lambda a, b: a ^ b, body, 0):02X}"


def assert_accounted(samples, gaps, rate):
    """Every hole in the tracker's clock between two samples is a recorded gap."""
    dev = np.array([s.device_time_s for s in samples])
    holes = np.round(np.diff(dev) * rate).astype(int) - 1
    assert np.all(holes >= 0)
    assert holes.sum() == sum(g.missing for g in gaps)


# ---------------------------------------------------------------- protocol
def test_lines_carry_an_xor_checksum():
    assert encode_line("IDN?") == b"IDN?*7C\n"                  # 0x49^0x44^0x4E^0x3F
    assert decode_line(b"OK STOP*" + xor(b"OK STOP").encode() + b"\r\n") == "OK STOP"
    with pytest.raises(ProtocolError, match="checksum"):
        decode_line(b"OK STOP*00\n")
    with pytest.raises(ProtocolError, match="malformed"):
        decode_line(b"OK STOP\n")
    m = Measurement(7, 1500, "R1", (1.0, -2.5, 0.25), "OK")
    assert m.body() == "M 7 1500 R1 1.000000000 -2.500000000 0.250000000 OK"
    assert parse_measurement(m.body()) == m
    with pytest.raises(ProtocolError, match="without a position"):
        parse_measurement("M 7 1500 R1 nan nan nan OK")


def test_byte_level_exchange_with_the_simulated_tracker(line_sim):
    sim = line_sim
    with socket.create_connection(("127.0.0.1", sim.tcp_port), timeout=2.0) as s:
        f = s.makefile("rwb")
        f.write(b"IDN?*7C\n")
        f.flush()
        body = b"IDN elastocal,SimTracker,SN42,0.1.0"
        assert f.readline() == body + b"*" + xor(body).encode() + b"\n"
        f.write(b"TARGET R9\n")                                 # hosts may omit the checksum
        f.flush()
        body = b"ERR 2 unknown target R9"
        assert f.readline() == body + b"*" + xor(body).encode() + b"\n"
        f.write(b"STREAM 5000\n")
        f.flush()
        assert f.readline().startswith(b"ERR 3 rate")


# ------------------------------------------------------------------- reads
def test_measure_gives_the_marker_in_metres(tracker, world, backend):
    info = tracker.identify()
    assert (info.vendor, info.model, info.serial) == backend.identity
    eq = world.equilibrium_at()
    for m in ("R2", "R1"):
        tracker.select(m)
        s = tracker.measure()
        assert s.marker == m
        truth = world.cell.tracker_positions(eq, [m])[0]
        np.testing.assert_allclose(s.tracker_p_marker, truth, atol=1e-9)
    with pytest.raises(InputError, match="unknown marker"):
        tracker.select("R9")


def test_stream_has_consecutive_sequence_and_device_clock(tracker, backend):
    rate = backend.rate_hz
    with tracker.stream(rate) as stream:
        batch = read_samples(stream, int(0.35 * rate))     # a count: a loaded machine takes longer
    seq = np.array([s.seq for s in batch.samples])
    holes = sum(g.missing for g in batch.gaps)
    assert seq[-1] - seq[0] + 1 == len(seq) + holes                        # every slot accounted for
    assert holes <= 0.2 * len(seq)      # a host-paced stream (emScon) records the slots a loaded host missed
    t_ns = np.array([s.t_ns for s in batch.samples])
    assert np.all(np.diff(t_ns) > 0)
    # each sample is stamped on the grid of its slots (tracker-clocked), or within 0.15 s of it (host-paced)
    lag = t_ns - (seq - seq[0]) * 1e9 / rate
    assert np.ptp(lag) < 0.15e9, np.ptp(lag)
    dev = np.array([s.device_time_s for s in batch.samples])
    np.testing.assert_allclose(np.diff(dev), np.diff(seq) / rate, atol=2e-6)
    assert_accounted(batch.samples, batch.gaps, rate)
    stream_last = batch.samples[-1].t_ns
    assert tracker.measure().t_ns > stream_last                            # the stream has stopped


def test_line_stream_is_stamped_with_the_trackers_clock(line_tracker):
    rate = 200.0
    with line_tracker.stream(rate) as stream:
        batch = read_samples(stream, int(0.35 * rate))
    seq = np.array([s.seq for s in batch.samples])
    assert not batch.gaps
    assert np.all(np.diff(seq) == 1)
    t = np.diff([s.t_ns for s in batch.samples])
    # stamped with the tracker's clock, not with the arrival time of the bytes
    assert np.mean(np.abs(t - 1e9 / rate) < 1e3) > 0.75
    dev = np.array([s.device_time_s for s in batch.samples])
    np.testing.assert_allclose(np.diff(dev), 1 / rate, atol=2e-6)
    # a late first read only slews the offset down, by at most half an interval per sample (the mean
    # interval then depends on the machine's load): never a step back, never a longer interval
    offset = np.array([s.t_ns for s in batch.samples]) - np.round(dev * 1e9)
    assert np.all(np.diff(offset) <= 1e3) and np.all(t >= 0.5e9 / rate - 1e3), (offset, t)
    assert line_tracker.measure().seq > seq[-1]                            # the stream has stopped


class LatePeer:
    """A line-protocol tracker on 127.0.0.1 whose first ``late`` lines reach the host in one
    write, ``delay_s`` after the newest of them was measured (what a loaded host that reads
    a backlog at once sees), the rest on time once the test sets ``go`` (it reads the backlog
    first: the lines measured meanwhile are overdue too, and a reader the machine's load held
    back would otherwise take some of them in the backlog's read, whose newest line sets the
    offset). It records the instant of each measurement on the host's monotonic clock (the
    test shares the clock)."""

    def __init__(self, rate_hz: float, lines: int, late: int, delay_s: float) -> None:
        import threading

        self.rate_hz, self.lines, self.late, self.delay_s = rate_hz, lines, late, delay_s
        self.measured_ns: dict[int, int] = {}
        self.go = threading.Event()
        self._server = socket.create_server(("127.0.0.1", 0))
        self.port = self._server.getsockname()[1]
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        conn, _ = self._server.accept()
        with conn, conn.makefile("rb") as lines_in:
            for raw in lines_in:
                words = raw.split(b"*")[0].decode().split()
                if words[0] == "TARGET":
                    conn.sendall(encode_line(f"OK TARGET {words[1]}"))
                elif words[0] == "STREAM":
                    conn.sendall(encode_line(f"OK STREAM {words[1]}"))
                    self._stream(conn)
                elif words[0] == "STOP":
                    conn.sendall(encode_line("OK STOP"))
                    return

    def _stream(self, conn) -> None:
        t0 = time.monotonic_ns()
        period_ns = int(1e9 / self.rate_hz)

        def line(k: int) -> bytes:
            self.measured_ns[k + 1] = t0 + k * period_ns
            return encode_line(Measurement(k + 1, k * period_ns // 1000, "R1", (1.0, 2.0, 0.5), "OK").body())

        time.sleep(((self.late - 1) * period_ns) / 1e9 + self.delay_s)
        conn.sendall(b"".join(line(k) for k in range(self.late)))
        if self.late < self.lines:
            self.go.wait(timeout=30.0)
        for k in range(self.late, self.lines):
            time.sleep(max(0.0, (t0 + k * period_ns - time.monotonic_ns()) / 1e9))
            conn.sendall(line(k))

    def close(self) -> None:
        self._server.close()


def test_a_late_backlog_is_stamped_on_the_trackers_grid():
    """Lines read at once are not stamped with their one receive time (the duplicate t_ns a
    loaded machine showed), and the stamps never step back when later lines arrive faster.

    The lines go through the driver's own reading code (``_on_lines``, the seam between the
    socket and the stamping) with receive times from a virtual clock, so the test checks the
    rule and not how fast this machine reads a socket: six lines measured 5 ms apart arrive in
    one read 40 ms after the newest was measured, the rest 0.3 ms after each."""
    from elastocal.drivers.samples import Stream
    from elastocal.drivers.tracker import _StreamState

    rate, period_ns, t0_ns = 200.0, 5_000_000, 10_000_000_000
    peer = LatePeer(rate, lines=0, late=0, delay_s=0.0)      # only to open the driver; it streams nothing
    tracker = tracker_for(f"tracker+tcp://127.0.0.1:{peer.port}", timeout_s=5.0)
    stream = Stream("tracker", rate, stop=lambda: None)
    tracker._state = _StreamState(stream, rate)
    measured_ns = {}

    def line(k: int) -> bytes:
        measured_ns[k + 1] = t0_ns + k * period_ns
        return encode_line(Measurement(k + 1, k * period_ns // 1000, "R1", (1.0, 2.0, 0.5), "OK").body())

    late, lines = 6, 120
    try:
        tracker._on_lines([line(k) for k in range(late)], t0_ns + (late - 1) * period_ns + 40_000_000)
        for k in range(late, lines):
            tracker._on_lines([line(k)], t0_ns + k * period_ns + 300_000)
        batch = stream.poll()
    finally:
        tracker._state = None
        tracker.close()
        peer.close()
    samples = batch.samples
    assert not batch.gaps and [s.seq for s in samples] == list(range(1, lines + 1))
    t = np.array([s.t_ns for s in samples], dtype=np.int64)
    dt = np.diff(t)
    assert np.all(dt[:late - 1] == period_ns), dt[:late]              # the backlog on the tracker's grid
    assert np.all(dt >= period_ns // 2), dt.min()                     # slewed, never a step back
    delay = t - np.array([measured_ns[s.seq] for s in samples])
    assert np.all(delay >= 0)                                         # never stamped before it was measured
    assert delay[0] >= 40_000_000                                     # the backlog's delay, at first ...
    assert delay[-1] == 300_000                                       # ... slewed out to the smallest one
    # the slew takes at most half an interval per sample: 39.7 ms at 2.5 ms a sample is 16 samples
    assert np.all(dt[late + 20:] == period_ns)


def test_a_late_backlog_over_a_socket_keeps_its_order_and_measurement_times():
    """The same backlog from a peer on 127.0.0.1, read by the driver's thread: whatever the
    machine's load does to the reads, stamps increase, never precede the measurement, and the
    first one carries the backlog's delay (the exact slew is checked on a virtual clock above)."""
    rate, period_ns = 200.0, 5_000_000
    peer = LatePeer(rate, lines=60, late=6, delay_s=0.04)
    tracker = tracker_for(f"tracker+tcp://127.0.0.1:{peer.port}", timeout_s=5.0)
    try:
        with tracker.stream(rate) as stream:
            backlog = read_samples(stream, 6)
            peer.go.set()
            rest = read_samples(stream, 40 - len(backlog.samples))
    finally:
        peer.go.set()
        tracker.close()
        peer.close()
    samples = backlog.samples + rest.samples
    batch = Batch(samples, backlog.gaps + rest.gaps)
    assert not batch.gaps and [s.seq for s in samples] == list(range(1, len(samples) + 1))
    t = np.array([s.t_ns for s in samples], dtype=np.int64)
    assert np.all(np.diff(t) >= period_ns // 2)
    late = t - np.array([peer.measured_ns[s.seq] for s in samples])
    assert np.all(late >= 0) and late[0] >= 0.04e9


def test_serial_tracker_on_a_pty(world):
    sim = SimTracker(world)
    path = sim.serve_pty()
    try:
        t = tracker_for(f"tracker+serial://{path}?baud=115200")
        try:
            s = t.measure()
            truth = world.cell.tracker_positions(world.equilibrium_at(), ["R1"])[0]
            np.testing.assert_allclose(s.tracker_p_marker, truth, atol=1e-9)
            with pytest.raises(InputError, match="115200 baud"):
                t.stream(1000.0)
            with t.stream(100.0) as stream:
                batch = read_samples(stream, 20)
            assert not batch.gaps
        finally:
            t.close()
    finally:
        sim.close()


# ------------------------------------------------------------------ faults
def test_beam_break_is_a_gap_and_a_fault(tracker, sim, backend):
    sim.break_beam(None)
    with pytest.raises(DeviceFault, match="beam broken"):
        tracker.measure()
    sim.restore_beam()
    rate = backend.rate_hz
    with tracker.stream(rate) as stream:
        before = stream.read_for(0.1)
        sim.break_beam(0.1)
        after = stream.read_for(0.35)
    samples = before.samples + after.samples
    gaps = before.gaps + after.gaps
    assert [g.reason for g in gaps] == ["beam broken"]
    assert gaps[0].missing == pytest.approx(0.1 * rate, rel=0.3)
    seq = [s.seq for s in samples]
    assert seq[-1] - seq[0] + 1 == len(seq) + gaps[0].missing            # every measurement accounted for
    assert_accounted(samples, gaps, rate)


def test_lost_and_garbled_lines_are_gaps(line_tracker, line_sim):
    tracker, sim = line_tracker, line_sim
    with tracker.stream(200.0) as stream:
        stream.read_for(0.05)
        sim.drop_lines(3)
        stream.read_for(0.1)
        sim.corrupt_lines(2)
        # until the five are seen and five good lines after them (a loaded machine sends them later)
        got = read_samples(stream, until=lambda got: stream.stats().missing >= 5 and len(got) >= 5)
        first = stream.stats()
    assert first.missing == 5 and sum(g.missing for g in got.gaps) <= 5
    with tracker.stream(200.0) as stream:
        stream.read_for(0.05)
        sim.corrupt_lines(50)
        with pytest.raises(ProtocolError, match="bad lines in a row"):
            for _ in range(20):
                stream.read(timeout_s=1.0)


def test_disconnect_is_resumed_with_a_gap(tracker, sim, backend):
    rate = backend.rate_hz
    with tracker.stream(rate) as stream:
        before = stream.read_for(0.1)
        sim.disconnect_all()
        after = read_samples(stream, int(0.2 * rate) + 1)
    assert sim.connections == 2                      # the driver connected again
    # a host-paced stream (emScon) on a loaded machine also records the requests it sent late
    assert {g.reason for g in after.gaps} <= {"reconnected", "request could not be sent on time"}
    assert_accounted(before.samples + after.samples, before.gaps + after.gaps, rate)
    assert tracker.measure().marker == "R1"


def test_stall_is_a_timeout(tracker, sim, backend):
    s0, w0 = tracker.measure(), time.monotonic()
    sim.stall(2.5)
    with pytest.raises(DeviceTimeout, match="no reply"):
        tracker.measure()                            # 3 attempts of 0.3 s
    # gave up after its attempts (no upper bound on wall-clock time: a loaded machine makes
    # them slower; that they ended in a timeout, not a late answer, shows they beat the stall)
    assert time.monotonic() - w0 > 0.85
    time.sleep(max(0.0, w0 + 2.7 - time.monotonic()))
    w1 = time.monotonic()
    s1 = tracker.measure()                           # a fresh measurement, not a late answer
    assert s1.device_time_s - s0.device_time_s >= w1 - w0 - 0.02
    with tracker.stream(100.0) as stream:
        stream.read_for(0.05)
        sim.stall(1.0)
        with pytest.raises(DeviceTimeout, match=f"{backend.silence} for 0.3 s"):
            for _ in range(20):
                stream.read(timeout_s=1.0)


def test_unreachable_tracker_is_disconnected(sim, backend):
    url = backend.url(sim)
    sim.close()
    with pytest.raises(DeviceDisconnected, match="cannot connect"):
        tracker_for(url, retries=0)
