"""Batch throughput: ``dslrxr run`` with ``--jobs 1``, the process pool and a LocalCluster.

N frames (default 8 of 24 MP, 6000x4000 colour, with a flat and a dark) go through the whole
pipeline three times, each run a separate ``dslrxr`` process writing its own folder:
``--jobs 1``; ``--jobs 2`` (process pool); ``--scheduler local --jobs 2`` (a 2-worker dask
LocalCluster, one thread each). Reports files per second, the ratios, the peak resident
memory of the largest process of each run (``wait4``: the command and every worker it
started) and, for the cluster, each worker's own peak as the command prints it; the CPU time
of each run (all its processes) over its wall time, i.e. the cores it kept busy on average,
and from ``--jobs 1``'s figure the bound on any parallel speedup on this machine (cores / cores
one process keeps busy, since the CPU time per file does not shrink when files run side by
side); checks that the three runs wrote the same bytes. Goal on a 2-core machine: the cluster
>= 1.8x the one-process throughput and within 5 % of the process pool.

The frames are one generated phantom shifted by a few pixels per file (generating eight 24 MP
phantoms would take longer than the benchmark). Usage:
``python benchmarks/bench_cluster.py [--frames N] [--height H --width W]``. Other work on the
machine slows the parallel runs first: the 1-minute load average before and after each run
is recorded with the figures.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import record  # noqa: E402


def _write_frames(folder: Path, n: int, shape: tuple[int, int]) -> tuple[list[Path], Path, Path]:
    from napari_dslrxr.core.io import write_tiff
    from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph

    frames = make_dslr_radiograph(shape, seed=0)
    shots = [write_tiff(folder / f"frame_{i:02d}.tif", np.roll(frames.raw_rgb, 8 * i, axis=1)) for i in range(n)]
    return shots, write_tiff(folder / "flat.tif", frames.flat), write_tiff(folder / "dark.tif", frames.dark)


def _run(args: list[str]) -> dict:
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "napari_dslrxr.cli", "run", *args], stderr=subprocess.PIPE,
                            text=True)
    stderr = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"dslrxr run {' '.join(args)} failed:\n{stderr}")
    found = re.search(r"peak memory per worker: ([\d, ]+) MiB", stderr)
    cpu = usage.ru_utime + usage.ru_stime  # the command and every worker process it started and reaped
    return {"wall_s": round(wall, 2), "cpu_s": round(cpu, 1), "cores_busy_on_average": round(cpu / wall, 2),
            "max_process_rss_mb": round(usage.ru_maxrss / 1024.0, 1),
            "worker_peak_rss_mb": [float(v) for v in found.group(1).split(",")] if found else None,
            "load_average_1min_before": round(load_before, 2), "load_average_1min_after": round(os.getloadavg()[0], 2)}


def _images(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.suffix in (".tif", ".png")}


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--height", type=int, default=4000)
    parser.add_argument("--width", type=int, default=6000)
    opts = parser.parse_args()
    shape = (opts.height, opts.width)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        shots, flat, dark = _write_frames(tmp, opts.frames, shape)
        print(f"wrote {opts.frames} frames of {shape[0]}x{shape[1]} in {time.perf_counter() - t0:.0f} s", flush=True)
        common = [*map(str, shots), "--flat", str(flat), "--dark", str(dark)]
        runs = {}
        for name, extra in (("jobs_1", ["--jobs", "1"]), ("process_pool_2", ["--jobs", "2"]),
                            ("local_cluster_2", ["--scheduler", "local", "--jobs", "2"])):
            runs[name] = _run([*common, "-o", str(tmp / name), *extra])
            runs[name]["files_per_min"] = round(60.0 * opts.frames / runs[name]["wall_s"], 2)
            print(name, runs[name], flush=True)
        identical = _images(tmp / "jobs_1") == _images(tmp / "process_pool_2") == _images(tmp / "local_cluster_2")
    throughput = {k: v["files_per_min"] for k, v in runs.items()}
    values = {
        "frames": opts.frames, "shape": [*shape, 3], "cpus": os.cpu_count(), "runs": runs,
        "cluster_vs_jobs_1": round(throughput["local_cluster_2"] / throughput["jobs_1"], 3),
        "cluster_vs_process_pool": round(throughput["local_cluster_2"] / throughput["process_pool_2"], 3),
        "pool_vs_jobs_1": round(throughput["process_pool_2"] / throughput["jobs_1"], 3),
        # one process already keeps cores_busy_on_average cores busy: with the same CPU time per
        # file, n processes cannot go faster than cpus / that (the per-file CPU time only grows)
        "parallel_speedup_bound": round((os.cpu_count() or 1) / runs["jobs_1"]["cores_busy_on_average"], 2),
        "outputs_identical": identical,
        "target": "cluster >= 1.8x jobs_1 and >= 0.95x process pool, on an otherwise idle 2-core machine",
    }
    values["pass"] = bool(identical and values["cluster_vs_jobs_1"] >= 1.8 and values["cluster_vs_process_pool"] >= 0.95)
    record("cluster", values)
    return 0 if identical else 1


if __name__ == "__main__":
    sys.exit(main())
