"""Drives read over Modbus (``modbus+tcp://`` and ``modbus+rtu://``).

The register map of the cell config names where the current and position
(and optionally velocity, torque and a status word) live, their type, scale and
unit. A reading is one Modbus transaction per contiguous block of registers;
a stream polls at its rate from a background thread.

Stream policy: a poll that fails with a timeout, lost connection, garbled
reply or a transient Modbus exception response (4 device failure, 5
acknowledge, 6 device busy, 10/11 gateway) is a recorded gap (the link
reconnects before the next poll); failures lasting longer than
``timeout_s * (retries + 1)`` end the stream with the last error. An exception
response that says the register map is wrong (1 illegal function, 2 illegal
address, 3 illegal value) or a status word with a fault bit ends the stream at once. Polls the loop could not start on time (the device is slower
than the rate) are recorded as gaps too, so ``expected`` always equals the
rate times the duration.
"""

from __future__ import annotations

import threading
import time
from typing import Callable

from elastocal.drivers.base import Drive, ModbusExceptionError, SharedLinks
from elastocal.drivers.samples import DeviceInfo, DriveSample, Stream
from elastocal.drivers.config import DriveConfig
from elastocal.drivers.modbus import ModbusLink
from elastocal.errors import DeviceDisconnected, DeviceError, DeviceFault, DeviceTimeout, ProtocolError


def link_key(url) -> tuple:
    if url.scheme == "modbus+tcp":
        return ("modbus+tcp", url.settings.host, url.settings.port)
    return ("modbus+rtu", url.settings.device)


def acquire_link(url, timeout_s: float, links: SharedLinks | None) -> tuple[ModbusLink, Callable[[], None]]:
    """The Modbus connection of ``url``, shared through ``links`` (a private one
    when None), and the function that gives it back."""
    if links is None:
        own = SharedLinks()
        link = own.acquire(link_key(url), lambda: ModbusLink(url, timeout_s=timeout_s), ModbusLink.close)
        return link, own.close
    key = link_key(url)
    link = links.acquire(key, lambda: ModbusLink(url, timeout_s=timeout_s), ModbusLink.close)
    return link, lambda: links.release(key)


class ModbusDrive(Drive):
    """A joint drive whose values are Modbus registers (see the module docstring)."""

    def __init__(self, config: DriveConfig, *, links: SharedLinks | None = None) -> None:
        super().__init__(config.url, joint=config.joint, timeout_s=config.timeout_s, retries=config.retries,
                         max_current_a=config.max_current_a, max_rate_hz=1000.0)
        self.config = config
        self.unit = config.url.settings.unit
        self.link, self._release_link = acquire_link(config.url, config.timeout_s, links)
        self._status = config.register("status")
        self._poller: threading.Thread | None = None
        self._stop = threading.Event()

    def _reconnect(self) -> None:
        self.link.connect()

    def _identify(self) -> DeviceInfo:
        info = self.link.identify(unit=self.unit)
        self._poll()  # proves the register map reads
        return DeviceInfo(kind="drive", url=self.url.text, vendor=info.get(0, "unknown"),
                          model=info.get(1, "Modbus drive (no device identification)"),
                          revision=info.get(2, ""),
                          details=(("joint", str(self.joint)), ("unit", str(self.unit)),
                                   ("registers", ", ".join(f"{r.name}@{r.address}" for r in self.config.registers))))

    def _poll(self) -> DriveSample:
        t0 = time.monotonic_ns()
        values = self.link.read_specs(self.config.registers, unit=self.unit)
        t1 = time.monotonic_ns()
        status = 0
        if self._status is not None:
            status = int(round(values["status"][0] / self._status.si_factor))
            if status & self._status.fault_mask:
                raise DeviceFault(f"{self.name} (unit {self.unit}): status 0x{status:04X} has a fault bit "
                                  f"(fault_mask 0x{self._status.fault_mask:04X})")
            if self._status.ready_mask and status & self._status.ready_mask != self._status.ready_mask:
                raise DeviceFault(f"{self.name} (unit {self.unit}): status 0x{status:04X} is not ready "
                                  f"(ready_mask 0x{self._status.ready_mask:04X})")
        return DriveSample(
            t_ns=(t0 + t1) // 2, joint=self.joint, position_rad=values["position"][0],
            current_a=values["current"][0],
            velocity_rad_s=values["velocity"][0] if "velocity" in values else None,
            torque_nm=values["torque"][0] if "torque" in values else None, status=status)

    def _read(self) -> DriveSample:
        return self._poll()

    def _stream(self, rate_hz: float) -> Stream[DriveSample]:
        if self._poller is not None and self._poller.is_alive():
            raise DeviceError(f"{self.name} is already streaming")
        self._stop.clear()
        stream: Stream[DriveSample] = Stream(self.name, rate_hz, stop=self._stop_stream)
        self._poller = threading.Thread(target=self._poll_loop, args=(stream, rate_hz),
                                        name=f"modbus-poll-J{self.joint}", daemon=True)
        self._poller.start()
        return stream

    def _poll_loop(self, stream: Stream[DriveSample], rate_hz: float) -> None:
        period_ns = int(round(1e9 / rate_hz))
        give_up_s = self.timeout_s * (self.retries + 1)
        next_ns = time.monotonic_ns()
        last_ok_ns = next_ns
        failing: DeviceError | None = None
        while not self._stop.is_set():
            now = time.monotonic_ns()
            if now < next_ns:
                self._stop.wait((next_ns - now) / 1e9)
                continue
            late = (now - next_ns) // period_ns
            if late:
                stream.gap(int(late), "poll could not start on time (device slower than the rate)",
                           end_ns=now)
            next_ns += period_ns * (late + 1)
            try:
                if isinstance(failing, DeviceDisconnected):
                    self.link.connect()
                sample = self.check_sample(self._poll())
            except ModbusExceptionError as exc:
                if not exc.transient:
                    stream.fail(exc)
                    return
                failing = exc
                stream.gap(1, f"poll failed: {exc}")
                if (time.monotonic_ns() - last_ok_ns) / 1e9 > give_up_s:
                    stream.fail(ModbusExceptionError(f"{exc} (no valid reply for {give_up_s:g} s)", exc.code))
                    return
                continue
            except DeviceFault as exc:
                stream.fail(exc)
                return
            except (DeviceTimeout, DeviceDisconnected, ProtocolError) as exc:
                failing = exc
                stream.gap(1, f"poll failed: {exc}")
                if (time.monotonic_ns() - last_ok_ns) / 1e9 > give_up_s:
                    stream.fail(type(exc)(f"{exc} (no valid reply for {give_up_s:g} s)"))
                    return
                continue
            except DeviceError as exc:
                stream.fail(exc)
                return
            failing = None
            last_ok_ns = sample.t_ns
            stream.emit(sample, sample.t_ns)

    def _stop_stream(self) -> None:
        self._stop.set()
        if self._poller is not None and self._poller is not threading.current_thread():
            self._poller.join(timeout=5.0)
        self._poller = None

    def _close(self) -> None:
        self._stop_stream()
        self._release_link()
