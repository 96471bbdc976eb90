"""`elastocal devices --cell cell.toml`: connect, identify, stream live readings (docs/devices.md)."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time

from elastocal.errors import InputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cell", required=True, help="cell.toml naming the devices (docs/cell-config.md)")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stream for S seconds (default: until Ctrl-C; 2 s with --json)")
    parser.add_argument("--identify-only", action="store_true", help="identify the devices, do not stream")
    parser.add_argument("--every", type=float, default=1.0, metavar="S",
                        help="print the live readings every S seconds (default 1)")
    parser.add_argument("--json", action="store_true",
                        help="print exactly one JSON object on stdout")


def _quiet_libraries() -> None:
    # pymodbus and canopen log their retries; the typed errors carry what matters
    for name in ("pymodbus", "canopen", "can"):
        logging.getLogger(name).addHandler(logging.NullHandler())
        logging.getLogger(name).propagate = False


def _info_dict(info) -> dict:
    return {"kind": info.kind, "url": info.url, "vendor": info.vendor, "model": info.model,
            "serial": info.serial, "revision": info.revision, "details": dict(info.details)}


def _last(sample) -> dict:
    if sample is None:
        return {}
    if hasattr(sample, "current_a"):
        out = {"t_ns": sample.t_ns, "position_rad": sample.position_rad, "current_a": sample.current_a,
               "status": sample.status}
        if sample.velocity_rad_s is not None:
            out["velocity_rad_s"] = sample.velocity_rad_s
        if sample.torque_nm is not None:
            out["torque_nm"] = sample.torque_nm
        return out
    return {"t_ns": sample.t_ns, "seq": sample.seq, "marker": sample.marker,
            "tracker_p_marker": list(sample.tracker_p_marker)}


def _line(name: str, sample, stats) -> str:
    rate = f"{stats.measured_rate_hz:7.1f} Hz"
    lost = f"lost {stats.missing}/{stats.expected}" + (f" in {stats.gaps} gap(s)" if stats.gaps else "")
    if sample is None:
        return f"  {name:<10} (no sample yet)  {rate}  {lost}"
    if hasattr(sample, "current_a"):
        extra = ""
        if sample.velocity_rad_s is not None:
            extra += f"  dq={sample.velocity_rad_s:+.5f} rad/s"
        if sample.torque_nm is not None:
            extra += f"  tau={sample.torque_nm:+.1f} N*m"
        return (f"  {name:<10} q={sample.position_rad:+.6f} rad  i={sample.current_a:+8.3f} A{extra}  "
                f"{rate}  {lost}")
    x, y, z = sample.tracker_p_marker
    return (f"  {name:<10} {sample.marker}=({x:+.6f}, {y:+.6f}, {z:+.6f}) m  seq {sample.seq}  "
            f"{rate}  {lost}")


def _identify(cell, quiet: bool) -> list[dict]:
    """Each device's identity (vendor, model, serial, ...), printed unless ``quiet``."""
    found = []
    for device in cell.devices():
        info = device.identify()
        found.append({"name": device.name, **_info_dict(info)})
        if not quiet:
            print(f"{device.name:<10} {info.url}")
            print(f"{'':<10} {info.vendor} {info.model} serial {info.serial or '-'} rev {info.revision or '-'}")
            for k, v in info.details:
                print(f"{'':<10} {k}: {v}")
    return found


def _watch(streams, duration: float, every: float | None):
    """Poll the streams for ``duration`` s (until Ctrl-C or a device's error), printing each
    stream's last sample every ``every`` s (None: silent); (last sample per stream, the error)."""
    from elastocal.errors import DeviceError

    last: dict[str, object] = {name: None for name, _ in streams}
    error: DeviceError | None = None
    start = time.monotonic()
    next_print = start + (every or 0.0)
    try:
        while time.monotonic() - start < duration and error is None:
            time.sleep(min(0.05, max(0.0, duration - (time.monotonic() - start))))
            for name, stream in streams:
                try:
                    batch = stream.poll()
                except DeviceError as exc:
                    error = exc
                    break
                if batch.samples:
                    last[name] = batch.samples[-1]
            if every is not None and time.monotonic() >= next_print:
                next_print += every
                print(f"[{time.monotonic() - start:6.1f} s]")
                for name, stream in streams:
                    print(_line(name, last[name], stream.stats()))
                sys.stdout.flush()
    except KeyboardInterrupt:     # Ctrl-C ends the watch: the last readings are still reported
        return last, error
    return last, error


def run(args: argparse.Namespace) -> int:
    from elastocal.drivers.cell import CellDevices
    from elastocal.drivers.config import load_cell_config
    from elastocal.errors import DeviceError

    if args.duration is not None and not args.duration > 0:
        raise InputError(f"must be > 0, got {args.duration}", source="--duration")
    if not args.every > 0:
        raise InputError(f"must be > 0, got {args.every}", source="--every")
    duration = args.duration if args.duration is not None else (2.0 if args.json else math.inf)
    _quiet_libraries()
    config = load_cell_config(args.cell)
    out: dict = {"cell": config.name, "devices": [], "streams": []}
    def opened(name: str, url: str, error) -> None:      # progress: a device that does not answer takes seconds
        if not args.json:
            print(f"  {name:<10} {url}: {'ok' if error is None else 'FAILED'}", flush=True)

    if not args.json:
        print(f"opening the devices of {config.name} ...", flush=True)
    with CellDevices.open(config, every_failure=True, on_device=opened) as cell:    # a dead cell: all named
        names = [d.name for d in cell.devices()]
        out["devices"] = _identify(cell, args.json)
        if args.identify_only:
            if args.json:
                print(json.dumps(out))
            return 0
        streams = []
        try:
            for joint, drive in cell.drives.items():
                streams.append((drive.name, drive.stream(config.drive(joint).rate_hz)))
            if cell.tracker is not None:
                streams.append(("tracker", cell.tracker.stream(config.tracker.rate_hz)))
            last, error = _watch(streams, duration, None if args.json else args.every)
            for name, stream in streams:
                st = stream.stats()
                out["streams"].append({"device": name, "rate_hz": st.rate_hz, "received": st.received,
                                       "expected": st.expected, "missing": st.missing, "gaps": st.gaps,
                                       "measured_rate_hz": st.measured_rate_hz, "last": _last(last[name])})
        finally:
            for _, stream in streams:
                try:
                    stream.close()
                except DeviceError:
                    pass
        if error is not None:
            raise error
    if args.json:
        print(json.dumps(out))
    else:
        print("summary:")
        for s in out["streams"]:
            print(f"  {s['device']:<10} received {s['received']} of {s['expected']} expected "
                  f"({s['measured_rate_hz']:.1f} Hz), {s['missing']} lost in {s['gaps']} gap(s)")
        print(f"devices: {', '.join(names)}")
    return 0
