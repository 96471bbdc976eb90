"""All devices of a cell, opened and closed together."""

from __future__ import annotations

from dataclasses import dataclass

from elastocal.drivers import open_controller, open_drive, open_tracker
from elastocal.drivers.base import CellController, Drive, SharedLinks, Tracker, close_all
from elastocal.drivers.config import CellConfig
from elastocal.errors import DeviceError


class CellUnreachable(DeviceError):
    """Devices of a cell that could not be opened, every one of them named (``failed``:
    (name, url, error) per device)."""

    def __init__(self, failed: list[tuple[str, str, DeviceError]], total: int) -> None:
        self.failed = tuple(failed)
        parts = "; ".join(f"{exc}" if str(exc).startswith(name) else f"{name} ({url}): {exc}"
                          for name, url, exc in failed)
        super().__init__(f"{len(failed)} of {total} devices could not be opened: {parts}")


@dataclass
class CellDevices:
    """The open devices of a cell (``with open_cell(config) as cell: ...``).

    ``drives`` maps joint number to :class:`~elastocal.drivers.base.Drive`;
    drives on one CAN channel share one network and SYNC, devices on one
    Modbus endpoint share one connection.
    """

    config: CellConfig
    drives: dict[int, Drive]
    tracker: Tracker | None
    controller: CellController | None
    links: SharedLinks

    @classmethod
    def open(cls, config: CellConfig, *, every_failure: bool = False, on_device=None) -> "CellDevices":
        """Open every device; the first failure is raised, or with ``every_failure`` each
        device is still tried and one :class:`CellUnreachable` names all that failed (a single
        failure is raised as it is).
        ``on_device(name, url, error or None)`` is told of each device as it is tried
        (opening a device that does not answer takes seconds)."""
        links = SharedLinks()
        opened: list = []
        failed: list[tuple[str, str, DeviceError]] = []

        def attempt(opener, device_config):
            try:
                device = opener(device_config, links=links)
            except DeviceError as exc:
                if on_device is not None:
                    on_device(device_config.name, str(device_config.url), exc)
                if not every_failure:
                    raise
                failed.append((device_config.name, str(device_config.url), exc))
                return None
            if on_device is not None:
                on_device(device_config.name, str(device_config.url), None)
            opened.append(device)
            return device

        try:
            drives = {}
            for d in config.drives:
                drive = attempt(open_drive, d)
                if drive is not None:
                    drives[d.joint] = drive
            tracker = attempt(open_tracker, config.tracker) if config.tracker is not None else None
            controller = attempt(open_controller, config.controller) if config.controller is not None else None
            if len(failed) == 1:
                raise failed[0][2]          # one device: its own error, as without every_failure
            if failed:
                total = len(config.drives) + (config.tracker is not None) + (config.controller is not None)
                raise CellUnreachable(failed, total)
        except BaseException:
            try:
                close_all(reversed(opened))
            finally:
                links.close()
            raise
        return cls(config, drives, tracker, controller, links)

    def devices(self) -> list:
        out: list = list(self.drives.values())
        if self.tracker is not None:
            out.append(self.tracker)
        if self.controller is not None:
            out.append(self.controller)
        return out

    def close(self) -> None:
        try:
            close_all(reversed(self.devices()))
        finally:
            self.links.close()

    def __enter__(self) -> "CellDevices":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
