"""The calibration history (acquisition/history.py, `elastocal history`):
records round-trip through SQLite, the current calibration is the latest,
drift follows the parameters, foreign files are refused, plots are written."""

import json
import sqlite3

import numpy as np
import pytest

from elastocal.acquisition.history import MAX_CHECK_RELATIVE_STD, History, iso_utc, plot_drift
from elastocal.acquisition.procedures import run_procedures
from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
from elastocal.formats.plan import LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.cli import main
from elastocal.errors import InputError
from elastocal.formats.calibration import (
    CalibratedParameter,
    Calibration,
    DataFile,
    Residual,
    file_sha256,
    write_calibration,
)
from elastocal.formats.robot_toml import bundled_robot
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.model.kinds import TorqueSource

DAY_NS = 86400 * 10**9
T0 = 1_767_600_000 * 10**9          # 2026-01-05


def calibration(k2: float, created: str) -> Calibration:
    params = tuple(CalibratedParameter(f"k{j}", v, v * 1e-3, "N*m/rad")
                   for j, v in enumerate((559e3, k2, 1829e3, 184e3, 171e3, 70e3), start=1))
    params += (CalibratedParameter("fc2", 180.0, 0.5, "N*m"),)
    return Calibration(robot="HH-150", created=created, model=("joint_stiffness", "coulomb_friction"),
                       torque=TorqueSource.CURRENT, parameters=params, residual=Residual(rms=8e-6, max=3e-5, n=216),
                       data=(DataFile("log.mcap", "ab" * 32),))


def check_result(k2: float, k2_std: float, unexplained: float) -> dict:
    return {"verdict": "holds", "deflection": {
        "rms_unexplained": unexplained, "noise_floor": 7.5e-6,
        "parameters": {"k2": {"calibrated": 1.435e6, "check": k2, "check_std": k2_std, "std": k2_std, "z": 0.0},
                       "k1": {"calibrated": 559e3, "check": 3e7, "check_std": 5e7, "std": 5e7, "z": 0.6}}}}


def test_records_round_trip_and_the_latest_calibration_is_current(tmp_path):
    db = tmp_path / "h.sqlite"
    with History(db) as h:
        first = h.add_calibration(calibration(1.435e6, "2026-01-05T08:00:00Z"), time_ns=T0, log_sha256="11" * 32,
                                  log_path="/cell/cal1.mcap", plan='name = "p"\n')
        h.add_check(calibration_id=first, time_ns=T0 + 7 * DAY_NS, verdict="holds", reasons=("fine",),
                    result=check_result(1.43e6, 2e3, 8e-6), log_sha256="22" * 32, log_path="/cell/c1.mcap")
        h.add_check(calibration_id=first, time_ns=T0 + 14 * DAY_NS, verdict="recalibrate", reasons=("k2 dropped",),
                    result=check_result(1.29e6, 2e3, 80e-6))
        second = h.add_calibration(calibration(1.29e6, "2026-01-19T09:00:00Z"), time_ns=T0 + 15 * DAY_NS)
    with History(db, create=False) as h:      # reopened: everything is on disk
        cals, checks, current = h.calibrations(), h.checks(), h.current()
        drift = h.drift()
    assert [c.id for c in cals] == [first, second] and current.id == second
    assert cals[0].calibration == calibration(1.435e6, "2026-01-05T08:00:00Z")
    assert cals[0].log_sha256 == "11" * 32 and cals[0].plan == 'name = "p"\n' and cals[1].plan is None
    assert cals[0].time == "2026-01-05T08:00:00Z" == iso_utc(T0)
    assert [c.verdict for c in checks] == ["holds", "recalibrate"] and checks[1].reasons == ("k2 dropped",)
    assert checks[0].result == check_result(1.43e6, 2e3, 8e-6)
    assert drift.names[:6] == tuple(f"k{j}" for j in range(1, 7)) and "fc2" in drift.names
    k2 = drift.names.index("k2")
    assert np.allclose(drift.calibration_value[:, k2], [1.435e6, 1.29e6])
    assert np.allclose(drift.check_value[:, k2], [1.43e6, 1.29e6])
    # a check that barely determines k1 stays out of the drift
    assert 5e7 / 3e7 > MAX_CHECK_RELATIVE_STD and np.all(np.isnan(drift.check_value[:, drift.names.index("k1")]))
    assert np.allclose(drift.check_unexplained_m, [8e-6, 80e-6])
    with History(db) as h:
        with pytest.raises(InputError, match="no calibration 99"):
            h.add_check(calibration_id=99, time_ns=T0, verdict="holds", reasons=(), result={})
        with pytest.raises(InputError, match="verdict"):
            h.add_check(calibration_id=first, time_ns=T0, verdict="maybe", reasons=(), result={})
        # the same data checked again against the same calibration is not recorded twice
        again = h.add_check(calibration_id=first, time_ns=T0 + 30 * DAY_NS, verdict="holds", reasons=("fine",),
                            result=check_result(1.43e6, 2e3, 8e-6), log_sha256="22" * 32, log_path="/copy.mcap")
        assert again == checks[0].id and len(h.checks()) == 2
        # against another calibration, it is a new check
        other = h.add_check(calibration_id=second, time_ns=T0 + 30 * DAY_NS, verdict="holds", reasons=(),
                            result={}, log_sha256="22" * 32)
        assert other not in (c.id for c in checks) and len(h.checks()) == 3


