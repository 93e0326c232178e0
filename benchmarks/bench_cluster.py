"""Batch throughput: ``dslrxr run`` with ``--jobs 1``, the process pool and a LocalCluster.

N frames (default 8 of 24 MP, 6000x4000 colour, with a flat and a dark) go through the whole
pipeline three times, each run a separate ``dslrxr`` process writing its own folder:
``--jobs 1``; ``--jobs 2`` (process pool); ``--scheduler local --jobs 2`` (a 2-worker dask
LocalCluster, one thread each). Reports files per second, the ratios, the peak resident
memory of the largest process of each run (sampled high-water marks of the command and every
worker it started) and, for the cluster, each worker's own peak as the command prints it; checks that
the three runs wrote the same bytes. Goal on a 2-core machine: the cluster >= 1.8x the
one-process throughput and within 5 % of the process pool.

Where the CPU time goes, per run: the CPU time of the command and all its processes
(``wait4``, exact) over the wall time, i.e. the cores it kept busy; user and system time and
minor page faults; each process's own CPU time, sampled from ``/proc`` every 0.1 s (the
command, the pool's or the cluster's workers, helper processes; the last tenth of a second of
a process may be missed); the pipeline's own stage timings summed over the files' sidecars
(wall time inside each stage: a stage slowed by the other process shows here). From
``--jobs 1``'s figure, the bound on any parallel speedup on this machine (cores / cores one
process keeps busy). Idle core-seconds: cores x wall - CPU (``idle_core_s``, which other work on
the machine inflates), and the run's own (``idle_core_s_own``: the cores left without one of its
threads running or waiting for a core, sampled every 0.1 s; other work delays those threads but
does not put them to sleep, so this one is expected to hold under load (not checked by this benchmark), but it counts dask's own threads as
work), with its timeline (``runnable_threads_per_second``: where in the run the cores idle), and
each process's own (``cpu_per_second_by_process``: a worker idle at the start, waiting for the
reference, or at the end while the other finishes). When each file was reported finished
(``files_finished_at_s``) and the seconds from the last one to the command's end
(``after_last_file_s``: closing the workers, the interpreter's exit).

Every mode runs ``--rounds`` times (default 2) in ABBA order (``--jobs 1``, pool, cluster, then
cluster, pool, ``--jobs 1``), and throughput comes from each mode's mean wall time: this
machine's speed drifts by 15-20 % within minutes (the CPU time of the same ``--jobs 1`` work
varied that much between two runs eight minutes apart), which a single run in fixed order puts on
whichever mode ran in the slow minutes. ``--two-commands`` adds two ``--jobs 1`` commands run at
once on half the files each (no scheduler at all). Last, code-independent kernels (an interpreter
loop, streaming adds, random gathers) run alone and as two processes at once
(``machine_two_process_speedup``): what the machine gives two processes of any code at that time.

The frames are one generated phantom shifted by a few pixels per file (generating eight 24 MP
phantoms would take longer than the benchmark). Usage:
``python benchmarks/bench_cluster.py [--frames N] [--height H --width W] [--modes ...] [--rounds R]``.
Other work on the machine slows the parallel runs first: the 1-minute load average before and
after each run is recorded with the figures.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import record  # noqa: E402

MODES = {"jobs_1": ["--jobs", "1"], "process_pool_2": ["--jobs", "2"],
         "local_cluster_2": ["--scheduler", "local", "--jobs", "2"]}
_TICKS = os.sysconf("SC_CLK_TCK")


def _write_frames(folder: Path, n: int, shape: tuple[int, int]) -> tuple[list[Path], Path, Path]:
    from napari_dslrxr.core.io import write_tiff
    from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph

    frames = make_dslr_radiograph(shape, seed=0)
    shots = [write_tiff(folder / f"frame_{i:02d}.tif", np.roll(frames.raw_rgb, 8 * i, axis=1)) for i in range(n)]
    return shots, write_tiff(folder / "flat.tif", frames.flat), write_tiff(folder / "dark.tif", frames.dark)


def _proc_stat(pid: int) -> tuple[int, float, float, int] | None:
    """(parent pid, user s, system s, minor faults) of a live process, from /proc."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()  # after the command name, which may hold spaces
    return int(fields[1]), int(fields[11]) / _TICKS, int(fields[12]) / _TICKS, int(fields[7])


