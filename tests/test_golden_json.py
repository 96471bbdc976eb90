"""Every ``--json`` object on the simulated datasets is what it was (issue 11: behaviour
unchanged while the code is moved and split).

The golden files in ``tests/data/golden/`` were made by this very test from the code
before the restructuring (``ELASTOCAL_WRITE_GOLDEN=1 python -m pytest
tests/test_golden_json.py``). A change that is *meant* to change an output (a new
optional field, a better fit) regenerates them the same way, and the diff of the
golden files shows the reviewer exactly what changed. Floats are compared to 1e-9
relative: the last bits may move when a sum is reordered, nothing else may.

Paths are written relative to the test's data folder (``<DATA>``); wall-clock fields
(the calibration file's ``created``, the plan's ``time_s``) are left out.
"""

from __future__ import annotations

import json
import math
import os
import pathlib

import pytest

from elastocal.cli import main

GOLDEN = pathlib.Path(__file__).parent / "data" / "golden"
WRITE = os.environ.get("ELASTOCAL_WRITE_GOLDEN") == "1"
REL = 1e-9
#: below this a float is rounding noise (a residual of 1e-16 m), compared absolutely
TINY = 1e-15
SMALL = ["--poses", "6", "--loads", "2", "--repeats", "2"]

#: name -> (command line with {d} for the data folder); sims first, the rest read their output
DATASETS = {
    "sim_static_none": ["sim", "static", "--hidden", "none", "--seed", "3", *SMALL, "--out", "{d}/s0", "--json"],
    "sim_static_link_compliance": ["sim", "static", "--hidden", "link_compliance", "--seed", "4",
                                   "--poses", "8", "--loads", "2", "--repeats", "2", "--out", "{d}/lc", "--json"],
    "sim_static_backlash": ["sim", "static", "--hidden", "backlash", "--seed", "6", *SMALL, "--out", "{d}/bl",
                            "--json"],
    "sim_static_thermal_drift": ["sim", "static", "--hidden", "thermal_drift", "--seed", "7", *SMALL,
                                 "--out", "{d}/td", "--json"],
    "sim_static_static_friction": ["sim", "static", "--hidden", "static_friction", "--seed", "8", *SMALL,
                                   "--out", "{d}/sf", "--json"],
    "sim_runs_friction": ["sim", "runs", "--hidden", "friction", "--seed", "5", "--out", "{d}/rf", "--json"],
    "sim_runs_none": ["sim", "runs", "--hidden", "none", "--seed", "9", "--out", "{d}/r0", "--json"],
}


def _tables(folder: str, *, runs: bool = False) -> list[str]:
    return ["--robot", f"{{d}}/{folder}/robot.toml", "--runs" if runs else "--static",
            f"{{d}}/{folder}/{'runs' if runs else 'static'}.csv"]


RUN_MODEL = "compensator,gravity,coulomb_friction,viscous_friction,load_dependent_friction"
COMMANDS = {
    "identify_static": ["identify", *_tables("s0"), "--json"],
    "identify_static_out": ["identify", *_tables("s0"), "--out", "{d}/s0/cal.json", "--json"],
    "identify_force_first_order": ["identify", *_tables("s0"), "--torque", "force", "--form", "first-order",
                                   "--json"],
    "identify_link_compliance": ["identify", *_tables("lc"), "--model", "joint_stiffness,link_compliance",
                                 "--json"],
    "identify_backlash": ["identify", *_tables("bl"), "--model", "joint_stiffness,backlash", "--json"],
    "identify_thermal_drift": ["identify", *_tables("td"), "--model", "joint_stiffness,thermal_drift", "--json"],
    "identify_log": ["identify", "{d}/s0/log.mcap", "--json"],
    "identify_runs": ["identify", *_tables("rf", runs=True), "--model", RUN_MODEL, "--json"],
    "identify_runs_none": ["identify", *_tables("r0", runs=True), "--model",
                           "compensator,coulomb_friction,viscous_friction", "--json"],
    "identify_static_and_runs": ["identify", "--robot", "{d}/s0/robot.toml", "--static", "{d}/s0/static.csv",
                                 "--runs", "{d}/r0/runs.csv", "--model", "joint_stiffness,compensator,gravity,"
                                 "coulomb_friction,viscous_friction", "--json"],
    # refusals: the exit code and the one line on stderr are part of the contract too
    "refused_runs_alone": ["identify", *_tables("r0", runs=True), "--json"],
    "refused_unknown_effect": ["identify", *_tables("s0"), "--model", "joint_stiffness,wobble", "--json"],
    "refused_run_effect_on_static": ["identify", *_tables("s0"), "--model", "joint_stiffness,viscous_friction",
                                     "--json"],
    "diagnose_static_none": ["diagnose", *_tables("s0"), "--json"],
    "diagnose_static_force": ["diagnose", *_tables("s0"), "--torque", "force", "--json"],
    "diagnose_link_compliance": ["diagnose", *_tables("lc"), "--json"],
    "diagnose_backlash": ["diagnose", *_tables("bl"), "--json"],
    "diagnose_thermal_drift": ["diagnose", *_tables("td"), "--json"],
    "diagnose_static_friction": ["diagnose", *_tables("sf"), "--torque", "force", "--json"],
    "diagnose_runs_friction": ["diagnose", *_tables("rf", runs=True), "--json"],
    "diagnose_runs_none": ["diagnose", *_tables("r0", runs=True), "--json"],
    "diagnose_log": ["diagnose", "{d}/lc/log.mcap", "--json"],
    "export_static_log": ["export", "{d}/s0/log.mcap", "--out", "{d}/export_s0", "--json"],
    "export_runs_log": ["export", "{d}/rf/log.mcap", "--out", "{d}/export_rf", "--json"],
    "compensate": ["compensate", "--robot", "{d}/s0/robot.toml", "--calibration", "{d}/s0/cal.json",
                   "--path", "{d}/path.csv", "--wrench", "0,0,-1500,0,0,0", "--out", "{d}/comp.csv", "--json"],
    "plan": ["plan", "--robot", "{d}/s0/robot.toml", "--test-pose", "0.3,0.5,-0.3,0.2,1.0,0.1",
             "--load", "800,-300,-600", "--f-max", "1100", "--tracker-position", "3.5,0,1.2",
             "--candidates", "200", "--check-poses", "3", "--seed", "2", "--out", "{d}/plan.toml", "--json"],
}
#: output files compared like the --json objects (JSON documents), with their volatile keys
FILES = {"calibration_static": ("{d}/s0/cal.json", ("created",))}
#: wall-clock fields of a --json object, left out of the comparison
VOLATILE = {"plan": ("planning_s", "time_s")}