def test_foreign_and_missing_files_are_refused(tmp_path):
    text = tmp_path / "notes.sqlite"
    text.write_text("this is not a database, " * 100)
    with pytest.raises(InputError, match="not an elastocal history database"):
        History(text)
    other = tmp_path / "other.sqlite"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE things (x)")
    con.commit()
    con.close()
    with pytest.raises(InputError, match="another application"):
        History(other)
    with pytest.raises(InputError, match="history add"):
        History(tmp_path / "none.sqlite", create=False)
    with pytest.raises(InputError, match="folder"):
        History(tmp_path / "no" / "such" / "h.sqlite")
    newer = tmp_path / "newer.sqlite"
    History(newer).close()
    con = sqlite3.connect(newer)
    con.execute("UPDATE meta SET value = '99' WHERE key = 'schema_version'")
    con.commit()
    con.close()
    with pytest.raises(InputError, match="schema version 99"):
        History(newer)


def test_drift_plot_png_and_svg(tmp_path):
    with History(tmp_path / "h.sqlite") as h:
        cid = h.add_calibration(calibration(1.435e6, "a"), time_ns=T0)
        h.add_check(calibration_id=cid, time_ns=T0 + DAY_NS, verdict="recalibrate", reasons=("x",),
                    result=check_result(1.3e6, 1e3, 50e-6))
        h.add_calibration(calibration(1.3e6, "b"), time_ns=T0 + 2 * DAY_NS)
        drift = h.drift()
    plot_drift(drift, tmp_path / "d.png")
    plot_drift(drift, tmp_path / "d.svg")
    assert (tmp_path / "d.png").read_bytes()[:4] == b"\x89PNG"
    assert "<svg" in (tmp_path / "d.svg").read_text()
    with pytest.raises(InputError, match=r"\.png or \.svg"):
        plot_drift(drift, tmp_path / "d.jpg")