def _runnable_threads(pid: int) -> int:
    """How many threads of a live process are running or waiting for a core (state R)."""
    count = 0
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with contextlib.suppress(OSError):
                text = Path(f"/proc/{pid}/task/{task}/stat").read_text()
                count += text[text.rindex(")") + 2] == "R"
    except OSError:
        pass
    return count


def _peak_rss_mb(pid: int) -> float | None:
    """A live process's peak resident memory so far (its high-water mark), MiB."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return None


def _role(pid: int, root: int, parent_role: str | None = None) -> str:
    if pid == root:
        return "command"
    if parent_role == "fork server":  # a LocalCluster's worker forked from it (same command line)
        return "dask worker"
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return "other"
    for marker, role in (("resource_tracker", "resource tracker"), ("forkserver", "fork server"),
                         ("spawn_main", "dask worker"), ("napari_dslrxr.cli", "pool worker")):
        if marker in cmdline:
            return role
    return "other"


class _ProcessSampler(threading.Thread):
    """Samples the CPU time of a process and all its descendants every ``interval`` seconds;
    keeps each process's last figures (so a process's last interval may be missed). New
    descendants are looked for in all of ``/proc`` every ``scan_every`` samples only: the scan
    reads every process's stat (about 7 ms with 100 processes: 7 % of a core at every sample,
    taken from the runs measured, the parallel ones most); a process found late keeps its CPU
    time (the kernel's counts are totals) and misses only its first cells of the timeline."""

    def __init__(self, root: int, interval: float = 0.1, scan_every: int = 10):
        super().__init__(daemon=True)
        self.root, self.interval, self.seen, self.done = root, interval, {}, threading.Event()
        self.scan_every = scan_every
        self.runnable: list[tuple[float, int]] = []  # (seconds since start, threads running or runnable)
        self.cpu: list[tuple[float, dict[int, float]]] = []  # (seconds since start, CPU s so far per process)
        self.t0 = time.perf_counter()

    def _descendants(self) -> set[int]:
        parents = {}
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                stat = _proc_stat(int(entry))
                if stat is not None:
                    parents[int(entry)] = stat[0]
        family = {self.root}
        grew = True
        while grew:  # descendants of the root
            grew = False
            for pid, ppid in parents.items():
                if ppid in family and pid not in family:
                    family.add(pid)
                    grew = True
        return family

    def run(self) -> None:
        family: set[int] = set()
        sample = 0
        while not self.done.is_set():
            if sample % self.scan_every == 0:
                family = self._descendants()
            sample += 1
            stats = {pid: stat for pid in family if (stat := _proc_stat(pid)) is not None}
            family = {self.root} | stats.keys()  # the ended ones go
            now = time.perf_counter() - self.t0
            self.runnable.append((now, sum(map(_runnable_threads, stats))))
            self.cpu.append((now, {pid: stats[pid][1] + stats[pid][2] for pid in stats}))
            for pid in sorted(stats):  # a fork server (its role seen first) before the workers it forked
                parent_role = self.seen.get(stats[pid][0], {}).get("role")
                role = self.seen.get(pid, {}).get("role") or _role(pid, self.root, parent_role)
                _, user, system, faults = stats[pid]
                peak = _peak_rss_mb(pid) or self.seen.get(pid, {}).get("peak_rss_mb", 0.0)
                self.seen[pid] = {"role": role, "user_s": user, "system_s": system, "minor_faults": faults,
                                  "peak_rss_mb": peak}
            self.done.wait(self.interval)

    def idle_core_seconds(self, cores: int) -> float:
        """Core-seconds the run left without a thread of its own to run: sum over the samples of
        ``cores`` minus the threads of the command's processes that were running or waiting for a
        core. Other work on the machine delays those threads but does not put them to sleep, so
        this counts what the run itself leaves idle (waits, serial parts), load or not."""
        total, previous = 0.0, 0.0
        for t, n in self.runnable:
            total += max(0, cores - n) * (t - previous)
            previous = t
        return round(total, 2)

    def runnable_per_second(self) -> str:
        """The threads running or runnable, averaged over each second of the run (a timeline)."""
        buckets: dict[int, list[int]] = {}
        for t, n in self.runnable:
            buckets.setdefault(int(t), []).append(n)
        return " ".join(f"{sum(v) / len(v):.1f}" for _, v in sorted(buckets.items()))

    def cpu_per_second(self) -> dict[str, str]:
        """Each process's cores kept busy, averaged over each second of the run (a per-process
        timeline: where a worker idles at the start, waiting, or at the end), keyed by role and pid;
        '.' before a process started and after it ended."""
        last = int(self.cpu[-1][0]) + 1 if self.cpu else 0
        timelines = {}
        for pid, figures in sorted(self.seen.items()):
            if figures["role"] in ("resource tracker", "fork server", "other"):
                continue
            points = [(t, c[pid]) for t, c in self.cpu if pid in c]
            cells = []
            for second in range(last):
                inside = [(t, c) for t, c in points if second <= t < second + 1]
                if not inside:
                    cells.append(".")
                    continue
                before = [(t, c) for t, c in points if t < second]
                (t_start, c_start), (t_end, c_end) = before[-1] if before else inside[0], inside[-1]
                cells.append(f"{(c_end - c_start) / (t_end - t_start):.1f}" if t_end > t_start else "0.0")
            timelines[f"{figures['role']} {pid}"] = " ".join(cells)
        return timelines

    def processes(self) -> list[dict]:
        return [{"pid": pid, **{k: round(v, 2) if isinstance(v, float) else v for k, v in fig.items()}}
                for pid, fig in sorted(self.seen.items())]


def _stage_seconds(out: Path) -> dict[str, float]:
    """The pipeline's stage timings summed over the files (from the TIFF outputs' sidecars)."""
    total: dict[str, float] = {}
    for sidecar in sorted(out.glob("*.tif.json")):
        for stage, seconds in json.loads(sidecar.read_text())["timings_s"].items():
            total[stage] = total.get(stage, 0.0) + float(seconds)
    return {k: round(v, 2) for k, v in sorted(total.items(), key=lambda kv: -kv[1])}


def _run(args: list[str]) -> dict:
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "napari_dslrxr.cli", "run", *args], stderr=subprocess.PIPE,
                            text=True)
    sampler = _ProcessSampler(proc.pid)
    sampler.start()
    lines = []  # (seconds since start, line): when each file was reported finished
    for line in proc.stderr:
        lines.append((time.perf_counter() - t0, line))
    stderr = "".join(line for _, line in lines)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    sampler.done.set()
    sampler.join()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"dslrxr run {' '.join(args)} failed:\n{stderr}")
    found = re.search(r"peak memory per worker: ([\d, ]+) MiB", stderr)
    cpu = usage.ru_utime + usage.ru_stime  # the command and every worker process it started and reaped
    processes = sampler.processes()
    by_role: dict[str, float] = {}
    for p in processes:
        by_role[p["role"]] = round(by_role.get(p["role"], 0.0) + p["user_s"] + p["system_s"], 2)
    finished = [round(t, 2) for t, line in lines if re.match(r"\[\d+/\d+\] ", line)]
    return {"wall_s": round(wall, 2), "cpu_s": round(cpu, 1), "cores_busy_on_average": round(cpu / wall, 2),
            # when each file was reported finished (the last two apart: the tail where one process
            # works alone), and the seconds from the last one to the command's end (shutdown, exit)
            "files_finished_at_s": finished,
            "after_last_file_s": round(wall - finished[-1], 2) if finished else None,
            "cpu_per_second_by_process": sampler.cpu_per_second(),
            # idle core-seconds: the cores' time the run did not use (cores x wall - CPU; grows with
            # other work on the machine), and what the run itself left without a runnable thread
            "idle_core_s": round((os.cpu_count() or 1) * wall - cpu, 1),
            "idle_core_s_own": sampler.idle_core_seconds(os.cpu_count() or 1),
            "runnable_threads_per_second": sampler.runnable_per_second(),
            "user_s": round(usage.ru_utime, 1), "system_s": round(usage.ru_stime, 1),
            "minor_faults": usage.ru_minflt, "cpu_s_by_role": by_role, "processes": processes,
            # the largest high-water mark sampled (wait4's maxrss would count what the benchmark held when
            # it started the command: the kernel keeps a process's peak across exec)
            "max_process_rss_mb": round(max((p["peak_rss_mb"] for p in processes), default=0.0), 1),
            "worker_peak_rss_mb": [float(v) for v in found.group(1).split(",")] if found else None,
            "load_average_1min_before": round(load_before, 2), "load_average_1min_after": round(os.getloadavg()[0], 2)}


