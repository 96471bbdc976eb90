"""Topics and JSON Schemas of the elastocal MCAP log (docs/log-format.md).

Every topic is JSON-encoded (message encoding ``json``) with a JSON Schema
(schema encoding ``jsonschema``), so Foxglove and the ``mcap`` CLI open a log
without elastocal. Message ``log_time`` is the acquisition timestamp in integer
Unix nanoseconds (wall clock: the acquisition time on the recording host's
monotonic clock plus the session's fixed offset to Unix time), and each sample
and event keeps its monotonic stamp in ``monotonic_ns``; ``publish_time`` is when
the recorder wrote the message, same clock. Logs written before the change have
monotonic log times and no ``monotonic_ns`` field; the reader takes their log
time as the monotonic stamp. Beside these, the log carries Foxglove's
well-known channels (:mod:`elastocal.acquisition.foxglove`).
"""

from __future__ import annotations

import functools
import json
import pathlib

#: value of the ``format`` field of the ``/elastocal/session`` message and of the log metadata
LOG_FORMAT = "elastocal.log/1"
#: MCAP header profile
PROFILE = "elastocal"

TOPIC_SESSION = "/elastocal/session"
TOPIC_ROBOT = "/elastocal/robot"
TOPIC_CELL = "/elastocal/cell"
TOPIC_PLAN = "/elastocal/plan"
TOPIC_EVENT = "/procedure/event"
TOPIC_TRACKER = "/tracker"
#: optional fields of a tracker sample: what the tracker reported about the air (emScon does)
TRACKER_ENVIRONMENT = {
    "temperature_c": "air temperature at the tracker [°C] (optional)",
    "pressure_hpa": "air pressure [hPa] (optional)",
    "humidity_pct": "relative humidity [%] (optional)",
    "ifm_refraction_index": "refraction index the interferometer used (optional)",
    "adm_refraction_index": "refraction index the absolute distance meter used (optional)",
}
DRIVE_TOPIC_PREFIX = "/drive/"
#: the most joints a log holds drives for: ``/drive/1`` .. ``/drive/N``, N the robot's (any serial chain)
MAX_JOINTS = 64


def drive_topic(joint: int) -> str:
    """Topic of the samples of drive ``joint`` (1-based): ``/drive/1`` .. ``/drive/N``."""
    if not 1 <= joint <= MAX_JOINTS:
        raise ValueError(f"joint must be 1..{MAX_JOINTS}, got {joint}")
    return f"{DRIVE_TOPIC_PREFIX}{joint}"


DRIVE_TOPICS = tuple(drive_topic(j) for j in range(1, MAX_JOINTS + 1))

_NUMBER_OR_NULL = {"type": ["number", "null"]}
_MONOTONIC = {"type": "integer", "description": "acquisition time on the recording host's monotonic clock [ns]; "
                                               "log_time is this plus the session's offset to Unix time"}
#: one value per joint (q1..qN)
_JOINT_VECTOR = {"type": "array", "items": {"type": "number"}, "minItems": 1, "maxItems": MAX_JOINTS}

