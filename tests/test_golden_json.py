"""Every ``--json`` object on the simulated datasets is what it was: a change of method
shows, a change of CPU or library version does not.

The golden files in ``tests/data/golden/`` are made by this very test
(``ELASTOCAL_WRITE_GOLDEN=1 python -m pytest tests/test_golden_json.py``). A change that is
*meant* to change an output (a new optional field, a better fit) regenerates them the same
way, and the diff of the golden files shows the reviewer exactly what changed.

The comparison is the one rule of ``tests/helpers/golden_tolerance.py``: a fitted
parameter's value to 0.01 of its std, a p-value to 1e-4 and every other float to 1e-5 relative (or below the
rounding noise of the numbers beside it), integers, strings, booleans and null exactly,
lists by length and element by element. So the goldens pass with another BLAS kernel
(:func:`test_goldens_hold_on_another_blas_kernel`) and fail on a tenth of a std
(:func:`test_a_tenth_of_a_std_fails`).

Paths are written relative to the test's data folder (``<DATA>``); wall-clock fields
(the calibration file's ``created``, the plan's ``time_s``) are left out.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import pathlib
import subprocess
import sys

import pytest
from golden_tolerance import STD_FRACTION, diff

from elastocal.cli import main

GOLDEN = pathlib.Path(__file__).parent / "data" / "golden"
WRITE = os.environ.get("ELASTOCAL_WRITE_GOLDEN") == "1"
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
             "--candidates", "200", "--check-poses", "3", "--loads-per-pose", "2", "--seed", "2",
             "--out", "{d}/plan.toml", "--json"],
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
        # the digests are checked here, against the files they name (the golden checks their form)
        for entry in doc.get("data", []):
            result[name].setdefault("digests", []).append(
                (entry["sha256"], hashlib.sha256(pathlib.Path(entry["path"]).read_bytes()).hexdigest()))
    return result


NAMES = [*DATASETS, *COMMANDS, *FILES]


@pytest.mark.parametrize("name", NAMES)
def test_json_output_is_unchanged(outputs, name):
    path = GOLDEN / f"{name}.json"
    got = {k: v for k, v in outputs[name].items() if k != "digests"}
    if WRITE:
        GOLDEN.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(got, indent=1, sort_keys=False) + "\n", encoding="utf-8")
    want = json.loads(path.read_text(encoding="utf-8"))
    problems = diff(got, want)
    assert not problems, f"{name}: {len(problems)} differences, first: " + "; ".join(problems[:8])


def test_calibration_names_the_digest_of_its_data(outputs):
    digests = outputs["calibration_static"]["digests"]
    assert digests and all(written == actual for written, actual in digests)


def test_the_comparison_can_fail():
    """The comparison lets the last digits move, and sees a changed digit, key, word or type."""
    want = {"a": 1.0, "b": [1, "x"], "c": {"d": None}}
    assert not diff({"a": 1.0 + 1e-8, "b": [1, "x"], "c": {"d": None}}, want)
    assert diff({"a": 1.0 + 1e-5, "b": [1, "x"], "c": {"d": None}}, want)
    assert diff({"a": 1.0, "b": [1, "y"], "c": {"d": None}}, want)
    assert diff({"a": 1.0, "b": [2, "x"], "c": {"d": None}}, want)
    assert diff({"a": 1.0, "b": [1, "x", 3], "c": {"d": None}}, want)
    assert diff({"a": 1.0, "b": [1, "x"], "c": {}}, want)
    assert diff({"a": 1.0, "b": [1, "x"], "c": {"d": False}}, want)
    assert diff({"a": 1, "b": [1, "x"], "c": {"d": None}}, {"a": 1.5, "b": [1, "x"], "c": {"d": None}})
    assert diff({"a": True}, {"a": 1})
    # rounding noise beside a large number, and in an object with a unit, is compared absolutely
    assert not diff([0.9, 3e-17], [0.9, 1e-16])
    assert diff([0.9, 3e-7], [0.9, 1e-7])
    assert not diff({"rms": 4e-17, "unit": "m"}, {"rms": 2e-16, "unit": "m"})
    assert diff({"rms": 1.0001e-5, "unit": "m"}, {"rms": 1e-5, "unit": "m"})
    assert not diff({"sha256": "0" * 64}, {"sha256": "f" * 64})
    assert diff({"sha256": "0" * 63}, {"sha256": "f" * 64})


def _parameters(obj, where="$"):
    """(path, object) of every fitted parameter (an object with value and std) in a JSON value."""
    if isinstance(obj, dict):
        if isinstance(obj.get("value"), float) and isinstance(obj.get("std"), float) and obj["std"] > 0:
            yield where, obj
        for k, v in obj.items():
            yield from _parameters(v, f"{where}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _parameters(v, f"{where}[{i}]")


def test_a_tenth_of_a_std_fails():
    """Every fitted parameter of every golden file: moved by 0.1 std the comparison fails and
    names it, moved by a tenth of the tolerance it passes."""
    checked = 0
    for path in sorted(GOLDEN.glob("*.json")):
        want = json.loads(path.read_text(encoding="utf-8"))
        for where, _ in _parameters(want):
            for fraction, fails in ((0.1, True), (-0.1, True), (0.1 * STD_FRACTION, False)):
                got = copy.deepcopy(want)
                dict(_parameters(got))[where]["value"] += fraction * dict(_parameters(got))[where]["std"]
                problems = diff(got, want)
                assert bool(problems) is fails, (path.name, where, fraction, problems)
                assert not fails or problems[0].startswith(where + ".value")
            checked += 1
    assert checked > 100


def _kernel(env: dict) -> str | None:
    """The OpenBLAS kernel numpy runs under ``env`` (None: numpy's BLAS is no OpenBLAS)."""
    code = ("import numpy, threadpoolctl; print(next((i.get('architecture') for i in "
            "threadpoolctl.threadpool_info() if i.get('internal_api') == 'openblas'), None))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    name = out.stdout.strip()
    return None if name == "None" else name


@pytest.mark.parametrize("coretype", [
    "Sandybridge",
    pytest.param("Haswell", marks=pytest.mark.heavy),
    pytest.param("Prescott", marks=pytest.mark.heavy),
])
def test_goldens_hold_on_another_blas_kernel(coretype, tmp_path):
    """The goldens pass with numpy's OpenBLAS forced to another CPU's kernel, whose last
    digits differ (``OPENBLAS_CORETYPE``, read when numpy loads: so in a new process)."""
    if WRITE:
        pytest.skip("writing the golden files")
    env = {k: v for k, v in os.environ.items() if not k.startswith("ELASTOCAL_")}
    here = _kernel(env)
    env["OPENBLAS_CORETYPE"] = coretype
    forced = _kernel(env)
    if here is None or forced == here:
        pytest.skip(f"numpy's BLAS runs the {coretype} kernel here already, or is no OpenBLAS")
    run = subprocess.run([sys.executable, "-m", "pytest", __file__, "-k", "test_json_output_is_unchanged",
                          "-n", "0", "-m", "", "-p", "no:cacheprovider", "--basetemp", str(tmp_path / "t")],
                         env=env, capture_output=True, text=True, cwd=pathlib.Path(__file__).parents[1])
    assert run.returncode == 0, f"kernel {forced} (here {here}):\n" + run.stdout[-3000:]
    assert f"{len(NAMES)} passed" in run.stdout
