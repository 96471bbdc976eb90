"""One online compensation run: devices, the operator's confirmation, the loop, the log.

:func:`run_online` is what ``elastocal stream`` does: read the robot, the calibration and the
path, precompute the plan, open the guidance channel and the force sensor (or serve their
simulated peers in this process), record everything into the MCAP log, ask the operator,
stream, and say what happened. Nothing moves before the operator confirms: the controller's
guided program starts after the prompt, and the stream refuses a robot that does not stand at
the path's first point.
"""

from __future__ import annotations

import contextlib
import dataclasses
import pathlib
from dataclasses import dataclass
from functools import partial

import numpy as np

from elastocal.acquisition.recorder import Recorder
from elastocal.acquisition.ui import Aborted, OperatorUI
from elastocal.compensation.files import read_path
from elastocal.compensation.model import CompensationModel
from elastocal.drivers import open_force_sensor, open_guidance
from elastocal.drivers.config import CellConfig
from elastocal.drivers.guidance import GuidanceKind
from elastocal.drivers.urls import parse_device_url
from elastocal.errors import DeviceError, InputError
from elastocal.formats.calibration import read_calibration
from elastocal.stream.correction import Limits
from elastocal.stream.loop import CycleRecord, StreamResult, StreamSettings, run_stream
from elastocal.stream.plan import StreamPlan, build_plan
from elastocal.stream.clock import ControllerTime, measure_ns
from elastocal.stream.realtime import STREAM_PRIORITY, realtime
from elastocal.stream.recording import StreamLog
from elastocal.stream.sources import CurrentsSource, ForceSourceKind, PathSource, SensorSource, tare

#: how long the sensor is averaged for its bias before guidance starts [s]
TARE_S = 0.2
#: with a simulated controller in lockstep, a sensor sample is stale only after this long on the wall
#: clock (the sensor streams on it): a silent sensor still stops the stream, a busy computer does not
LOCKSTEP_SENSOR_AGE_S = 0.5


@dataclass(frozen=True)
class StreamOptions:
    out: pathlib.Path
    source: ForceSourceKind | None = None          # None: the sensor if the cell has one, else the path's wrench
    wrench: np.ndarray | None = None               # a constant process wrench (the path source)
    settings: StreamSettings = StreamSettings()
    current_filter_s: float = 0.1
    overwrite: bool = False
    simulate: object | None = None                 # a sims.guided_cell.GuidedCellSpec: serve simulated peers
    priority: int | None = STREAM_PRIORITY         # SCHED_FIFO priority of the stream's threads (None: normal)
    time_scale: float = 1.0                        # a simulated cell runs the path this many times faster
    #: a simulated controller on this machine's wall clock (late when this machine is busy) instead of
    #: in lockstep on its own time (late only where the simulated cell injects it)
    sim_realtime: bool = False


@dataclass(frozen=True)
class StreamOutcome:
    log: str
    status: str                                    # completed, aborted, failed
    message: str
    guidance: GuidanceKind
    source: ForceSourceKind
    plan: StreamPlan
    result: StreamResult | None
    records: tuple[CycleRecord, ...]
    sim: object | None = None                      # the simulated cell when it was served (its truth)
    model: CompensationModel | None = None
    scheduling: str = ""                           # the scheduling the stream ran under


class _Keeping(StreamLog):
    """The log sink that also keeps the cycles (for the summary and the simulated cell's truth)."""

    def __init__(self, *args, **kw) -> None:
        super().__init__(*args, **kw)
        self.records: list[CycleRecord] = []

    def cycle(self, record: CycleRecord) -> None:
        self.records.append(record)
        super().cycle(record)