#: schema name -> JSON Schema (draft 2020-12)
SCHEMAS: dict[str, dict] = {
    "elastocal.Session": {
        "title": "elastocal.Session",
        "description": "First message of a log: format version and how the monotonic clock maps to UTC.",
        "type": "object",
        "properties": {
            "format": {"type": "string", "const": LOG_FORMAT},
            "software": {"type": "string", "description": "elastocal version that wrote the log"},
            "started_utc": {"type": "string", "description": "ISO 8601 wall-clock time at monotonic_ns"},
            "monotonic_ns": {"type": "integer", "description": "monotonic clock reading at started_utc"},
            "unix_ns": {"type": "integer", "description": "Unix time at monotonic_ns [ns]: the offset of the log clock"},
            "log_clock": {"type": "string", "enum": ["unix"],
                          "description": "log times are Unix ns (absent in logs with monotonic log times)"},
            "resumed_from": {"type": ["string", "null"],
                             "description": "log this one continues (copied messages keep their times)"},
        },
        "required": ["format", "started_utc", "monotonic_ns"],
    },
    "elastocal.Document": {
        "title": "elastocal.Document",
        "description": "A configuration document kept verbatim: robot.toml, cell.toml or plan.toml.",
        "type": "object",
        "properties": {
            "kind": {"type": "string", "enum": ["robot", "cell", "plan"]},
            "name": {"type": "string"},
            "path": {"type": ["string", "null"], "description": "where it was read from when recorded"},
            "sha256": {"type": "string"},
            "text": {"type": "string", "description": "the TOML text"},
        },
        "required": ["kind", "name", "sha256", "text"],
    },
    "elastocal.DriveSample": {
        "title": "elastocal.DriveSample",
        "description": "One raw sample of one joint drive; log_time is its acquisition time [ns].",
        "type": "object",
        "properties": {
            "joint": {"type": "integer", "minimum": 1, "maximum": MAX_JOINTS},
            "position_rad": {"type": "number", "description": "joint coordinate q (motor side) [rad]"},
            "velocity_rad_s": {**_NUMBER_OR_NULL, "description": "joint speed dq [rad/s]"},
            "current_a": {**_NUMBER_OR_NULL,
                          "description": "motor current [A], signed: torque_constant * i = load torque"},
            "status": {"type": ["integer", "null"], "description": "drive status word as read"},
            "monotonic_ns": _MONOTONIC,
        },
        "required": ["joint", "position_rad", "velocity_rad_s", "current_a"],
    },
    "elastocal.TrackerSample": {
        "title": "elastocal.TrackerSample",
        "description": "One raw tracker measurement of one marker; log_time is its acquisition time [ns].",
        "type": "object",
        "properties": {
            "marker": {"type": "string"},
            "x": {"type": "number", "description": "[m], measurement frame"},
            "y": {"type": "number", "description": "[m]"},
            "z": {"type": "number", "description": "[m]"},
            **{k: {"type": "number", "description": d} for k, d in TRACKER_ENVIRONMENT.items()},
            "monotonic_ns": _MONOTONIC,
        },
        "required": ["marker", "x", "y", "z"],
    },
    "elastocal.ProcedureEvent": {
        "title": "elastocal.ProcedureEvent",
        "description": "A procedure event: what the cell and the operator were doing (docs/log-format.md).",
        "type": "object",
        "properties": {
            "kind": {"type": "string", "enum": [
                "procedure_start", "procedure_end", "step_start", "step_done", "pose", "load",
                "settle", "hold_start", "reading", "hold_end", "run_start", "run_end",
                "prompt", "answer", "fault", "gap", "resume", "unattended", "standstill", "beam_back"]},
            "procedure": {"type": "string"},
            "step": {"type": "integer", "description": "0-based index of the step in the procedure"},
            "step_id": {"type": "string"},
            "steps": {"type": "integer", "description": "number of steps of the procedure"},
            "pose": {"type": "string"},
            "load": {"type": "string", "description": "load state id; '0' is unloaded"},
            "q": {**_JOINT_VECTOR, "description": "commanded joint coordinates q1..qN [rad, m]"},
            "wrench": {"type": ["array", "null"], "items": {"type": "number"}, "minItems": 6, "maxItems": 6,
                       "description": "nominal external wrench on the load point, base axes [N, N*m]"},
            "mass_kg": {"type": ["number", "null"]},
            "marker": {"type": ["string", "null"]},
            "repeat": {"type": "integer"},
            "window_ns": {"type": "array", "items": {"type": "integer"}, "minItems": 2, "maxItems": 2,
                          "description": "[start, end] of a reading on the monotonic clock of the samples' "
                                         "monotonic_ns (the log time in logs without that field) [ns]"},
            "run": {"type": "string"},
            "direction": {"type": "string", "enum": ["UV", "VU", "+", "-"]},
            "speed_rad_s": {"type": "number"},
            "joint": {"type": "integer"},
            "settled": {"type": "boolean"},
            "duration_s": {"type": "number"},
            "max_speed_rad_s": {"type": ["number", "null"]},
            "spread_m": {"type": ["number", "null"]},
            "text": {"type": "string", "description": "prompt text or fault message"},
            "answer": {"type": "string"},
            "automatic": {"type": "boolean", "description": "answered by --yes, not by a person"},
            "source": {"type": "string", "description": "who answered a prompt: 'terminal /dev/pts/N', '--yes'"},
            "delay_s": {"type": "number", "description": "time from a prompt to its answer [s]"},
            "error": {"type": "string", "description": "error type of a fault"},
            "status": {"type": "string", "enum": ["completed", "aborted", "failed"]},
            "device": {"type": "string", "description": "device of a gap"},
            "missing": {"type": "integer", "description": "samples a gap lost"},
            "completed_steps": {"type": "array", "items": {"type": "string"}},
            "monotonic_ns": _MONOTONIC,
        },
        "required": ["kind"],
        # what each kind must carry for the log to be turned into tables (docs/log-format.md)
        "allOf": [{"if": {"properties": {"kind": {"const": kind}}, "required": ["kind"]},
                   "then": {"required": required}}
                  for kind, required in (("reading", ["step_id", "pose", "load", "marker", "q", "window_ns"]),
                                         ("run_start", ["step_id", "run", "direction"]),
                                         ("run_end", ["step_id", "run"]),
                                         ("step_start", ["step_id"]), ("step_done", ["step_id"]))],
    },
}

