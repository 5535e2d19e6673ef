"""The heavy test cases that CI leaves out (``@pytest.mark.slow``), run as one benchmark.

CI runs the README's test command, which deselects them to stay within its time; they are
the full versions of checks CI runs at a smaller size (every model kind and parameter against
finite differences, the path-traced variants of the Mitsuba comparisons, the installed
stress suite, the recovery with shadows in view). This runs all of them and writes pytest's
summary and its slowest cases to ``benchmarks/results_slow_tests.txt``. It takes about an
hour on 2 cores.

Usage: python -m benchmarks.slow_tests [-k EXPRESSION] [--out PATH]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("-k", dest="expression", help="only the slow cases matching this "
                                                      "pytest expression")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results_slow_tests.txt"),
                        help="where to write the summary ('' for nowhere)")
    args = parser.parse_args(argv)
    command = [sys.executable, "-m", "pytest", "-q", "-m", "slow", "-p", "no:cacheprovider",
               "--durations=25", *(["-k", args.expression] if args.expression else [])]
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    print(result.stdout[-20000:], result.stderr[-5000:], sep="\n")
    if args.out:
        # The durations and the summary: the part of pytest's report after the progress dots.
        report = result.stdout
        tail = report[report.find("slowest"):] if "slowest" in report else report[-5000:]
        Path(args.out).write_text(f"python -m benchmarks.slow_tests, started {started}, "
                                  f"exit status {result.returncode}\n{tail}")
    return result.returncode


if __name__ == "__main__":
    sys.exit(main())