def _two_commands(common_files: list[str], reference: list[str], out: Path) -> dict:
    """Two ``dslrxr run --jobs 1`` commands started together, each on half the files, into one
    folder: no scheduler, no pool, nothing shared. Its speedup over ``--jobs 1`` is what this
    machine gives this pipeline on two cores when nothing coordinates the work (each command
    prepares the flat/dark reference itself, which the schedulers do once)."""
    load_before = os.getloadavg()[0]
    halves = [common_files[0::2], common_files[1::2]]
    logs = [tempfile.TemporaryFile("w+") for _ in halves]  # not pipes: a full pipe would stall a command
    t0 = time.perf_counter()
    procs = {subprocess.Popen([sys.executable, "-m", "napari_dslrxr.cli", "run", *half, *reference, "-o", str(out),
                               "--jobs", "1"], stderr=log, text=True).pid: log for half, log in zip(halves, logs)}
    cpu, ended = 0.0, []
    for _ in procs:  # in the order they end
        pid, status, usage = os.wait4(-1, 0)
        ended.append(time.perf_counter() - t0)
        if os.waitstatus_to_exitcode(status) != 0:
            procs[pid].seek(0)
            raise SystemExit(f"dslrxr run (two commands) failed:\n{procs[pid].read()}")
        cpu += usage.ru_utime + usage.ru_stime
    for log in logs:
        log.close()
    wall = max(ended)
    return {"wall_s": round(wall, 2), "cpu_s": round(cpu, 1), "cores_busy_on_average": round(cpu / wall, 2),
            "commands_ended_at_s": [round(t, 2) for t in ended], "stage_s_summed_over_files": _stage_seconds(out),
            "load_average_1min_before": round(load_before, 2), "load_average_1min_after": round(os.getloadavg()[0], 2)}