def _normalise(obj, d: str):
    if isinstance(obj, dict):
        return {k: _normalise(v, d) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_normalise(v, d) for v in obj]
    if isinstance(obj, str):
        return obj.replace(d, "<DATA>")
    return obj


def _diff(got, want, where: str = "$") -> list[str]:
    """Differences between two JSON values: floats to REL relative, everything else exactly."""
    if isinstance(want, bool) or want is None or isinstance(want, str):
        return [] if got == want and type(got) is type(want) else [f"{where}: {got!r} != {want!r}"]
    if isinstance(want, (int, float)):
        if isinstance(got, bool) or not isinstance(got, (int, float)):
            return [f"{where}: {got!r} != {want!r}"]
        if isinstance(want, int) and isinstance(got, int):
            return [] if got == want else [f"{where}: {got} != {want}"]
        if math.isnan(want) or math.isnan(got):
            return [] if math.isnan(want) and math.isnan(got) else [f"{where}: {got!r} != {want!r}"]
        return [] if math.isclose(got, want, rel_tol=REL, abs_tol=TINY) else [f"{where}: {got!r} != {want!r}"]
    if isinstance(want, dict):
        if not isinstance(got, dict):
            return [f"{where}: {type(got).__name__} != object"]
        out = [f"{where}: keys {sorted(set(got) ^ set(want))} differ"] if set(got) != set(want) else []
        if list(got) != list(want) and not out:
            out.append(f"{where}: key order {list(got)} != {list(want)}")
        for k in want:
            if k in got:
                out += _diff(got[k], want[k], f"{where}.{k}")
        return out
    if isinstance(want, list):
        if not isinstance(got, list) or len(got) != len(want):
            return [f"{where}: length {len(got) if isinstance(got, list) else '-'} != {len(want)}"]
        out = []
        for i, (g, w) in enumerate(zip(got, want)):
            out += _diff(g, w, f"{where}[{i}]")
        return out
    raise TypeError(f"{where}: unexpected {type(want).__name__}")


@pytest.fixture(scope="module")
def outputs(tmp_path_factory) -> dict:
    """Run every command once on freshly simulated data; name -> normalised JSON."""
    import contextlib
    import io

    from elastocal.compensation.files import write_path
    from elastocal.compensation.ik import yang_path
    from elastocal.formats.robot_toml import load_robot

    d = str(tmp_path_factory.mktemp("golden"))
    result = {}

    def run(name, argv):
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main([a.replace("{d}", d) for a in argv])
        obj = json.loads(out.getvalue()) if code == 0 else None
        if isinstance(obj, dict):
            obj = {k: v for k, v in obj.items() if k not in VOLATILE.get(name, ())}
        result[name] = {"exit": code, "json": _normalise(obj, d)}
        if code != 0:
            result[name]["stderr"] = _normalise(err.getvalue(), d)

    for name, argv in DATASETS.items():
        run(name, argv)
    write_path(pathlib.Path(d) / "path.csv", yang_path(load_robot(pathlib.Path(d) / "s0" / "robot.toml"),
                                                       step_m=0.1))
    for name, argv in COMMANDS.items():
        run(name, argv)
    for name, (path, volatile) in FILES.items():
        doc = json.loads(pathlib.Path(path.replace("{d}", d)).read_text(encoding="utf-8"))
        result[name] = {"exit": 0, "json": _normalise({k: v for k, v in doc.items() if k not in volatile}, d)}
    return result


NAMES = [*DATASETS, *COMMANDS, *FILES]


@pytest.mark.parametrize("name", NAMES)
def test_json_output_is_unchanged(outputs, name):
    path = GOLDEN / f"{name}.json"
    got = outputs[name]
    if WRITE:
        GOLDEN.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(got, indent=1, sort_keys=False) + "\n", encoding="utf-8")
    want = json.loads(path.read_text(encoding="utf-8"))
    problems = _diff(got, want)
    assert not problems, f"{name}: {len(problems)} differences, first: " + "; ".join(problems[:8])


def test_the_comparison_can_fail():
    """The comparison sees a change in the tenth digit, a missing key and a changed word."""
    want = {"a": 1.0, "b": [1, "x"], "c": {"d": None}}
    assert not _diff({"a": 1.0 + 1e-12, "b": [1, "x"], "c": {"d": None}}, want)
    assert _diff({"a": 1.0 + 1e-8, "b": [1, "x"], "c": {"d": None}}, want)
    assert _diff({"a": 1.0, "b": [1, "y"], "c": {"d": None}}, want)
    assert _diff({"a": 1.0, "b": [1, "x"], "c": {}}, want)
    assert _diff({"a": 1, "b": [1, "x"], "c": {"d": None}}, {"a": 1.5, "b": [1, "x"], "c": {"d": None}})
    assert _diff({"a": True}, {"a": 1})
