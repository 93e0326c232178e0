"""Run every ``benchmarks/bench_*.py`` in its own process and summarise the results.

Usage: ``python benchmarks/run_all.py [NAME_FILTER]``. Each script prints and records its own
figures (see ``_harness.record``); this runner adds the wall time and peak RSS per script and
exits non-zero when a script fails or reports ``"pass": false``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main() -> int:
    pattern = sys.argv[1] if len(sys.argv) > 1 else ""
    scripts = sorted(p for p in HERE.glob("bench_*.py") if pattern in p.stem)
    failed = []
    summary = {}
    for script in scripts:
        print(f"== {script.name}", flush=True)
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, str(script)], cwd=HERE.parent)
        _, status, usage = os.wait4(proc.pid, 0)
        code = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t0
        summary[script.stem] = {"exit": code, "wall_s": round(wall, 1),
                                "peak_rss_mb": round(usage.ru_maxrss / 1024.0, 1)}
        result = HERE / "results" / f"{script.stem.removeprefix('bench_')}.json"
        if code != 0:
            failed.append(script.name)
        elif result.exists() and json.loads(result.read_text()).get("pass") is False:
            failed.append(script.name)
    print(json.dumps(summary, indent=2))
    if failed:
        print("benchmarks that failed or missed their target: " + ", ".join(failed), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