def test_history_command_add_and_show(tmp_path, capsys):
    cell = tmp_path / "cell.toml"
    cell.write_text('[cell]\nname = "c"\nrobot = "hh150"\nhistory = "db/history.sqlite"\n')
    (tmp_path / "db").mkdir()
    write_calibration(tmp_path / "cal.json", calibration(1.435e6, "2026-01-05T08:00:00Z"))
    # a real log with its plan: the plan is kept with the calibration
    robot = bundled_robot()
    plan_text = plan_toml(poses=[(0.2, 0.3, -0.4, 0.3, 1.0, 0.2)], loads=(LoadSpec("L1", mass_kg=60.0),),
                          markers=("R1",), repeats=2, reading_s=0.04,
                          settle=SettleSpec(speed_rad_s=2e-3, spread_m=60e-6, window_s=0.15, timeout_s=20.0))
    io = VirtualCellIO(SimCell(robot, CellTruth()), seed=1, timing=VirtualTiming(drive_rate_hz=100.0,
                                                                                 tracker_rate_hz=100.0))
    assert run_procedures(io, parse_plan(plan_text), tmp_path / "cal.mcap").status == "completed"
    assert main(["history", "add", "--cell", str(cell), "--calibration", str(tmp_path / "cal.json"),
                 "--log", str(tmp_path / "cal.mcap"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"db": str(tmp_path / "db" / "history.sqlite"), "calibration": 1}
    with History(tmp_path / "db" / "history.sqlite") as h:
        rec = h.current()
    assert rec.plan == plan_text and rec.log_sha256 == file_sha256(tmp_path / "cal.mcap")
    assert main(["history", "--cell", str(cell), "--plot", str(tmp_path / "drift.svg")]) == 0
    out = capsys.readouterr().out
    assert "1 calibration(s), 0 check(s)" in out and "1.4350" in out and (tmp_path / "drift.svg").exists()
    assert main(["history", "--db", str(tmp_path / "db" / "history.sqlite"), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["calibrations"][0]["parameters"]["k2"]["value"] == 1.435e6 and obj["checks"] == []
    assert obj["drift"]["k2"]["change"] == 0.0
    # bad input: one line, exit 2
    assert main(["history", "--cell", str(cell), "--calibration", "x.json"]) == 2
    assert "history add" in capsys.readouterr().err
    no_db = tmp_path / "bare.toml"
    no_db.write_text('[cell]\nrobot = "hh150"\n')
    assert main(["history", "--cell", str(no_db)]) == 2
    err = capsys.readouterr().err
    assert "no history database" in err and err.count("\n") == 1
    assert main(["history", "--db", str(tmp_path / "empty.sqlite")]) == 2
    assert "history add" in capsys.readouterr().err


# ------------------------------------------------------- the drift plot on a simulated history
@pytest.fixture(scope="module")
def simulated_history(tmp_path_factory):
    """A cell's history as `elastocal check` records it, from the simulated cell: a calibration
    (12 poses under 2 loads, UV/VU friction runs) that leaves k1 undetermined, then checks of an
    unchanged cell, joint 2 10 % softer, joint-3 Coulomb friction 50 % up, two runs-only checks
    whose friction failed, and a recorded check whose joint-3 friction reads -101.7 %."""
    import dataclasses

    from elastocal.acquisition.history import clean
    from elastocal.formats.calibration import calibration_from_fit
    from elastocal.diagnose.check import check_calibration
    from elastocal.identify.runs import identify_runs
    from elastocal.identify.static import identify_static
    from elastocal.sims.runs import FrictionPlan, default_run_truth, simulate_runs
    from elastocal.sims.static import StaticPlan, simulate_static

    friction = ("coulomb_friction", "viscous_friction", "load_dependent_friction")
    robot = bundled_robot()
    truth = default_run_truth(CellTruth())
    fit = identify_static(robot, simulate_static(robot, truth, seed=1, plan=StaticPlan(n_poses=12, n_loads=2)))
    obj = fit.to_json()
    runs = identify_runs(robot, simulate_runs(robot, truth, seed=2, sweeps=None, friction=FrictionPlan(samples=120)),
                         model=("joint_stiffness", *friction))
    obj["parameters"].update(runs.to_json()["parameters"])
    obj["model"] = obj["model"] + list(friction)
    cal = calibration_from_fit(robot.name, obj, created="2026-01-05T08:00:00Z")
    assert cal.find("k1").determined is False     # what the plot must not show as a finding

    def scaled(name, joint, factor):
        v = getattr(truth, name).copy()
        v[joint - 1] *= factor
        return dataclasses.replace(truth, **{name: v})

    cases = [(truth, True), (scaled("stiffness", 2, 0.9), True), (scaled("coulomb", 3, 1.5), True),
             (scaled("coulomb", 3, 0.3), False), (scaled("coulomb", 2, 1.6), False)]
    check_run = FrictionPlan(speeds_rad_s=(0.1,), loads=(("0", (0.0,) * 6),), samples=100)
    db = tmp_path_factory.mktemp("history") / "history.sqlite"
    results = []
    with History(db) as h:
        cid = h.add_calibration(cal, time_ns=T0)
        for i, (case, static) in enumerate(cases):
            res = check_calibration(
                robot, cal, runs=simulate_runs(robot, case, seed=530 + i, sweeps=None, friction=check_run),
                static=simulate_static(robot, case, seed=30 + i, plan=StaticPlan(n_poses=3, n_loads=1))
                if static else None)
            results.append(clean(res.to_json()))
            h.add_check(calibration_id=cid, time_ns=T0 + (i + 1) * DAY_NS, verdict=res.verdict, reasons=res.reasons,
                        result=results[-1])
        odd = json.loads(json.dumps(results[3]))           # friction measured against the calibration's sign
        odd["friction"]["joints"]["3"].update(measured=-0.017 * odd["friction"]["joints"]["3"]["predicted"])
        h.add_check(calibration_id=cid, time_ns=T0 + 6 * DAY_NS, verdict="recalibrate", reasons=("friction",),
                    result=odd)
        results.append(odd)
        drift = h.drift()
    return drift, results, db


def _inside(ax, xy_display: np.ndarray) -> np.ndarray:
    """Which display points lie inside the axes box (its edges included)."""
    box = ax.get_window_extent()
    return ((xy_display[:, 0] >= box.x0 - 0.5) & (xy_display[:, 0] <= box.x1 + 0.5)
            & (xy_display[:, 1] >= box.y0 - 0.5) & (xy_display[:, 1] <= box.y1 + 0.5))


def test_drift_plot_draws_every_check_point_inside_its_panel(simulated_history, tmp_path):
    """Every value drawn lies inside its panel (a -101.7 % point too), no legend covers a panel, the
    undetermined k1 does not set the stiffness scale, and each friction failure is drawn (filled red),
    joint by joint, exactly where the checks failed."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PathCollection

    from elastocal.acquisition.history import drift_figure

    drift, results, db = simulated_history
    fig = drift_figure(drift)
    FigureCanvasAgg(fig).draw()
    titles = [ax.get_title() for ax in fig.axes]
    stiff, other, friction, checks = fig.axes
    assert titles[2].startswith("friction") and titles[3].startswith("checks")
    n_points = 0
    for ax in fig.axes:
        for line in ax.lines:
            x, y = line.get_xdata(), line.get_ydata()
            if line.get_marker() in ("None", None, "", "_", "|") or len(x) == 0:   # lines, error bar caps
                continue
            xy = line.get_transform().transform(np.column_stack([ax.convert_xunits(x), y]).astype(float))
            assert _inside(ax, xy).all(), (ax.get_title(), line.get_label(), y)
            n_points += len(x)
        for coll in ax.collections:          # scatter markers (error bars may leave a panel: see drift_plot.py)
            offsets = coll.get_offsets()
            if isinstance(coll, PathCollection) and len(offsets):
                xy = coll.get_offset_transform().transform(np.asarray(offsets, dtype=float))
                assert _inside(ax, xy).all(), (ax.get_title(), coll.get_label())
                n_points += len(offsets)
        legend = ax.get_legend()
        assert legend is not None
        box = legend.get_window_extent()
        assert fig.bbox.x0 <= box.x0 and box.x1 <= fig.bbox.x1 + 1 and fig.bbox.y0 <= box.y0 <= fig.bbox.y1
        for other_ax in fig.axes:             # beside its panel, over none
            assert not box.overlaps(other_ax.get_window_extent()), (ax.get_title(), other_ax.get_title())
            if other_ax is not ax:
                assert not box.overlaps(other_ax.get_legend().get_window_extent())
    assert n_points > 40
    # every check is on the checks panel: its deflection, or (runs only) on the axis
    assert sum(len(c.get_offsets()) for c in checks.collections) == len(results) == 6
    # the stiffness scale follows the values: the 10 % softer joint 2 stands out, k1 (std ~300 %) is an x
    lo, hi = stiff.get_ylim()
    assert hi - lo < 40.0
    k2_checks = [line for line in stiff.lines if line.get_marker() == "o" and line.get_mfc() == "none"
                 and line.get_color() == stiff.get_legend_handles_labels()[0][1][0].get_color()]
    assert k2_checks and min(np.min(line.get_ydata()) for line in k2_checks) == pytest.approx(-10.0, abs=2.5)
    assert any(label.startswith("k1 (x on the edge: not determined)") for label in stiff.get_legend_handles_labels()[1])
    # friction: the failed (check, joint) pairs are exactly the checks' own
    expected = set()
    for i, res in enumerate(results):
        fr = res["friction"]
        level = fr.get("alpha", 0.0) / len(fr["joints"])
        for joint, f in fr["joints"].items():
            rel = f["measured"] / f["predicted"] - 1.0
            if f["p_value"] < level and abs(rel) > fr["tolerance"]:
                expected.add((i, int(joint), round(rel * 100.0, 6)))
    assert {(i, j) for i, j, _ in expected} == {(2, 3), (3, 3), (4, 2), (5, 3)}
    failed = [line for line in friction.lines if line.get_label() == "failed the check"]
    assert len(failed) == 1 and failed[0].get_mfc() != "none"
    check_days = (drift.check_time_ns - drift.check_time_ns[0]) // DAY_NS
    drawn = {(int(round(float(friction.convert_xunits(x) - friction.convert_xunits(
        drift.check_time_ns[0].astype("datetime64[ns]"))))), round(float(y), 6))
        for x, y in zip(failed[0].get_xdata(), failed[0].get_ydata())}
    assert drawn == {(int(check_days[i]), rel) for i, _, rel in expected}
    assert any(abs(rel + 101.7) < 1e-9 for _, _, rel in expected)
    # and the history command writes it, marking k1's drift as no finding
    assert main(["history", "--db", str(db), "--plot", str(tmp_path / "drift.png")]) == 0
    assert (tmp_path / "drift.png").read_bytes()[:4] == b"\x89PNG"


def test_an_undetermined_calibration_is_no_drift_finding(simulated_history, capsys):
    drift, _, db = simulated_history
    from elastocal.acquisition.history import drift_summary

    summary = drift_summary(drift)
    assert summary["k1"]["determined"] is False and summary["k2"]["determined"] is True
    assert main(["history", "--db", str(db)]) == 0
    out = capsys.readouterr().out
    assert "k1" in out and "(n/d: a calibration does not determine it, no finding)" in out
    assert main(["history", "--db", str(db), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["drift"]["k1"]["determined"] is False and obj["drift"]["fc3"]["determined"] is True
