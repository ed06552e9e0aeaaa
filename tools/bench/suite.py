"""The test suite's cost: README's test command (``pytest``), timed as CI meets it.

    python tools/bench/suite.py [PYTEST_ARGS ...]

Wall time and the CPU time of pytest and every process under it (its xdist workers, the
CLI runs they fork), and the outcome line; the budget is 12 minutes on the 2-core CI
machine, the goal 10.
"""

from __future__ import annotations

import resource
import subprocess
import sys
import time

from records import Row, record


def main() -> None:
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", *sys.argv[1:]], capture_output=True, text=True)
    wall = time.perf_counter() - start
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    lines = [line for line in done.stdout.splitlines() if line.strip()]
    outcome = lines[-1].strip("= ") if lines else f"exit {done.returncode}"
    print("\n".join(lines[-25:]))
    print(f"pytest: {wall:.0f} s wall, {usage.ru_utime:.0f} s user + {usage.ru_stime:.0f} s system; {outcome}")
    record(
        [
            Row(
                "the whole test suite, README's `pytest` (one xdist worker per core)",
                f"{wall:.0f} s wall ({usage.ru_utime + usage.ru_stime:.0f} s of CPU); {outcome} (budget 720 s, goal "
                "600 s)",
            )
        ]
    )
    sys.exit(done.returncode)


if __name__ == "__main__":
    main()
