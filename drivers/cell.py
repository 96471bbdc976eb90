"""All devices of a cell, opened and closed together."""

from __future__ import annotations

from dataclasses import dataclass

from elastocal.drivers import open_controller, open_drive, open_tracker
from elastocal.drivers.base import CellController, Drive, SharedLinks, Tracker, close_all
from elastocal.drivers.config import CellConfig


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
    def open(cls, config: CellConfig) -> "CellDevices":
        links = SharedLinks()
        opened: list = []
        try:
            drives = {}
            for d in config.drives:
                drives[d.joint] = open_drive(d, links=links)
                opened.append(drives[d.joint])
            tracker = open_tracker(config.tracker, links=links) if config.tracker is not None else None
            if tracker is not None:
                opened.append(tracker)
            controller = open_controller(config.controller, links=links) if config.controller is not None else None
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
