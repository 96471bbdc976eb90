"""The cell in Foxglove's well-known schemas, written into the log beside the raw channels.

The raw channels (``/drive/N``, ``/tracker``, ``/procedure/event``) keep their
elastocal schemas; this module adds what Foxglove's 3-D and Log panels read
(docs/log-format.md, "Foxglove"):

* ``/cell/frames`` (``foxglove.FrameTransforms``): each joint's frame in the
  previous one, ``base`` → ``measured/joint1`` … ``measured/jointN`` from the
  drives' positions (10 per second of log time, at grid instants every drive has
  reached, each joint at its latest sample by then), and ``base`` →
  ``commanded/joint1`` … from the commanded joint values of ``pose``,
  ``hold_start`` and ``run_start`` events;
* ``/cell/robot`` (``foxglove.SceneUpdate``): the links as lines between joint
  origins, the joints as spheres, the load point and the markers on the flange,
  each entity locked to its joint frame so it moves with it; the commanded robot
  drawn translucent. Published when the robot description is recorded and again
  at every pose and run, so a seek in Foxglove finds it;
* ``/cell/tracker`` (``foxglove.SceneUpdate``): the latest tracker reading of
  each marker, a sphere in the ``base`` frame (the tracker's measurement frame,
  which the model takes to be the robot's base), at most 10 per second and marker;
* ``/cell/log`` (``foxglove.Log``): every procedure event as a line of text.

Every message is JSON and valid against Foxglove's published JSON Schemas,
shipped in ``foxglove_schemas/`` with their MIT licence. Times are wall-clock
Unix nanoseconds (the log's clock). Pure bookkeeping: the publisher calls
``write(topic, unix_ns, message)``; it never touches a file itself.
"""

from __future__ import annotations

import collections
from typing import Callable, Mapping, Sequence

import numpy as np
import pinocchio as pin

from elastocal.formats.logformat import TOPIC_FRAMES, TOPIC_LOG, TOPIC_ROBOT_SCENE, TOPIC_TRACKER_SCENE
from elastocal.model.robot import FLANGE_FRAME, LOAD_FRAME, Robot

BASE_FRAME = "base"
MEASURED = "measured"
COMMANDED = "commanded"

PERIOD_NS = 100_000_000          # measured frames and tracker readings: 10 per second of log time
_MAX_PENDING = 20_000            # samples kept per joint while waiting for the slowest drive

LOG_DEBUG, LOG_INFO, LOG_WARNING, LOG_ERROR = 1, 2, 3, 4
_LEVELS = {"fault": LOG_ERROR, "gap": LOG_WARNING}
_END_LEVELS = {"completed": LOG_INFO, "aborted": LOG_WARNING, "failed": LOG_ERROR}
_QUIET_FIELDS = ("step", "q", "window_ns", "completed_steps", "monotonic_ns")

Write = Callable[[str, int, dict], None]


