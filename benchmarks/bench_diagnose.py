"""Time to diagnose a 60-pose static dataset against every effect.

    python benchmarks/bench_diagnose.py [--poses 60] [--repeat 3]

60 poses x 3 loads x 3 markers x 3 repeats (1620 deflection components), a
hidden link compliance. Prints, per torque source, the median wall time of
diagnose_static (the model, every candidate effect fitted and tested, the
residual summaries) and of one identify_static for comparison, with the
verdict, so speed and result are read together; then the report page's
rendering time.

The limit is 10 s on 2 cores for the current-based diagnosis (every
candidate, located compliance included). A shared machine's load changes wall
times by several times, so the limit is also measured in the same run, as in
bench_absolute.py: one Pinocchio forward kinematics timed in batches between the
diagnoses, the fastest batch (the machine unloaded) against the median one (as
loaded as the diagnoses); the diagnosis' time at the fastest batch's speed is
its time on this machine unloaded. Both ratios to the limit are printed.
"""

from __future__ import annotations

import argparse
import statistics
import time


from elastocal.diagnose.static import diagnose_static
from elastocal.report.html import render_report
from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.static import build_dataset, identify_static
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static
from elastocal.model.kinds import TorqueSource


def _median_time(fn, repeat: int):
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


from fk_limit import fk_batches_s  # benchmarks/fk_limit.py: the run's own FK limit

LIMIT_S = 10.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--hidden", default="link_compliance")
    args = parser.parse_args()
    robot = bundled_robot()
    t0 = time.perf_counter()
    table = simulate_static(robot, CellTruth().with_hidden(args.hidden), seed=60,
                            plan=StaticPlan(n_poses=args.poses))
    t_sim = time.perf_counter() - t0
    ds = build_dataset(table)
    print(f"dataset: {args.poses} poses, {len(table)} rows, {3 * ds.n_deflections} deflection components, "
          f"hidden {args.hidden} (simulated in {t_sim:.2f} s)")
    print(f"{'torque':<8} {'identify s':>10} {'diagnose s':>10} {'candidates':>10} {'tested':>6}  verdict")
    diag = None
    fk = fk_batches_s(robot, batches=5)
    t_current = None
    for torque in (TorqueSource.CURRENT, TorqueSource.FORCE):
        t_fit, _ = _median_time(lambda: identify_static(robot, ds, torque=torque), args.repeat)
        t_diag, diag_t = _median_time(lambda: diagnose_static(robot, ds, torque=torque), args.repeat)
        fk += fk_batches_s(robot, batches=5)
        if torque == TorqueSource.CURRENT:
            t_current = t_diag
        n_all = len(diag_t.candidates) + len(diag_t.not_testable)
        print(f"{torque:<8} {t_fit:>10.3f} {t_diag:>10.3f} {n_all:>10} {len(diag_t.candidates):>6}  "
              f"{diag_t.verdict} ({diag_t.fit.rms * 1e6:.1f} -> {diag_t.final.rms * 1e6:.1f} um, "
              f"floor {diag_t.final.noise_floor * 1e6:.1f} um)")
        if torque == TorqueSource.CURRENT:
            diag = diag_t
    fastest, typical = min(fk), statistics.median(fk)
    unloaded = t_current * fastest / typical
    print(f"diagnose (current): {t_current:.2f} s wall, {t_current / LIMIT_S:.2f} of the {LIMIT_S:.0f} s limit; "
          f"{t_current / typical:,.0f} x one forward kinematics ({typical * 1e6:.2f} µs median, "
          f"{fastest * 1e6:.2f} µs fastest batch: machine load factor {typical / fastest:.2f})")
    print(f"  at this machine's unloaded speed: {unloaded:.2f} s; {unloaded / LIMIT_S:.2f} of the "
          f"{LIMIT_S:.0f} s limit ({'met' if unloaded < LIMIT_S else 'NOT met'})")
    t_rep, page = _median_time(lambda: render_report(robot, diag), 1)
    print(f"report page: {t_rep:.2f} s, {len(page.encode('utf-8')) / 1e6:.2f} MB")


if __name__ == "__main__":
    main()
