"""Tiny benchmark helpers: best-of-N wall time, peak memory, and a JSON record per benchmark.

Each ``bench_*.py`` is run in its own process by ``run_all.py`` so its peak resident memory
is its own.
"""

from __future__ import annotations

import importlib.util
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

RESULTS = Path(__file__).resolve().parent / "results"
ROOT = Path(__file__).resolve().parents[1]


def load_test_module(relative_path: str, name: str) -> ModuleType:
    """Import a test file (e.g. ``tests/core/stages/test_impulse_realdata.py``) to reuse its protocol.

    The evaluation scripts print the full figures for exactly what the tests assert, so they
    share the test's data preparation instead of copying it.
    """
    spec = importlib.util.spec_from_file_location(name, ROOT / relative_path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def best_time(fn: Callable[[], object], repeat: int = 3,
              clock: Callable[[], float] = time.perf_counter) -> float:
    """Best time of ``repeat`` calls, in seconds: wall time, or with ``clock=time.process_time``
    the process CPU time (all threads), which other jobs on a shared machine do not inflate."""
    best = float("inf")
    for _ in range(repeat):
        t0 = clock()
        fn()
        best = min(best, clock() - t0)
    return best


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def record(name: str, values: dict) -> Path:
    """Write ``results/<name>.json`` and print it."""
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(values, indent=2) + "\n")
    print(json.dumps({name: values}, indent=2))
    return path


def rerun_under_xvfb(script: str, name: str, args: list[str]) -> int | None:
    """For a benchmark that needs a display: ``None`` when there is one (run here); else the
    exit code of ``script`` re-run under ``xvfb-run`` (a skip recorded as ``name`` when there
    is no xvfb-run either)."""
    if os.environ.get("DISPLAY") or os.environ.get("_DSLRXR_UNDER_XVFB") == "1":
        return None
    if shutil.which("xvfb-run") is None:
        record(name, {"skipped": "no X display and no xvfb-run"})
        return 0
    env = {**os.environ, "_DSLRXR_UNDER_XVFB": "1"}
    return subprocess.call(["xvfb-run", "-a", "-s", "-screen 0 1600x1000x24", sys.executable, script, *args],
                           env=env)