# Code-independent kernels, each run alone and then as two processes at once: how much of two cores
# this machine delivers to work with no shared state (the host's other tenants, shared caches and
# memory bandwidth, clock boost on one busy core). Run minutes after the pipeline's runs, they tell the
# machine's state then, not a bound on those runs.
_KERNELS = {  # name: (set-up, timed work)
    # integer arithmetic in the interpreter: registers and L1 only
    "python_loop": ("s = 0", "for i in range(25_000_000):\n    s += i * i % 7"),
    # streaming adds over 24 M float32 (96 MB each): memory bandwidth
    "numpy_stream": ("import numpy as np\na = np.ones(24_000_000, np.float32); b = a + 1; c = np.empty_like(a)",
                     "for _ in range(60):\n    np.add(a, b, out=c)"),
    # random gathers from a 24 M float32 array: cache and memory latency, as the impulse stage's lookups
    "numpy_gather": ("import numpy as np\nrng = np.random.default_rng(0)\na = rng.random(24_000_000, np.float32)\n"
                     "idx = rng.integers(0, a.size, 4_000_000)", "for _ in range(25):\n    a.take(idx)"),
}
_TIMED = "import sys, time\nexec(sys.argv[1])\nt = time.perf_counter()\nexec(sys.argv[2])\nprint(time.perf_counter() - t)"


def _kernel_seconds(kernel: tuple[str, str], copies: int) -> float:
    """Wall seconds of the kernel's timed part: the slowest of ``copies`` processes started together
    (their set-up is not timed, so the pair's timed parts overlap but for the set-up's spread)."""
    procs = [subprocess.Popen([sys.executable, "-c", _TIMED, *kernel], stdout=subprocess.PIPE, text=True)
             for _ in range(copies)]
    return max(float(p.communicate()[0]) for p in procs)


def machine_two_process_speedup(rounds: int = 2) -> dict:
    """Per kernel: alone and as a pair, alternated ``rounds`` times; the speedup is
    2 x (best time alone) / (best time of the pair's slower process)."""
    result = {}
    for name, kernel in _KERNELS.items():
        alone, pair = [], []
        for _ in range(rounds):
            alone.append(_kernel_seconds(kernel, 1))
            pair.append(_kernel_seconds(kernel, 2))
        result[name] = {"alone_s": [round(t, 2) for t in alone], "pair_s": [round(t, 2) for t in pair],
                        "speedup": round(2 * min(alone) / min(pair), 3)}
    return result