#: the online compensation stream (elastocal stream, docs/stream.md)
TOPIC_STREAM_CYCLE = "/stream/cycle"
_VECTOR = {"type": "array", "items": {"type": "number"}}
SCHEMAS["elastocal.StreamCycle"] = {
    "title": "elastocal.StreamCycle",
    "description": "One cycle of the online compensation stream; log_time is the arrival of the controller's "
                   "state message [ns].",
    "type": "object",
    "properties": {
        "cycle": {"type": "integer", "description": "0-based cycle of the stream"},
        "sequence": {"type": "integer", "description": "the controller's message counter (EGM seqno, RSI IPOC)"},
        "t_path_s": {"type": "number", "description": "path time by the controller's clock [s]"},
        "q_planned": {**_VECTOR, "description": "the plan's joint coordinates at t_path_s [rad]"},
        "correction_rad": {**_VECTOR, "description": "the correction sent, within its limits [rad]"},
        "wanted_rad": {"type": ["array", "null"], "items": {"type": "number"},
                       "description": "the correction the model asked for (null in a late cycle) [rad]"},
        "q_sent": {**_VECTOR, "description": "q_planned + correction_rad, sent to the controller [rad]"},
        "q_measured": {**_VECTOR, "description": "the joint coordinates the controller reported [rad]"},
        "wrench": {"type": ["array", "null"], "items": {"type": "number"}, "minItems": 6, "maxItems": 6,
                   "description": "process wrench on the load point, base axes [N, N*m] (null: none fresh)"},
        "wrench_source": {"type": "string", "enum": ["sensor", "currents", "path"]},
        "wrench_age_ms": {"type": ["number", "null"], "description": "age of the wrench when used [ms]"},
        "compute_us": {"type": "number", "description": "from taking up the message to the answer [us]"},
        "response_us": {"type": "number", "description": "from the message's arrival to the answer [us]"},
        "period_us": {"type": "number", "description": "since the previous message's arrival [us]"},
        "late": {"type": ["string", "null"], "enum": ["schedule", "force", "compute", None],
                 "description": "why the cycle held the last correction (null: on time)"},
        "limited": {"type": "boolean", "description": "the correction was clamped to its size or rate limit"},
        "lost_before": {"type": "integer", "description": "controller messages lost just before this one"},
        "monotonic_ns": _MONOTONIC,
    },
    "required": ["cycle", "t_path_s", "q_planned", "correction_rad", "q_sent", "q_measured", "wrench",
                 "wrench_source", "late", "limited"],
}

#: Foxglove's well-known channels (elastocal.acquisition.foxglove)
TOPIC_FRAMES = "/cell/frames"
TOPIC_ROBOT_SCENE = "/cell/robot"
TOPIC_TRACKER_SCENE = "/cell/tracker"
TOPIC_LOG = "/cell/log"
#: the stream's path and its corrections as 3-D arrows (foxglove.SceneUpdate)
TOPIC_STREAM_SCENE = "/stream/correction"
#: topic -> schema name of Foxglove's well-known channels
FOXGLOVE_TOPIC_SCHEMAS: dict[str, str] = {
    TOPIC_FRAMES: "foxglove.FrameTransforms",
    TOPIC_ROBOT_SCENE: "foxglove.SceneUpdate",
    TOPIC_TRACKER_SCENE: "foxglove.SceneUpdate",
    TOPIC_LOG: "foxglove.Log",
}
#: Foxglove's published JSON Schemas, shipped verbatim with their MIT licence
FOXGLOVE_SCHEMA_DIR = pathlib.Path(__file__).with_name("foxglove_schemas")

#: topic -> schema name, for the fixed topics
TOPIC_SCHEMAS: dict[str, str] = {
    TOPIC_SESSION: "elastocal.Session",
    TOPIC_ROBOT: "elastocal.Document",
    TOPIC_CELL: "elastocal.Document",
    TOPIC_PLAN: "elastocal.Document",
    TOPIC_EVENT: "elastocal.ProcedureEvent",
    TOPIC_TRACKER: "elastocal.TrackerSample",
    **{t: "elastocal.DriveSample" for t in DRIVE_TOPICS},
    TOPIC_STREAM_CYCLE: "elastocal.StreamCycle",
    TOPIC_STREAM_SCENE: "foxglove.SceneUpdate",
    **FOXGLOVE_TOPIC_SCHEMAS,
}


def schema_bytes(name: str) -> bytes:
    """The JSON Schema ``name`` as UTF-8 bytes (key order fixed); Foxglove's as published."""
    if name.startswith("foxglove."):
        return (FOXGLOVE_SCHEMA_DIR / f"{name.removeprefix('foxglove.')}.json").read_bytes()
    return json.dumps(SCHEMAS[name], separators=(",", ":")).encode()


#: topics whose messages are checked against their schema when a log is read (the few
#: documents and events; the many samples are checked by the reader as arrays)
CHECKED_TOPICS = (TOPIC_SESSION, TOPIC_ROBOT, TOPIC_CELL, TOPIC_PLAN, TOPIC_EVENT)


@functools.lru_cache(maxsize=None)
def _validator(name: str):
    import jsonschema

    return jsonschema.Draft202012Validator(SCHEMAS[name])


def message_error(topic: str, payload: object) -> str | None:
    """Why ``payload`` does not follow its topic's schema (one line), or None when it does."""
    import jsonschema

    error = jsonschema.exceptions.best_match(_validator(TOPIC_SCHEMAS[topic]).iter_errors(payload))
    if error is None:
        return None
    where = ".".join(str(p) for p in error.absolute_path)
    text = error.message if len(error.message) <= 200 else error.message[:200] + "..."
    return f"{where}: {text}" if where else text
