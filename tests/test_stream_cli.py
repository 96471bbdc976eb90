"""`elastocal stream` end to end on the simulated cell (controller and Net F/T in a process of
their own on 127.0.0.1), its refusals, and the faults it types and logs. What is asserted is
what the stream and the simulated cell recorded, never how fast it ran."""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest
from mcap.reader import make_reader

from elastocal.acquisition.ui import AutoUI
from elastocal.cli import main
from elastocal.compensation.ik import yang_path
from elastocal.errors import DeviceError
from elastocal.formats import logformat as lf
from elastocal.sims.cell import CellTruth
from elastocal.sims.guided import Faults
from elastocal.sims.guided_cell import GuidedCellSpec
from elastocal.stream.loop import LateCause, WatchdogFault
from elastocal.stream.session import StreamOptions, run_online

PATH_S = 3.0        # Yang's 60 s line, played 20 times faster: the statics do not depend on the speed


@pytest.fixture(scope="module")
def files(tmp_path_factory, robot):
    root = tmp_path_factory.mktemp("stream")
    path = yang_path(robot, step_m=0.01)
    t = np.linspace(0.0, PATH_S, len(path.q))
    lines = ["t," + ",".join(f"q{j}" for j in range(1, 7))]
    lines += [",".join(repr(float(v)) for v in (ti, *qi)) for ti, qi in zip(t, path.q)]
    (root / "path.csv").write_text("\n".join(lines) + "\n")
    k = CellTruth().stiffness            # a calibration that knows the simulated cell's joints
    params = {f"k{j}": {"value": float(v), "std": 0.001 * float(v), "unit": "N*m/rad"} for j, v in enumerate(k, 1)}
    (root / "cal.json").write_text(json.dumps({
        "format": "elastocal.calibration/1", "robot": "HH-150", "created": "2026-12-02T00:00:00Z",
        "model": ["joint_stiffness"], "torque": "current", "parameters": params,
        "residual": {"rms": 1e-5, "max": 3e-5, "n": 100}, "data": []}))
    (root / "cell.toml").write_text('[cell]\nname = "rsi cell"\nrobot = "hh150"\n[guidance]\n'
                                    'url = "rsi://0.0.0.0:59152?cycle_ms=4"\n')
    (root / "nocell.toml").write_text('[cell]\nname = "no guidance"\nrobot = "hh150"\n')
    return root


def _cycles(log: pathlib.Path) -> list[dict]:
    with open(log, "rb") as f:
        return [json.loads(m.data) for _, c, m in make_reader(f).iter_messages(topics=[lf.TOPIC_STREAM_CYCLE])]


def _events(log: pathlib.Path) -> list[dict]:
    with open(log, "rb") as f:
        return [json.loads(m.data) for _, c, m in make_reader(f).iter_messages(topics=[lf.TOPIC_EVENT])]


@pytest.mark.parametrize("argv,flag", [
    (["--cell", "{root}/cell.toml", "--yes"], "--yes"),       # a person answers unless the cell is simulated
    ([], "--cell"),                                            # no cell and no --sim
    (["--cell", "{root}/nocell.toml"], "guidance"),
    (["--sim", "--sim-speed", "0"], "--sim-speed"),
    (["--cell", "{root}/cell.toml", "--sim-speed", "2"], "--sim-speed"),
    (["--sim", "--wrench", "1,2"], "--wrench"),
    (["--cell", "{root}/cell.toml", "--sim-realtime"], "--sim-realtime"),   # a real controller keeps its own clock
])
def test_bad_input_is_one_line_and_exit_2(files, capsys, argv, flag):
    out = files / "bad.mcap"
    code = main(["stream", "--calibration", str(files / "cal.json"), "--path", str(files / "path.csv"),
                 "--out", str(out), *[a.format(root=files) for a in argv]])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and flag in err[0], err
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize("argv,guidance,source", [
    (["--sim"], "egm", "sensor"),
    (["--cell", "{root}/cell.toml", "--sim", "--source", "currents"], "rsi", "currents"),
])
def test_the_stream_brings_the_tool_onto_the_plan_through_each_controller(files, capsys, argv, guidance, source):
    out = files / f"{guidance}-{source}.mcap"
    code = main(["stream", "--calibration", str(files / "cal.json"), "--path", str(files / "path.csv"),
                 "--out", str(out), "--sim-speed", "1", "--yes", "--force", "--json",
                 *[a.format(root=files) for a in argv]])
    obj = json.loads(capsys.readouterr().out)
    assert code == 0 and obj["status"] == "completed", obj
    assert (obj["guidance"], obj["source"]) == (guidance, source)
    truth = obj["truth"]
    # the process deflects the uncompensated tool by millimetres; the stream removes nearly all of it
    assert truth["uncompensated"]["rms"] > 1e-3
    assert truth["stream"]["rms"] < 0.05 * truth["uncompensated"]["rms"]
    assert truth["stream"]["rms"] < truth["offline_mean_wrench"]["rms"]
    cycles = _cycles(out)
    assert len(cycles) == obj["cycles"]
    assert sum(c["late"] is not None for c in cycles) == obj["late_cycles"]
    assert {c["wrench_source"] for c in cycles} == {source}
    kinds = [e["kind"] for e in _events(out)]
    assert kinds[0] == "procedure_start" and kinds[-1] == "procedure_end" and "answer" in kinds


