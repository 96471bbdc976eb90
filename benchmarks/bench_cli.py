"""Start-up time of ``elastocal --help`` and ``--version`` against a bare interpreter.

    python benchmarks/bench_cli.py [--repeat N]

Each figure is the median wall time of N fresh interpreters (subprocesses), measured in the
same run as ``python -c pass`` (the limit: the interpreter's own start-up), so the ratio and
the difference mean the same on a loaded machine. Goal: ``--help`` under 0.2 s.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

CODE = "import sys; from elastocal.cli import main; sys.argv[1:] = {argv!r}; raise SystemExit(main())"


def median_s(command: list[str], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=15)
    args = parser.parse_args()
    bare = median_s([sys.executable, "-c", "pass"], args.repeat)
    print(f"{'command':<26} {'median s':>9} {'x python -c pass':>17} {'minus start-up s':>17}")
    print(f"{'python -c pass':<26} {bare:>9.3f} {1.0:>17.2f} {0.0:>17.3f}")
    for argv in (["--help"], ["--version"], ["identify", "--help"]):
        t = median_s([sys.executable, "-c", CODE.format(argv=argv)], args.repeat)
        print(f"{'elastocal ' + ' '.join(argv):<26} {t:>9.3f} {t / bare:>17.2f} {t - bare:>17.3f}")
    print("goal: elastocal --help < 0.2 s")


if __name__ == "__main__":
    main()
