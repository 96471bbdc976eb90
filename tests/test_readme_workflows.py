"""Every command of the README's "Try every command on simulated data" blocks runs, as
written, in an empty folder with only simulated data: the offline block in this process
(the view is started and stopped), the shop-floor block against a simulated cell served
by `elastocal sim serve` in a process of its own, as the README starts it."""

import json
import pathlib
import re
import shlex
import subprocess
import sys
import time

import pytest

from elastocal.cli import main

README = pathlib.Path(__file__).parents[1] / "README.md"
SECTION = "## Try every command on simulated data"


def readme_blocks() -> list[list[list[str]]]:
    """The ```bash blocks of the section, each a list of argv (without `elastocal`)."""
    text = README.read_text(encoding="utf-8")
    section = text[text.index(SECTION) + len(SECTION):]
    section = section[:section.index("\n## ")]
    blocks = []
    for body in re.findall(r"```bash\n(.*?)```", section, flags=re.S):
        commands = []
        for line in body.strip().splitlines():
            argv = shlex.split(line, comments=True)
            assert argv[0] == "elastocal", line
            commands.append(argv[1:])
        blocks.append(commands)
    return blocks


def workflow_commands() -> set[str]:
    """The commands of the README's Workflows table."""
    text = README.read_text(encoding="utf-8")
    table = text[text.index("## Workflows"):]
    table = table[:table.index("\n\n", table.index("| --- |"))]
    return set(re.findall(r"`elastocal (\w+)", table))


def test_the_blocks_cover_every_workflow_of_the_readme():
    offline, devices = readme_blocks()
    names = {argv[0] for argv in offline + devices}
    assert workflow_commands() <= names, workflow_commands() - names
    assert {"devices", "calibrate", "check", "schedule", "compensate", "import", "fleet"} <= names
    assert devices[0][:2] == ["sim", "serve"] and devices[0][-1] == "&"    # served in the background


def _view(argv: list[str]) -> None:
    """`view` serves until Ctrl-C: build its page on a free port, then stop it."""
    from elastocal.cli import build_parser
    from elastocal.commands.view import ViewPage, build_view

    args = build_parser("view")[0].parse_args(argv)
    args.notes = []
    page = ViewPage(build_view(args), port=0)
    assert page.url.startswith("http://127.0.0.1:")
    page.stop()