def _image_digests(out: Path) -> dict[str, str]:
    """sha256 of each TIFF and PNG a run wrote (8 x 24 MP outputs per run: digests, not bytes, are kept)."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(out.iterdir())
            if p.suffix in (".tif", ".png")}


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--height", type=int, default=4000)
    parser.add_argument("--width", type=int, default=6000)
    parser.add_argument("--modes", nargs="+", choices=list(MODES), default=list(MODES))
    parser.add_argument("--rounds", type=int, default=2,
                        help="runs of every mode, in ABBA order; throughput from the mean wall time")
    parser.add_argument("--two-commands", action="store_true",
                        help="also run two --jobs 1 commands at once, each on half the files")
    parser.add_argument("--no-machine", action="store_true", help="skip the code-independent kernels")
    parser.add_argument("--no-record", action="store_true", help="print only (a partial or proxy run)")
    opts = parser.parse_args()
    if opts.rounds < 1:
        parser.error("--rounds must be at least 1")
    shape = (opts.height, opts.width)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        shots, flat, dark = _write_frames(tmp, opts.frames, shape)
        print(f"wrote {opts.frames} frames of {shape[0]}x{shape[1]} in {time.perf_counter() - t0:.0f} s", flush=True)
        common = [*map(str, shots), "--flat", str(flat), "--dark", str(dark)]
        runs: dict[str, dict] = {}
        walls: dict[str, list[float]] = {name: [] for name in opts.modes}
        digests = []  # of every run's outputs; each run's folder is removed once read (about 1 GB each)
        for round_ in range(opts.rounds):
            # ABBA order: the machine's speed drifts by 15-20 % within minutes here, and a drift
            # linear in time then weighs every mode alike
            for name in (opts.modes if round_ % 2 == 0 else opts.modes[::-1]):
                out = tmp / f"{name}_{round_}"
                run = _run([*common, "-o", str(out), *MODES[name]])
                run["stage_s_summed_over_files"] = _stage_seconds(out)
                digests.append(_image_digests(out))
                shutil.rmtree(out)
                walls[name].append(run["wall_s"])
                runs.setdefault(name, run)  # the first run's details; every run's wall below
                print(name, round_, json.dumps({k: v for k, v in run.items() if k != "processes"}), flush=True)
        for name in opts.modes:
            runs[name]["wall_s_per_round"] = walls[name]
            runs[name]["files_per_min"] = round(60.0 * opts.frames / (sum(walls[name]) / len(walls[name])), 2)
        if opts.two_commands:
            runs["two_commands_jobs_1"] = _two_commands(list(map(str, shots)), ["--flat", str(flat), "--dark", str(dark)],
                                                        tmp / "two_commands_jobs_1")
            runs["two_commands_jobs_1"]["files_per_min"] = round(60.0 * opts.frames / runs["two_commands_jobs_1"]["wall_s"], 2)
            digests.append(_image_digests(tmp / "two_commands_jobs_1"))
            print("two_commands_jobs_1", json.dumps(runs["two_commands_jobs_1"]), flush=True)
        identical = all(d == digests[0] for d in digests[1:])
    values = {"frames": opts.frames, "shape": [*shape, 3], "cpus": os.cpu_count(), "runs": runs,
              "outputs_identical": identical}
    if not opts.no_machine:
        values["machine_two_process_speedup"] = machine_two_process_speedup()
        print("machine", json.dumps(values["machine_two_process_speedup"]), flush=True)
    if set(MODES) <= runs.keys():
        throughput = {k: v["files_per_min"] for k, v in runs.items()}
        values.update({
            "cluster_vs_jobs_1": round(throughput["local_cluster_2"] / throughput["jobs_1"], 3),
            "cluster_vs_process_pool": round(throughput["local_cluster_2"] / throughput["process_pool_2"], 3),
            "pool_vs_jobs_1": round(throughput["process_pool_2"] / throughput["jobs_1"], 3),
            # each round's cluster run against the same round's --jobs 1 run: the spread
            "cluster_vs_jobs_1_per_round": [round(j / c, 3) for j, c in zip(walls["jobs_1"], walls["local_cluster_2"])],
            # one process already keeps cores_busy_on_average cores busy: with the same CPU time per
            # file, n processes cannot go faster than cpus / that (the per-file CPU time only grows)
            "parallel_speedup_bound": round((os.cpu_count() or 1) / runs["jobs_1"]["cores_busy_on_average"], 2),
            **({"two_commands_vs_jobs_1": round(runs["two_commands_jobs_1"]["files_per_min"] / throughput["jobs_1"], 3)}
               if "two_commands_jobs_1" in runs else {}),
            "target": "cluster >= 1.8x jobs_1 and >= 0.95x process pool, on an otherwise idle 2-core machine",
        })
        values["pass"] = bool(identical and values["cluster_vs_jobs_1"] >= 1.8
                              and values["cluster_vs_process_pool"] >= 0.95)
    print(json.dumps({k: v for k, v in values.items() if k != "runs"}), flush=True)
    if not opts.no_record:
        record("cluster", values)
    return 0 if identical else 1


if __name__ == "__main__":
    sys.exit(main())