def _run(files, tmp_path, spec, **options):
    from elastocal.commands.stream import simulated_stream_cell

    out = tmp_path / "fault.mcap"
    opts = StreamOptions(out=out, simulate=spec, **options)
    try:
        return run_online(simulated_stream_cell("egm"), str(files / "cal.json"), str(files / "path.csv"), opts,
                          AutoUI(quiet=True)), out
    except DeviceError as exc:
        return exc, out


def _spec(**kw) -> GuidedCellSpec:
    return GuidedCellSpec(start_wrench=(0, 0, 500, 0, 0, 0), end_wrench=(0, 0, 1500, 0, 0, 0), duration_s=PATH_S,
                          **kw)


@pytest.mark.slow
def test_a_sensor_that_goes_silent_stops_the_stream_by_the_watchdog(files, tmp_path):
    exc, out = _run(files, tmp_path, _spec(sensor_silent_after_s=1.0))
    assert isinstance(exc, WatchdogFault) and exc.cause is LateCause.FORCE
    records = exc.outcome.records
    assert [r.late for r in records[-3:]] == [LateCause.FORCE] * 3
    events = _events(out)
    assert events[-2]["kind"] == "fault" and events[-2]["error"] == "WatchdogFault"
    assert events[-1]["kind"] == "procedure_end" and events[-1]["status"] == "failed"


@pytest.mark.slow
def test_lost_controller_messages_are_counted_and_silence_is_typed(files, tmp_path):
    lost = frozenset({100, 101, 250})
    exc, out = _run(files, tmp_path, _spec(faults=Faults(lost_cycles=lost, silent_from_cycle=400)),
                    source=None)
    assert type(exc).__name__ == "ControllerLost"
    records = exc.outcome.records
    assert sum(r.lost_before for r in records) == 3
    gaps = [e for e in _events(out) if e["kind"] == "gap" and "lost" in e.get("text", "")]
    assert sum(e["missing"] for e in gaps) == 3
    assert _events(out)[-1]["status"] == "failed"


@pytest.mark.slow
def test_a_correction_at_its_limit_is_clamped_and_logged(files, tmp_path):
    from elastocal.stream.correction import Limits
    from elastocal.stream.loop import StreamSettings

    limits = Limits(max_rad=float(np.radians(0.005)), max_rate_rad_s=float(np.radians(0.5)))
    outcome, out = _run(files, tmp_path, _spec(), settings=StreamSettings(limits=limits))
    assert outcome.status == "completed"
    sent = np.array([r.correction for r in outcome.records])
    assert np.max(np.abs(sent)) <= limits.max_rad + 1e-15
    cycles = _cycles(out)
    assert any(c["limited"] for c in cycles)
    assert all(max(abs(v) for v in c["wanted_rad"]) > limits.max_rad for c in cycles if c["limited"]
               and c["late"] is None and c["cycle"] > 300)
    end = _events(out)[-1]
    assert end["limited_cycles"] == sum(c["limited"] for c in cycles) > 0