@pytest.mark.heavy
def test_every_offline_readme_workflow_runs_from_simulated_data(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    outputs = {}
    for argv in readme_blocks()[0]:
        if argv[0] == "view":
            _view(argv)
            continue
        code = main(argv)
        out = capsys.readouterr()
        assert code == 0, (argv, out.err)
        outputs[tuple(argv)] = out.out
    for f in ("sim/report.html", "sim/cal.json", "sim/export/static.csv", "drift.png", "runs/sweep.csv",
              "plan.toml", "abs/cal.json", "calibrated.toml", "calibrated.urdf", "history.sqlite",
              "path/path.csv", "path/compensated.csv", "path/compensated.src", "path/compensated.mod",
              "sim/imported.csv", "fleet.csv"):
        assert (tmp_path / f).stat().st_size > 0, f
    # the tracker software's points import to the simulated table itself
    from elastocal.formats.tables import read_static_table

    simulated, imported = (read_static_table(tmp_path / "sim" / f) for f in ("static.csv", "imported.csv"))
    assert list(imported.pose) == list(simulated.pose) and list(imported.marker) == list(simulated.marker)
    assert abs(imported.xyz - simulated.xyz).max() < 1e-9 and abs(imported.currents - simulated.currents).max() < 1e-12
    # the fleet's table has one row per log or table folder (export's), each identified
    import csv

    with open(tmp_path / "fleet.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["path"] for r in rows] == ["sim/export", "sim/log.mcap", "abs/log.mcap"], [r["path"] for r in rows]
    assert all(r["error"] == "" and float(r["k2"]) > 1e6 for r in rows)
    header = (tmp_path / "path/compensated.csv").read_text().splitlines()[0].split(",")
    assert header[:7] == ["t", "q1", "q2", "q3", "q4", "q5", "q6"] and "qc1" in header and "dz" in header
    _the_simulated_plant_shows_its_drift(tmp_path, outputs, capsys)


def _the_simulated_plant_shows_its_drift(root: pathlib.Path, outputs: dict, capsys) -> None:
    """The README's plant lines (sim plant, fleet check/identify --record, fleet history): the drifting
    cell fails its checks from the log its joint softened on, the others hold; the drift table shows the
    softening; a rerun with --record records nothing twice."""
    import sqlite3

    from elastocal.fleet.table import read_table

    truth = json.loads((root / "plant/truth.json").read_text())
    cells = [c["cell"] for c in truth["cells"]]
    drifting = [c for c in truth["cells"] if c["drift"]]
    assert len(cells) == 3 and len(drifting) == 1, truth
    drift = drifting[0]["drift"]
    # every check says what the truth says: recalibrate exactly for the drifted logs of the drifting cell
    rows = read_table(root / "checks.csv")
    assert len(rows) == sum(len(c["logs"]) for c in truth["cells"]) == 12
    expected = {str(pathlib.Path("plant", c["cell"], log["log"])): "recalibrate" if log["drifted"] else "holds"
                for c in truth["cells"] for log in c["logs"]}
    assert {r["path"]: r["decision"] for r in rows} == expected
    assert sum(v == "recalibrate" for v in expected.values()) == 2
    # the first calibrations were in the histories already; the later logs' are recorded once
    def printed(*words: str) -> str:
        """What the README's command starting with ``words`` printed."""
        (out,) = [out for argv, out in outputs.items() if argv[:len(words)] == words]
        return out

    assert "recorded 0 calibration(s) and 12 check(s) in 3 histories; 0 already recorded" \
        in printed("fleet", "check", "plant")
    assert "recorded 9 calibration(s) and 0 check(s) in 3 histories; 3 already recorded" \
        in printed("fleet", "identify", "plant")

    def counts() -> dict:
        out = {}
        for name in cells:
            with sqlite3.connect(root / "plant" / name / "history.sqlite") as db:
                out[name] = (db.execute("select count(*) from calibration").fetchone()[0],
                             db.execute("select count(*) from check_run").fetchone()[0])
        return out

    assert counts() == {name: (4, 4) for name in cells}
    # the drift table: the drifting cell's joint moved by the truth's change (its built stiffness is the
    # first calibration's truth), within 2 % of the stiffness; the others' within 2 %
    capsys.readouterr()      # what the view printed when it stopped
    assert main(["fleet", "history", "plant", "--json"]) == 0
    table = {c["cell"]: c for c in json.loads(capsys.readouterr().out)["cells"]}
    joint = f"k{drift['joint']}"
    for name, c in table.items():
        assert c["calibrations"] == 4 and c["checks"] == 4 and not c["error"], c
        change = c["drift"][joint]["change"]
        if name == drifting[0]["cell"]:
            assert abs(change + drift["fraction"]) < 0.02, (name, change)
            assert c["checks_failed"] == 2 and c["last_verdict"] == "recalibrate"
        else:
            assert abs(change) < 0.02, (name, change)
            assert c["checks_failed"] == 0 and c["last_verdict"] == "holds"
    line = next(x for x in printed("fleet", "history", "plant").splitlines()
                if x.split()[:1] == [drifting[0]["cell"]])
    assert "2 of 4" in line and f"{table[drifting[0]['cell']]['drift'][joint]['change'] * 100:+6.2f}%" in line
    # a rerun with --record records nothing twice
    assert main(["fleet", "identify", "plant", "--out", "plant-cals.csv", "--record", "--force"]) == 0
    assert "recorded 0 calibration(s) and 0 check(s) in 3 histories; 12 already recorded" in capsys.readouterr().out
    assert counts() == {name: (4, 4) for name in cells}
    # checked again, now against each cell's latest calibration: new evidence, recorded once; cell-02's logs
    # from before the change no longer agree with its (soft) current calibration
    for again, recorded in ((False, "recorded 0 calibration(s) and 12 check(s) in 3 histories; 0 already"),
                            (True, "recorded 0 calibration(s) and 0 check(s) in 3 histories; 12 already")):
        assert main(["fleet", "check", "plant", "--out", "checks.csv", "--record", "--force"]) == 0
        assert recorded in capsys.readouterr().out
        assert counts() == {name: (4, 8) for name in cells}
    decisions = {r["path"]: r["decision"] for r in read_table(root / "checks.csv")}
    assert decisions == {path: ("recalibrate" if path.startswith(f"plant/{drifting[0]['cell']}/")
                                and expected[path] == "holds" else "holds") for path in expected}


@pytest.mark.heavy
def test_every_shop_floor_readme_workflow_runs_on_the_served_simulated_cell(tmp_path, monkeypatch, capsys):
    """The second block as written: `sim serve ... &` in its own process, then devices, calibrate,
    plan, calibrate, identify, history add, check, schedule install and history against it."""
    monkeypatch.chdir(tmp_path)
    serve, *commands = readme_blocks()[1]
    cell = tmp_path / serve[serve.index("--write-cell") + 1]
    server = subprocess.Popen([sys.executable, "-m", "elastocal", *serve[:-1]], cwd=tmp_path,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120.0
        while not cell.exists():
            assert server.poll() is None, server.communicate()
            assert time.monotonic() < deadline, "sim serve wrote no cell config in 120 s"
            time.sleep(0.2)
        capsys.readouterr()
        outputs = {}
        for argv in commands:
            code = main(argv)
            out = capsys.readouterr()
            assert code == 0, (argv, out.err[-2000:])
            outputs[argv[0]] = out.out
        assert server.poll() is None, "the served cell stopped during the workflows"
    finally:
        server.terminate()           # SIGTERM: sim serve stops serving and exits 0
        try:
            rc = server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            raise
    assert rc == 0
    # what each step must have done
    assert "devices: drive J1, drive J2, drive J3, drive J4, drive J5, drive J6, tracker, controller" \
        in outputs["devices"]
    assert "(6/6 steps, completed)" in outputs["calibrate"], outputs["calibrate"]
    cal = json.loads((tmp_path / "cell-cal.json").read_text())
    # the served cell is the default simulated HH-150: k2 and k3 as its truth (docs/robots.md), within 1 %
    from elastocal.sims.cell import CellTruth

    truth = CellTruth().stiffness
    for j in (2, 3):
        assert cal["parameters"][f"k{j}"]["value"] == pytest.approx(truth[j - 1], rel=0.01)
    assert outputs["check"].startswith("HOLDS"), outputs["check"]
    assert "recorded as check 1 of calibration 1" in outputs["check"]
    assert list((tmp_path / "checks").glob("check-*.mcap"))
    service = (tmp_path / "units/elastocal-check.service").read_text()
    assert f"-m elastocal check --cell {cell}" in service and "--db cell-history.sqlite" in service
    assert "OnCalendar=Mon *-*-* 06:00:00" in (tmp_path / "units/elastocal-check.timer").read_text()
    assert "1 calibration(s), 1 check(s)" in outputs["history"]


def test_the_glossary_explains_every_effect_name():
    """The README's glossary says in words what each effect a diagnosis can name is."""
    from elastocal.model.effects import ALL_EFFECTS

    text = README.read_text(encoding="utf-8")
    glossary = text[text.index("## Glossary"):]
    glossary = glossary[:glossary.index("\n## ")]
    # `name` (words), or `a` and `b` (words shared)
    missing = [name for name in ALL_EFFECTS
               if not re.search(rf"`{name}`(\s+and\s+`\w+`)?\s+\([a-z]", glossary)]
    assert not missing, missing
    for word in ("noise floor", "ΔBIC", "exact form", "TPDO / SYNC"):
        assert f"**{word}" in glossary, word
