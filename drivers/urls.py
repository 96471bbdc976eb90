"""Device URLs: parsed and checked once, here; backends read the parsed :class:`DeviceUrl`.

::

    canopen://virtual/cell?node=5            CiA 402 drive on a python-can bus
    modbus+tcp://127.0.0.1:1502?unit=1       Modbus TCP drive or cell controller
    modbus+rtu:///dev/pts/3?baud=115200&unit=1
    tracker+tcp://127.0.0.1:7000             laser tracker, line protocol over TCP
    tracker+serial:///dev/ttyUSB0?baud=115200
    tracker+emscon://192.168.0.1:700         Leica tracker through its emScon server (port 700 by default)
    egm://0.0.0.0:6510                       ABB EGM: the UDP address elastocal listens on for the controller
    rsi://0.0.0.0:59152?cycle_ms=4           KUKA RSI over Ethernet, likewise
    netft://192.168.1.1                      ATI Net F/T force/torque sensor (RDT, UDP port 49152 by default)

The schemes are those of the backend tables in :mod:`elastocal.drivers` (listed once, there).
The URL is parsed once: the syntax here, then the parameters its backend reads (host, port,
node, unit, baud, ...) by the backend's frozen parameter class (``URL_PARAMS`` there), kept on
the URL as :attr:`DeviceUrl.settings`; the backends read those and parse nothing again.
"""

from __future__ import annotations

import math
import importlib
from dataclasses import dataclass, field, replace
from urllib.parse import parse_qsl, urlsplit

from elastocal.drivers import (
    CONTROLLER_BACKENDS,
    DRIVE_BACKENDS,
    ENTRY_POINT_GROUPS,
    FORCE_BACKENDS,
    GUIDANCE_BACKENDS,
    TRACKER_BACKENDS,
    URL_PARAMS,
    plugin_entry_points,
)
from elastocal.errors import InputError

#: URL schemes per device kind (the keys of the lazy backend tables)
DRIVE_SCHEMES = tuple(DRIVE_BACKENDS)
TRACKER_SCHEMES = tuple(TRACKER_BACKENDS)
CONTROLLER_SCHEMES = tuple(CONTROLLER_BACKENDS)
GUIDANCE_SCHEMES = tuple(GUIDANCE_BACKENDS)
FORCE_SCHEMES = tuple(FORCE_BACKENDS)


# ------------------------------------------------------------------- URLs
@dataclass(frozen=True)
class DeviceUrl:
    """A parsed device URL. ``host`` is the CAN interface for ``canopen``;
    ``path`` the CAN channel, serial device or empty; ``params`` the query."""

    text: str
    scheme: str
    host: str
    port: int | None
    path: str
    params: tuple[tuple[str, str], ...] = ()
    #: what the backend reads from the URL, checked (drivers.url_params and the table
    #: URL_PARAMS); None for an outside package's scheme (its backend checks its own URL)
    settings: object = field(default=None, compare=False, repr=False)

    def param(self, key: str, default: str | None = None) -> str | None:
        for k, v in self.params:
            if k == key:
                return v
        return default

    def int_param(self, key: str, default: int, *, source: str = "url", low: int = 0,
                  high: int = 2**31) -> int:
        raw = self.param(key)
        if raw is None:
            return default
        try:
            value = int(raw, 0)
        except ValueError:
            raise InputError(f"{key}={raw!r} is not an integer in {self.text}", source=source) from None
        if not low <= value <= high:
            raise InputError(f"{key}={value} is outside {low}..{high} in {self.text}", source=source)
        return value

    def float_param(self, key: str, default: float, *, source: str = "url") -> float:
        raw = self.param(key)
        if raw is None:
            return default
        try:
            value = float(raw)
        except ValueError:
            raise InputError(f"{key}={raw!r} is not a number in {self.text}", source=source) from None
        if not math.isfinite(value) or value <= 0:
            raise InputError(f"{key}={raw} must be a positive number in {self.text}", source=source)
        return value

    # --------------------------------------------------------- per scheme
    @property
    def can_interface(self) -> str:
        return self.host

    @property
    def can_channel(self) -> str:
        return self.path.lstrip("/")

    def with_port(self, port: int) -> "DeviceUrl":
        """The same URL with another TCP port (used for ephemeral ports)."""
        query = "&".join(f"{k}={v}" for k, v in self.params)
        text = f"{self.scheme}://{self.host}:{port}{self.path}" + (f"?{query}" if query else "")
        return self._reparsed(replace(self, text=text, port=port))

    def with_path(self, path: str) -> "DeviceUrl":
        """The same URL with another path (serial device or CAN channel)."""
        query = "&".join(f"{k}={v}" for k, v in self.params)
        netloc = self.host + (f":{self.port}" if self.port is not None else "")
        if not path.startswith("/"):
            path = "/" + path
        text = f"{self.scheme}://{netloc}{path}" + (f"?{query}" if query else "")
        return self._reparsed(replace(self, text=text, path=path))

    def with_param(self, key: str, value) -> "DeviceUrl":
        """The same URL with the query parameter ``key`` set to ``value`` (added or replaced)."""
        params = tuple((k, v) for k, v in self.params if k != key) + ((key, str(value)),)
        query = "&".join(f"{k}={v}" for k, v in params)
        netloc = self.host + (f":{self.port}" if self.port is not None else "")
        return self._reparsed(replace(self, text=f"{self.scheme}://{netloc}{self.path}?{query}", params=params))

    def with_host(self, host: str) -> "DeviceUrl":
        query = "&".join(f"{k}={v}" for k, v in self.params)
        netloc = host + (f":{self.port}" if self.port is not None else "")
        text = f"{self.scheme}://{netloc}{self.path}" + (f"?{query}" if query else "")
        return self._reparsed(replace(self, text=text, host=host))

    def __str__(self) -> str:
        return self.text

    def _reparsed(self, changed: "DeviceUrl") -> "DeviceUrl":
        """``changed`` (an address or parameter replaced) with its backend's parameters made anew."""
        return changed if self.settings is None else replace(changed, settings=_settings(changed, "url"))


