"""The stream into the MCAP log: every cycle, the events, and what Foxglove draws of it.

``/stream/cycle`` (``elastocal.StreamCycle``) carries each cycle: planned, sent and measured
joints, the correction (sent and wanted), the wrench and its source and age, the cycle's
timing and whether it was late or clamped. Events go to ``/procedure/event`` (``procedure =
"stream"``: start, prompts, lost controller messages as ``gap``, faults, the end with the
counts). For Foxglove, ``/stream/correction`` (``foxglove.SceneUpdate``, frame ``base``)
holds the path of the load point as a line, and the correction as a 3-D arrow at the
planned load point: the load point's displacement the correction makes (``J_p`` times the
joint correction), magnified ``ARROW_GAIN`` times, 10 times a second; late and clamped
cycles become lines of Foxglove's Log panel (``/cell/log``) when they start and end.
"""

from __future__ import annotations

import queue
import threading

import numpy as np

from elastocal.acquisition.foxglove import LOG_INFO, LOG_WARNING, stamp
from elastocal.acquisition.recorder import Recorder
from elastocal.formats import logformat as lf
from elastocal.stream.loop import CycleRecord
from elastocal.stream.plan import StreamPlan

#: the arrow shows the correction's displacement of the load point this many times larger
ARROW_GAIN = 100.0
SCENE_PERIOD_NS = 100_000_000


def _vec(p) -> dict:
    return {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}


def _arrow_orientation(direction: np.ndarray) -> dict:
    """The quaternion turning +x onto ``direction`` (unit)."""
    x = np.array([1.0, 0.0, 0.0])
    c = float(np.dot(x, direction))
    if c < -1.0 + 1e-12:
        return {"x": 0.0, "y": 0.0, "z": 1.0, "w": 0.0}
    axis = np.cross(x, direction)
    w = 1.0 + c
    norm = np.sqrt(w * w + float(np.dot(axis, axis)))
    return {"x": float(axis[0] / norm), "y": float(axis[1] / norm), "z": float(axis[2] / norm), "w": float(w / norm)}