def stamp(unix_ns: int) -> dict:
    """Foxglove ``time``: ``{"sec", "nsec"}`` of Unix nanoseconds."""
    sec, nsec = divmod(int(unix_ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def _vec(p: Sequence[float]) -> dict:
    return {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}


def _pose(p: Sequence[float] = (0.0, 0.0, 0.0)) -> dict:
    return {"position": _vec(p), "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def _color(r: float, g: float, b: float, a: float = 1.0) -> dict:
    return {"r": r, "g": g, "b": b, "a": a}


def _entity(unix_ns: int, frame_id: str, entity_id: str, **primitives: list) -> dict:
    entity = {"timestamp": stamp(unix_ns), "frame_id": frame_id, "id": entity_id,
              "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": True, "metadata": []}
    for kind in ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models"):
        entity[kind] = primitives.get(kind, [])
    return entity


def _sphere(p: Sequence[float], diameter_m: float, color: dict) -> dict:
    return {"pose": _pose(p), "size": _vec((diameter_m,) * 3), "color": color}


def _line(points: Sequence[Sequence[float]], thickness_m: float, color: dict) -> dict:
    return {"type": 0, "pose": _pose(), "thickness": thickness_m, "scale_invariant": False,
            "points": [_vec(p) for p in points], "color": color, "colors": [], "indices": []}


_STYLE = {MEASURED: (_color(0.93, 0.55, 0.13), _color(0.25, 0.25, 0.28)),
          COMMANDED: (_color(0.35, 0.6, 0.95, 0.35), _color(0.35, 0.6, 0.95, 0.35))}
_MARKER_COLOR = _color(0.1, 0.75, 0.3)
_LOAD_COLOR = _color(0.85, 0.1, 0.1)
_TRACKER_COLOR = _color(0.95, 0.1, 0.85)


class CellPublisher:
    """Turns the recorder's samples and events into Foxglove messages for one robot."""

    def __init__(self, robot: Robot, write: Write, *, period_ns: int = PERIOD_NS) -> None:
        self.robot = robot
        self.write = write
        self.period_ns = int(period_ns)
        model = robot.model
        self._joint_ids = [model.getJointId(f"joint{i}") for i in range(1, robot.n_joints + 1)]
        data = model.createData()
        pin.framesForwardKinematics(model, data, robot.theta(np.zeros(robot.n_joints)))
        # each link drawn in its joint's frame: from the joint's origin to the next joint's origin
        # (the last one to the flange); the next joint's placement does not depend on this joint's angle
        self._link_ends = [np.array(model.jointPlacements[j].translation) for j in self._joint_ids[1:]]
        flange = model.frames[model.getFrameId(FLANGE_FRAME)].placement
        self._link_ends.append(np.array(flange.translation))
        self._tool_points = {LOAD_FRAME: np.array(model.frames[model.getFrameId(LOAD_FRAME)].placement.translation)}
        for name in robot.marker_names:
            frame = model.frames[robot.frame_id(name)].placement
            self._tool_points[name] = np.array(frame.translation)
        self._pending: list[collections.deque] = [collections.deque() for _ in range(robot.n_joints)]
        self._next_frame_ns: int | None = None
        self._tracker_last_ns: dict[str, int] = {}
        self._scene_written = False

    def _first(self, unix_ns: int) -> None:
        """The robot scene goes out with the first message (after the log's documents)."""
        if not self._scene_written:
            self.publish_scene(unix_ns)

    # ---------------------------------------------------------------- frames
    def transforms(self, prefix: str, q: Sequence[float], unix_ns: int) -> dict:
        """``foxglove.FrameTransforms`` of the N joint frames at motor-side ``q``."""
        model = self.robot.model
        data = model.createData()
        pin.forwardKinematics(model, data, self.robot.theta(np.asarray(q, dtype=float)))
        out, parent = [], BASE_FRAME
        for i, jid in enumerate(self._joint_ids, start=1):
            placement = data.liMi[jid]
            quat = pin.Quaternion(placement.rotation)
            child = f"{prefix}/joint{i}"
            out.append({"timestamp": stamp(unix_ns), "parent_frame_id": parent, "child_frame_id": child,
                        "translation": _vec(placement.translation),
                        "rotation": {"x": float(quat.x), "y": float(quat.y), "z": float(quat.z),
                                     "w": float(quat.w)}})
            parent = child
        return {"transforms": out}

    def measured_sample(self, joint: int, t_ns: int, position_rad: float, offset_ns: int) -> None:
        """One drive sample (``t_ns`` on the acquisition clock; ``offset_ns`` maps it to Unix time)."""
        pending = self._pending[joint - 1]
        pending.append((int(t_ns), float(position_rad)))
        if len(pending) > _MAX_PENDING:
            pending.popleft()
        if self._next_frame_ns is None:
            if not all(self._pending):
                return
            self._next_frame_ns = max(p[0][0] for p in self._pending)
        while all(p and p[-1][0] >= self._next_frame_ns for p in self._pending):
            t = self._next_frame_ns
            q = []
            for p in self._pending:
                while len(p) > 1 and p[1][0] <= t:
                    p.popleft()
                q.append(p[0][1])
            self._first(t + offset_ns)
            self.write(TOPIC_FRAMES, t + offset_ns, self.transforms(MEASURED, q, t + offset_ns))
            self._next_frame_ns = t + self.period_ns

    def commanded(self, q: Sequence[float], unix_ns: int) -> None:
        self.write(TOPIC_FRAMES, unix_ns, self.transforms(COMMANDED, q, unix_ns))

    # ----------------------------------------------------------------- scene
    def robot_scene(self, unix_ns: int) -> dict:
        """``foxglove.SceneUpdate`` of the measured and the commanded robot."""
        entities = []
        for prefix, (link_color, joint_color) in _STYLE.items():
            for i, end in enumerate(self._link_ends, start=1):
                entities.append(_entity(unix_ns, f"{prefix}/joint{i}", f"{prefix}/link{i}",
                                        lines=[_line(((0.0, 0.0, 0.0), end), 0.09, link_color)],
                                        spheres=[_sphere((0.0, 0.0, 0.0), 0.16, joint_color)]))
        tool = [_sphere(p, 0.05, _LOAD_COLOR if name == LOAD_FRAME else _MARKER_COLOR)
                for name, p in self._tool_points.items()]
        entities.append(_entity(unix_ns, f"{MEASURED}/joint{self.robot.n_joints}", f"{MEASURED}/tool", spheres=tool))
        return {"deletions": [], "entities": entities}

    def publish_scene(self, unix_ns: int) -> None:
        self._scene_written = True
        self.write(TOPIC_ROBOT_SCENE, unix_ns, self.robot_scene(unix_ns))

    def tracker_sample(self, marker: str, xyz: Sequence[float], t_ns: int, offset_ns: int) -> None:
        last = self._tracker_last_ns.get(marker)
        if last is not None and t_ns - last < self.period_ns:
            return
        self._tracker_last_ns[marker] = int(t_ns)
        unix_ns = int(t_ns) + offset_ns
        self._first(unix_ns)
        entity = _entity(unix_ns, BASE_FRAME, f"tracker/{marker}", spheres=[_sphere(xyz, 0.04, _TRACKER_COLOR)])
        entity["frame_locked"] = False
        entity["metadata"] = [{"key": "marker", "value": str(marker)}]
        self.write(TOPIC_TRACKER_SCENE, unix_ns, {"deletions": [], "entities": [entity]})

    # ------------------------------------------------------------ procedure
    def event(self, message: Mapping, unix_ns: int) -> None:
        """A procedure event: a ``foxglove.Log`` line; commanded frames when it names ``q``;
        the robot scene again at each pose and run."""
        kind = str(message.get("kind", ""))
        self._first(unix_ns)
        self.write(TOPIC_LOG, unix_ns, log_message(message, unix_ns))
        q = message.get("q")
        if kind in ("pose", "hold_start", "run_start") and isinstance(q, list) and len(q) == self.robot.n_joints:
            self.commanded(q, unix_ns)
        if kind in ("pose", "run_start") and self._scene_written:
            self.publish_scene(unix_ns)


def log_message(message: Mapping, unix_ns: int) -> dict:
    """``foxglove.Log`` of a procedure event: its kind, then its fields in words."""
    kind = str(message.get("kind", ""))
    level = _END_LEVELS.get(message.get("status"), LOG_INFO) if kind == "procedure_end" else \
        _LEVELS.get(kind, LOG_INFO)
    parts = [f"{k}={v}" for k, v in message.items() if k != "kind" and k not in _QUIET_FIELDS and k != "text"]
    text = message.get("text")
    line = " ".join([kind, *parts])
    if text:
        line += f": {text}"
    return {"timestamp": stamp(unix_ns), "level": level, "message": line, "name": "elastocal.procedure",
            "file": "", "line": 0}