def _source_kind(options: StreamOptions, config: CellConfig, has_path_wrench: bool) -> ForceSourceKind:
    if options.source is not None:
        kind = options.source
    elif config.force_sensor is not None:
        kind = ForceSourceKind.SENSOR
    elif has_path_wrench or options.wrench is not None:
        kind = ForceSourceKind.PATH
    else:
        raise InputError("no force source: name a [force_sensor] in the cell, give the path fx..mz columns or a "
                         "constant wrench, or use the motor currents", argument="source")
    if kind is ForceSourceKind.SENSOR and config.force_sensor is None:
        raise InputError("the sensor source needs a [force_sensor] table in the cell config", source=config.source)
    if kind is ForceSourceKind.PATH and not has_path_wrench and options.wrench is None:
        raise InputError("the path source needs fx..mz columns in the path or a constant wrench", argument="wrench")
    return kind


def _limits(config: CellConfig) -> Limits:
    g = config.guidance
    defaults = Limits()
    return Limits(max_rad=np.radians(g.max_correction_deg) if g.max_correction_deg else defaults.max_rad,
                  max_rate_rad_s=np.radians(g.max_rate_deg_s) if g.max_rate_deg_s else defaults.max_rate_rad_s)


def run_online(config: CellConfig, calibration: str, path: str, options: StreamOptions,
               ui: OperatorUI) -> StreamOutcome:
    """Run one stream (see the module docstring); devices' and the loop's typed faults end it
    with status ``failed`` (the log says why), the operator's abort with ``aborted``."""
    if config.guidance is None:
        raise InputError("the cell config has no [guidance] table (egm:// or rsi://; docs/cell-config.md)",
                         source=config.source)
    robot = config.load_robot()
    model = CompensationModel.from_calibration(robot, read_calibration(calibration), source=calibration)
    planned = read_path(path, robot)
    kind = _source_kind(options, config, planned.wrench is not None)
    if options.time_scale != 1.0 and options.simulate is None:
        raise InputError("only a simulated cell runs a path faster than planned", argument="time_scale")
    plan = build_plan(model, planned.t / options.time_scale, planned.q)
    settings = dataclasses.replace(options.settings, limits=_limits(config)) \
        if options.settings.limits == Limits() else options.settings
    url = config.guidance.url
    sim = None
    if options.simulate is not None:
        from elastocal.sims.guided_cell import ServedGuidedCell

        sim = ServedGuidedCell(str(config.robot_path()), options.simulate, start_q=plan.q[0],
                               with_sensor=kind is ForceSourceKind.SENSOR)
        url = url.with_host("127.0.0.1").with_port(0)
    closers = [] if sim is None else [sim]
    with realtime(options.priority) if options.priority else contextlib.nullcontext("normal scheduling") as sched:
        return _run_devices(config, calibration, path, options, ui, url, plan, planned, kind, settings, sim, model,
                            closers, sched)


def _run_devices(config, calibration, path, options, ui, url, plan, planned, kind, settings, sim, model, closers,
                 sched) -> StreamOutcome:
    try:
        guidance = open_guidance(url, n_joints=plan.n_joints, source=f"{config.source}, guidance.url")
        closers.append(guidance)
        if sim is not None and not options.sim_realtime:
            guidance = ControllerTime(guidance)      # lockstep: judged on the simulated controller's time
        wrench = options.wrench if options.wrench is not None else planned.wrench
        source = _open_source(kind, config, plan, options, guidance.cycle_s, sim, closers, wrench)
        outcome = _record_and_stream(config, calibration, path, options, ui, guidance, source, kind, plan,
                                     settings, sim, model)
        if isinstance(guidance, ControllerTime):
            sched += "; the simulated controller in lockstep: cycles judged on its clock"
        return dataclasses.replace(outcome, scheduling=sched)
    finally:
        for item in reversed(closers):
            item.close()


def _open_source(kind, config, plan, options, cycle_s, sim, closers, wrench):
    if kind is ForceSourceKind.SENSOR:
        url = config.force_sensor.url if sim is None else parse_device_url(sim.sensor_url())
        sensor = open_force_sensor(url, source=f"{config.source}, force_sensor.url")
        closers.append(sensor)
        sensor.start()
        sensor.wait_first(1.0)
        if sim is not None and not options.sim_realtime:
            return SensorSource(sensor, plan, max_age_s=max(config.force_sensor.max_age_s, LOCKSTEP_SENSOR_AGE_S),
                                bias=tare(sensor, TARE_S), age_clock_ns=measure_ns)
        return SensorSource(sensor, plan, max_age_s=config.force_sensor.max_age_s, bias=tare(sensor, TARE_S))
    if kind is ForceSourceKind.CURRENTS:
        return CurrentsSource(plan, filter_s=options.current_filter_s, cycle_s=cycle_s)
    return PathSource(plan, wrench)