def _entity(unix_ns: int, entity_id: str, **primitives) -> dict:
    entity = {"timestamp": stamp(unix_ns), "frame_id": "base", "id": entity_id,
              "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False, "metadata": []}
    for kind in ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models"):
        entity[kind] = primitives.get(kind, [])
    return entity


class StreamLog:
    """The stream's sink (:class:`elastocal.stream.loop.Sink`) writing into a :class:`Recorder`.

    The cycle only hands its record over: a thread of its own turns it into messages and writes
    them (a file write can block for as long as the disk pleases, and the cycle must not). The
    thread keeps the stream's scheduling: at a lower priority it could be preempted while it
    holds the interpreter lock, and the cycle would wait for it. :meth:`close` (or leaving the
    ``with`` block) writes what is left."""

    def __init__(self, recorder: Recorder, plan: StreamPlan, source: str) -> None:
        self.recorder = recorder
        self.plan = plan
        self.source = source
        self._next_scene_ns: int | None = None
        self._late = False
        self._limited = False
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._error: BaseException | None = None
        self._writer = threading.Thread(target=self._write_loop, name="stream-log", daemon=True)
        self._writer.start()

    def _write_loop(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self._error is not None:
                continue                  # the first failure is raised by close(); the rest is dropped
            kind, payload = item
            try:
                if kind == "cycle":
                    self._write_cycle(payload)
                else:
                    self.recorder.event(payload[0], procedure="stream", **payload[1])
            except BaseException as exc:  # noqa: BLE001 - handed to the stream's thread by close()
                self._error = exc

    def close(self) -> None:
        """Write everything handed over; raise what the writing thread met."""
        if self._writer.is_alive():
            self._queue.put(None)
            self._writer.join()
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _unix(self, t_ns: int) -> int:
        return int(t_ns) + self.recorder.offset_ns

    def event(self, kind: str, **fields) -> None:
        self._queue.put(("event", (kind, fields)))

    def path_scene(self, t_ns: int) -> dict:
        line = {"type": 0, "pose": {"position": _vec((0, 0, 0)), "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}},
                "thickness": 0.004, "scale_invariant": False, "points": [_vec(p) for p in self.plan.load_point],
                "color": {"r": 0.35, "g": 0.6, "b": 0.95, "a": 1.0}, "colors": [], "indices": []}
        return {"deletions": [], "entities": [_entity(self._unix(t_ns), "stream/path", lines=[line])]}

    def arrow_scene(self, record: CycleRecord) -> dict:
        i, w = self.plan.locate(record.t_path_s)
        tail = self.plan.at(self.plan.load_point, i, w)
        moved = self.plan.at(self.plan.position_jacobian, i, w) @ record.correction
        length = float(np.linalg.norm(moved)) * ARROW_GAIN
        arrows = []
        if length > 0:
            head = min(0.3 * length, 0.03)
            color = {"r": 0.95, "g": 0.3 if (record.late or record.limited) else 0.55, "b": 0.1, "a": 1.0}
            pose = {"position": _vec(tail), "orientation": _arrow_orientation(moved / np.linalg.norm(moved))}
            arrows.append({"pose": pose,
                           "shaft_length": max(length - head, 0.0), "shaft_diameter": 0.008, "head_length": head,
                           "head_diameter": 0.02, "color": color})
        entity = _entity(self._unix(record.t_ns), "stream/correction", arrows=arrows)
        entity["metadata"] = [{"key": "correction_mm", "value": f"{np.linalg.norm(moved) * 1e3:.4f}"},
                              {"key": "arrow_gain", "value": f"{ARROW_GAIN:g}"}]
        return {"deletions": [], "entities": [entity]}

    def cycle(self, r: CycleRecord) -> None:
        self._queue.put(("cycle", r))

    def _write_cycle(self, r: CycleRecord) -> None:
        msg = {"cycle": r.cycle, "sequence": int(r.sequence), "t_path_s": float(r.t_path_s),
               "q_planned": r.q_planned.tolist(), "correction_rad": r.correction.tolist(),
               "wanted_rad": None if r.wanted is None else r.wanted.tolist(), "q_sent": r.q_sent.tolist(),
               "q_measured": r.q_measured.tolist(), "wrench": None if r.wrench is None else r.wrench.tolist(),
               "wrench_source": self.source,
               "wrench_age_ms": None if r.wrench_age_ns is None else r.wrench_age_ns * 1e-6,
               "compute_us": r.compute_ns * 1e-3, "response_us": r.response_ns * 1e-3, "period_us": r.period_ns * 1e-3,
               "late": None if r.late is None else r.late.value, "limited": r.limited,
               "lost_before": int(r.lost_before), "monotonic_ns": int(r.t_ns)}
        rec = self.recorder
        rec.message(lf.TOPIC_STREAM_CYCLE, r.t_ns, msg)
        if self._next_scene_ns is None:
            rec.message(lf.TOPIC_STREAM_SCENE, r.t_ns, self.path_scene(r.t_ns))
            self._next_scene_ns = r.t_ns
        if r.t_ns >= self._next_scene_ns:
            rec.message(lf.TOPIC_STREAM_SCENE, r.t_ns, self.arrow_scene(r))
            self._next_scene_ns = r.t_ns + SCENE_PERIOD_NS
        self._transition(r, "late", r.late is not None,
                         f"late cycles from cycle {r.cycle} ({r.late.value if r.late else ''}): the last "
                         "correction is held", "on time again")
        self._transition(r, "limited", r.limited, f"correction at its limit from cycle {r.cycle}",
                         "correction within its limits again")

    def _transition(self, r: CycleRecord, name: str, now: bool, start: str, end: str) -> None:
        attr = f"_{name}"
        if now == getattr(self, attr):
            return
        setattr(self, attr, now)
        text = start if now else f"{end} at cycle {r.cycle}"
        line = {"timestamp": stamp(self._unix(r.t_ns)), "level": LOG_WARNING if now else LOG_INFO,
                "message": text, "name": "elastocal.stream", "file": "", "line": 0}
        self.recorder.message(lf.TOPIC_LOG, r.t_ns, line)
