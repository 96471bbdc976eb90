"""A simulated cell for the online stream: a guided controller (EGM or RSI) and a Net F/T.

:class:`SimGuidedCell` builds the simulated robot under guidance
(:class:`~elastocal.sims.guided.GuidedRobot`, at the path's first point, with the process
force profile), the simulated controller of the guidance URL's kind pointed at the address the
stream listens on, and a simulated Net F/T when asked. The controller starts only when the
stream asks (:meth:`start_controller`: after the operator's confirmation, as a person starts
the robot's program).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.egm_controller import SimEgmController
from elastocal.sims.guided import Faults, GuidedRobot, ProcessLoad
from elastocal.sims.netft_sensor import SimNetFt
from elastocal.sims.rsi_controller import SimRsiController


@dataclass(frozen=True)
class GuidedCellSpec:
    """What to simulate: the process wrench profile (built up over ``engage_s``, then start -> end
    over ``duration_s``: :class:`~elastocal.sims.guided.ProcessLoad`), the seed, injected faults."""

    start_wrench: tuple[float, ...]
    end_wrench: tuple[float, ...]
    duration_s: float
    engage_s: float = 1.0
    seed: int = 0
    faults: Faults = Faults()
    sensor_silent_after_s: float | None = None


class SimGuidedCell:
    """The simulated peers of one stream (see the module docstring)."""

    def __init__(self, robot, spec: GuidedCellSpec, *, start_q: Sequence[float], truth: CellTruth | None = None,
                 with_sensor: bool) -> None:
        self.cell = SimCell(robot, truth)      # None: the cell's default truth, sized for the robot
        self.spec = spec
        self.load = ProcessLoad(np.asarray(spec.start_wrench, dtype=float), np.asarray(spec.end_wrench, dtype=float),
                                spec.duration_s, spec.engage_s)
        self.robot = GuidedRobot(self.cell, start_q=start_q, load=self.load, seed=spec.seed)
        self.sensor = SimNetFt(self.robot, seed=spec.seed + 1,
                               silent_after_s=spec.sensor_silent_after_s).start() if with_sensor else None
        self.controller = None

    def sensor_url(self) -> str:
        return self.sensor.url()

    def start_controller(self, kind: str, computer: tuple[str, int], cycle_s: float, *, lockstep: bool = False):
        """Start the simulated controller of ``kind`` ("egm" or "rsi") guiding toward ``computer``,
        on simulated time when ``lockstep`` (:mod:`~elastocal.sims.guidance_peer`)."""
        host = "127.0.0.1" if computer[0] in ("0.0.0.0", "") else computer[0]
        cls = {"egm": SimEgmController, "rsi": SimRsiController}[kind]
        self.controller = cls(self.robot, (host, computer[1]), cycle_s=cycle_s, faults=self.spec.faults,
                              lockstep=lockstep).start()
        return self.controller

    def close(self) -> None:
        if self.controller is not None:
            self.controller.close()
        if self.sensor is not None:
            self.sensor.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ------------------------------------------------------------- in a process of its own
def _spec_json(spec: GuidedCellSpec) -> dict:
    return {"start_wrench": list(spec.start_wrench), "end_wrench": list(spec.end_wrench),
            "duration_s": spec.duration_s, "engage_s": spec.engage_s, "seed": spec.seed,
            "lost_cycles": sorted(spec.faults.lost_cycles), "silent_from_cycle": spec.faults.silent_from_cycle,
            "sensor_silent_after_s": spec.sensor_silent_after_s}


def _spec_of(obj: dict) -> GuidedCellSpec:
    return GuidedCellSpec(start_wrench=tuple(obj["start_wrench"]), end_wrench=tuple(obj["end_wrench"]),
                          duration_s=float(obj["duration_s"]), engage_s=float(obj["engage_s"]),
                          seed=int(obj["seed"]),
                          faults=Faults(lost_cycles=frozenset(obj["lost_cycles"]),
                                        silent_from_cycle=obj["silent_from_cycle"]),
                          sensor_silent_after_s=obj["sensor_silent_after_s"])


class ServedGuidedCell:
    """:class:`SimGuidedCell` served by a child process (``python -m elastocal.sims.guided_cell``),
    so that the simulated controller's physics and the sensor's stream do not share this
    interpreter with the stream they test. The same methods; ``cell`` and ``load`` are built
    here too (the truth, for judging what the stream did)."""

    def __init__(self, robot_path: str, spec: GuidedCellSpec, *, start_q: Sequence[float], with_sensor: bool) -> None:
        import json
        import subprocess
        import sys

        from elastocal.formats.robot_toml import load_robot

        self.spec = spec
        self.cell = SimCell(load_robot(robot_path))
        self.load = ProcessLoad(np.asarray(spec.start_wrench, dtype=float), np.asarray(spec.end_wrench, dtype=float),
                                spec.duration_s, spec.engage_s)
        args = {"robot": str(robot_path), "spec": _spec_json(spec), "start_q": [float(v) for v in start_q],
                "with_sensor": bool(with_sensor)}
        self._proc = subprocess.Popen([sys.executable, "-m", "elastocal.sims.guided_cell", json.dumps(args)],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        line = self._proc.stdout.readline()
        if not line:
            self._proc.wait(timeout=10)
            raise RuntimeError(f"the simulated guided cell did not start (exit {self._proc.returncode})")
        self._ready = json.loads(line)
        self.controller = None
        self.controller_stats: dict | None = None      # what the simulated controller counted (after close)

    def sensor_url(self) -> str:
        return self._ready["sensor_url"]

    def start_controller(self, kind: str, computer: tuple[str, int], cycle_s: float, *, lockstep: bool = False) -> None:
        import json

        order = {"kind": kind, "computer": list(computer), "cycle_s": cycle_s, "lockstep": bool(lockstep)}
        self._proc.stdin.write(json.dumps(order) + "\n")
        self._proc.stdin.flush()
        self.controller = kind

    def close(self) -> None:
        import json

        if self._proc.poll() is None:
            try:
                self._proc.stdin.close()
            except OSError:
                pass                            # the child is gone already: waiting below reaps it
            try:
                self._proc.wait(timeout=5)
            except Exception:                   # noqa: BLE001 - whatever hangs, the child is ended
                self._proc.kill()
                self._proc.wait()
        line = self._proc.stdout.readline()
        self.controller_stats = json.loads(line) if line.strip() else None
        self._proc.stdout.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _serve(argument: str) -> None:
    """The child's side: the sensor at once, the controller when the parent says so, until stdin closes."""
    import contextlib
    import json
    import os
    import sys

    from elastocal.formats.robot_toml import load_robot

    args = json.loads(argument)
    sys.setswitchinterval(2e-4)
    # a simulated controller stands in for a hard real-time one: its threads (started below, they
    # inherit it) run under SCHED_FIFO where the system allows, above the stream it tests
    with contextlib.suppress(AttributeError, OSError):
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(45))
    cell = SimGuidedCell(load_robot(args["robot"]), _spec_of(args["spec"]), start_q=args["start_q"],
                         with_sensor=args["with_sensor"])
    try:
        print(json.dumps({"sensor_url": cell.sensor_url() if cell.sensor is not None else None}), flush=True)
        line = sys.stdin.readline()
        if line.strip():
            order = json.loads(line)
            cell.start_controller(order["kind"], tuple(order["computer"]), float(order["cycle_s"]),
                                  lockstep=bool(order.get("lockstep", False)))
            sys.stdin.readline()                # runs until the parent closes our input
    finally:
        stats = cell.controller.stats() if cell.controller is not None else None
        cell.close()
        if stats is not None:
            print(json.dumps({"cycles": stats.cycles, "sent": stats.sent, "answered": stats.answered,
                              "late": stats.late, "state": stats.state.value, "reason": stats.reason}), flush=True)


if __name__ == "__main__":
    import sys

    _serve(sys.argv[1])