def _record_and_stream(config, calibration, path, options, ui, guidance, source, kind, plan, settings, sim, model):
    robot_text = config.robot_path().read_text(encoding="utf-8")
    with Recorder(options.out, overwrite=options.overwrite) as rec:
        rec.document("robot", config.robot, robot_text, str(config.robot_path()))
        rec.document("cell", config.name, config.to_toml(), config.source)
        host, port = guidance.address
        rec.event("procedure_start", procedure="stream", steps=1,
                  text=f"{guidance.kind.value} on {host}:{port}, {len(plan.t)} path samples over "
                       f"{plan.duration_s:.3f} s, wrench from {kind.value}; calibration {calibration}; path {path}")
        lim = settings.limits
        prompt = (f"stream {plan.duration_s:.1f} s of path {path} to the {guidance.kind.name} controller "
                  f"(listening on {host}:{port}, corrections within {np.degrees(lim.max_rad):.3f} deg and "
                  f"{np.degrees(lim.max_rate_rad_s):.3f} deg/s, wrench from {kind.value}); the robot must stand at "
                  "the path's first point; start the guided program on the controller after answering")
        rec.event("prompt", procedure="stream", text=prompt)
        outcome = partial(_outcome, options, guidance=guidance, kind=kind, plan=plan, sim=sim, model=model)
        try:
            ui.confirm(prompt)
        except Aborted as exc:
            rec.event("procedure_end", procedure="stream", status="aborted", text=str(exc))
            return outcome("aborted", str(exc), records=())
        rec.event("answer", procedure="stream", answer="yes", automatic=bool(getattr(ui, "automatic", False)))
        if sim is not None:
            sim.start_controller(guidance.kind.value, guidance.address, guidance.cycle_s,
                                 lockstep=isinstance(guidance, ControllerTime))
        ui.message("streaming; Ctrl-C stops (the robot holds the last target)")
        sink = _Keeping(rec, plan, kind.value)
        try:
            try:
                if isinstance(guidance, ControllerTime):
                    result = run_stream(guidance, source, plan, sink, settings=settings, clock_ns=guidance.clock_ns,
                                        measure_ns=measure_ns)
                else:
                    result = run_stream(guidance, source, plan, sink, settings=settings)
            finally:
                sink.close()             # every cycle written before the end's events
        except DeviceError as exc:
            rec.event("fault", procedure="stream", error=type(exc).__name__, text=str(exc))
            rec.event("procedure_end", procedure="stream", status="failed", text=str(exc),
                      **_counts_of(sink.records))
            exc.outcome = outcome("failed", f"{type(exc).__name__}: {exc}", records=sink.records)
            raise
        except KeyboardInterrupt:
            rec.event("procedure_end", procedure="stream", status="aborted", text="interrupted by the operator",
                      **_counts_of(sink.records))
            return outcome("aborted", "interrupted by the operator", records=sink.records)
        rec.event("procedure_end", procedure="stream", status="completed", **_counts_of(sink.records))
    return outcome("completed", "completed", result=result, records=sink.records)


def _counts_of(records) -> dict:
    return {"cycles": len(records), "late_cycles": sum(r.late is not None for r in records),
            "lost_messages": sum(r.lost_before for r in records), "limited_cycles": sum(r.limited for r in records)}


def _outcome(options, status, message, *, guidance, kind, plan, sim, model, records, result=None) -> StreamOutcome:
    return StreamOutcome(log=str(options.out), status=status, message=message, guidance=guidance.kind, source=kind,
                         plan=plan, result=result, records=tuple(records), sim=sim, model=model)