def parse_device_url(text: str, *, allowed: tuple[str, ...] | None = None,
                     source: str = "url", kind: str | None = None) -> DeviceUrl:
    """Parse and check a device URL (see the module docstring). With ``kind`` ("drive",
    "tracker"), the schemes installed packages register for that kind by entry point are
    allowed too; their URLs are checked by their backend when it opens."""
    if not isinstance(text, str) or "://" not in text:
        raise InputError(f"expected a device URL like modbus+tcp://127.0.0.1:1502?unit=1, got {text!r}",
                         source=source)
    parts = urlsplit(text)
    scheme = parts.scheme.lower()
    known = DRIVE_SCHEMES + TRACKER_SCHEMES + GUIDANCE_SCHEMES + FORCE_SCHEMES
    plugins = plugin_entry_points(kind) if kind is not None and scheme not in known else {}
    if plugins:
        allowed = None if allowed is None else allowed + tuple(sorted(plugins))
        known = known + tuple(plugins)
    if kind is not None and scheme not in known:        # another kind's outside backend?
        known = known + tuple(s for k in ENTRY_POINT_GROUPS if k != kind for s in plugin_entry_points(k))
    if scheme not in known:
        names = sorted(set(known) | set(plugins))
        raise InputError(f"unknown device scheme {scheme!r} in {text}; one of {', '.join(names)}"
                         + (" (outside packages add schemes by entry point, docs/devices.md)" if kind else ""),
                         source=source)
    if allowed is not None and scheme not in allowed:
        raise InputError(f"{scheme}:// cannot be used here; expected one of {', '.join(allowed)}", source=source)
    try:
        port = parts.port
    except ValueError:
        raise InputError(f"bad port in {text}", source=source) from None
    params = tuple(parse_qsl(parts.query, keep_blank_values=True))
    url = DeviceUrl(text=text, scheme=scheme, host=parts.hostname or "", port=port, path=parts.path,
                    params=params)
    if scheme in plugins or scheme not in URL_PARAMS:
        return url                      # the outside package's backend checks its own URL when it opens
    return replace(url, settings=_settings(url, source))


def _settings(url: DeviceUrl, source: str):
    """The backend's parameters of ``url`` (its scheme's class in URL_PARAMS)."""
    module_name, class_name = URL_PARAMS[url.scheme]
    return getattr(importlib.import_module(module_name), class_name).from_url(url, source=source)
