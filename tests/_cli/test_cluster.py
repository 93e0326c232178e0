"""``dslrxr run --scheduler``: a batch on dask.distributed, run as a user would.

Each test starts real worker processes (one thread each) and runs the ``dslrxr`` process
against them: a LocalCluster started by the command itself, and an external scheduler and
worker (``python -m distributed.cli.dask_scheduler`` / ``dask_worker``) whose worker or
scheduler the test kills in the middle of a batch. Outputs are compared byte for byte with
``--jobs 1`` (the process-pool-free reference).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from napari_dslrxr.cli import main
from napari_dslrxr.core.io import file_sha256, write_tiff
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph

pytest.importorskip("distributed", reason="dask.distributed is an optional extra")

RUN_TIMEOUT_S = 180


def _dslrxr(*args: str, timeout: float = RUN_TIMEOUT_S, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "napari_dslrxr.cli", *args], capture_output=True,
                          text=True, timeout=timeout, env=None if env is None else {**os.environ, **env})


def _write_batch(folder: Path, shape: tuple[int, int], n: int) -> tuple[list[Path], Path, Path]:
    folder.mkdir(parents=True, exist_ok=True)
    shots = []
    for seed in range(n):
        frames = make_dslr_radiograph(shape, seed=seed)
        shots.append(write_tiff(folder / f"shot{seed}.tif", frames.raw_rgb))
    return shots, write_tiff(folder / "flat.tif", frames.flat), write_tiff(folder / "dark.tif", frames.dark)


@pytest.fixture(scope="module")
def small_batch(tmp_path_factory):
    """Four small frames, their flat and dark, and a broken file."""
    folder = tmp_path_factory.mktemp("small")
    shots, flat, dark = _write_batch(folder, (160, 240), 4)
    bad = folder / "broken.tif"
    bad.write_bytes(b"II*\x00" + b"\x00" * 20)
    return {"shots": shots, "flat": flat, "dark": dark, "bad": bad}


@pytest.fixture(scope="module")
def slow_batch(tmp_path_factory):
    """Frames that take about a second each, so a worker can be killed in the middle of one."""
    folder = tmp_path_factory.mktemp("slow")
    shots, flat, dark = _write_batch(folder, (600, 900), 3)
    reference = folder / "jobs1"  # what --jobs 1 writes, to compare with
    assert main(["run", *map(str, shots), "--flat", str(flat), "--dark", str(dark), "-o", str(reference)]) == 0
    return {"shots": shots, "flat": flat, "dark": dark, "reference": _images(reference)}


def _images(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.suffix in (".tif", ".png", ".dcm")}


def _sidecars_without_timings(out: Path) -> dict[str, dict]:
    found = {}
    for p in sorted(out.glob("*.json")):
        side = json.loads(p.read_text())
        side.pop("timings_s")
        side["results"].pop("batch", None)
        found[p.name] = side
    return found


def _assert_nothing_partial(out: Path) -> None:
    """Only complete outputs: no temporary file or reference folder left, and every image has the
    sidecar that describes it."""
    names = sorted(p.name for p in out.iterdir())
    assert not [n for n in names if n.startswith(".")], names
    for path in sorted(out.iterdir()):
        if path.suffix == ".json":
            continue
        side = path.with_name(path.name + ".json")
        assert json.loads(side.read_text())["output"]["sha256"] == file_sha256(path), path.name


@contextlib.contextmanager
def _external_cluster(folder: Path, n_workers: int):
    """A scheduler and ``n_workers`` single-thread worker processes, as on a cluster; yields
    (address, scheduler process, client seen by the test)."""
    from distributed import Client

    scheduler_file = folder / "scheduler.json"
    log = open(folder / "cluster.log", "w")  # noqa: SIM115 - closed below
    common = ["--no-dashboard"]
    scheduler = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                                  "--port", "0", "--scheduler-file", str(scheduler_file), *common],
                                 stdout=log, stderr=log, start_new_session=True)
    workers = None
    client = None
    try:
        deadline = time.monotonic() + 60
        while not scheduler_file.exists():
            assert time.monotonic() < deadline and scheduler.poll() is None, "the dask scheduler did not start"
            time.sleep(0.1)
        workers = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file",
                                    str(scheduler_file), "--nworkers", str(n_workers), "--nthreads", "1", *common],
                                   stdout=log, stderr=log, start_new_session=True)
        client = Client(scheduler_file=str(scheduler_file), timeout=60, set_as_default=False)
        client.wait_for_workers(n_workers, timeout=90)
        yield client.scheduler.address, scheduler, client
    finally:
        if client is not None:
            with contextlib.suppress(Exception):
                client.close(timeout=5)
        for proc in (workers, scheduler):
            if proc is not None and proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)  # the group: a worker's nanny and its worker process
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
        log.close()


def _start_run(shots: list[Path], refs: list[str], out: Path, address: str) -> subprocess.Popen:
    """``dslrxr run`` against the scheduler at ``address``, in the background (the test acts meanwhile)."""
    return subprocess.Popen([sys.executable, "-m", "napari_dslrxr.cli", "run", *map(str, shots), *refs,
                             "-o", str(out), "--scheduler", address],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_local_cluster_from_the_parameter_file_matches_jobs_1_and_a_bad_file_fails_alone(tmp_path, small_batch):
    shots, refs = small_batch["shots"], ["--flat", str(small_batch["flat"]), "--dark", str(small_batch["dark"]), "--dicom"]
    cfg = tmp_path / "p.toml"
    cfg.write_text('[batch]\nscheduler = "local"\njobs = 2\n')
    scratch = tmp_path / "dask-scratch"  # where the workers keep their folders
    run = _dslrxr("run", *map(str, shots[:2]), str(small_batch["bad"]), *map(str, shots[2:]), *refs,
                  "-o", str(tmp_path / "cluster"), "-c", str(cfg), env={"DASK_TEMPORARY_DIRECTORY": str(scratch)})
    assert run.returncode == 1, run.stderr
    assert "on a local dask cluster (2 worker(s)" in run.stderr
    assert "broken.tif" in run.stderr and "1 of 5 file(s) failed" in run.stderr
    assert "peak memory per worker" in run.stderr and "Traceback" not in run.stderr
    # the finished batch's workers were stopped at once, yet quietly and completely: no line about
    # them, and each one's folder removed as dask removes it when a worker ends
    assert "killed" not in run.stderr and "Worker process" not in run.stderr, run.stderr
    assert not list(scratch.rglob("worker-*")), sorted(p.name for p in scratch.rglob("*"))
    assert main(["run", *map(str, shots), *refs, "-o", str(tmp_path / "jobs1"), "--jobs", "1"]) == 0
    cluster, reference = _images(tmp_path / "cluster"), _images(tmp_path / "jobs1")
    assert len(reference) == 3 * len(shots) and cluster == reference  # TIFF, PNG and DICOM, same bytes
    assert not (tmp_path / "cluster" / "broken_dslrxr.tif").exists()
    # sidecars differ only in timings and where the batch ran
    assert _sidecars_without_timings(tmp_path / "cluster") == _sidecars_without_timings(tmp_path / "jobs1")
    side = json.loads((tmp_path / "cluster" / "shot0_dslrxr.tif.json").read_text())
    assert side["results"]["batch"] == {"scheduler": "local"} and "batch" not in side["parameters"]


@pytest.mark.slow
def test_a_local_cluster_starts_the_largest_files_first(tmp_path):
    """One worker runs the files in the order the cluster gives them: the largest first (the
    last files to start are then the short ones, so several workers finish together), whatever
    the order on the command line; each output is that of --jobs 1."""
    folder = tmp_path / "inputs"
    folder.mkdir()
    shapes = {"small": (120, 180), "large": (240, 360), "medium": (180, 270)}
    shots = [write_tiff(folder / f"{name}.tif", make_dslr_radiograph(shape, seed=1).raw_rgb)
             for name, shape in shapes.items()]
    run = _dslrxr("run", *map(str, shots), "-o", str(tmp_path / "cluster"), "--scheduler", "local", "--jobs", "1")
    assert run.returncode == 0, run.stderr
    order = [Path(line.split("] ", 1)[1].split(":", 1)[0]).stem for line in run.stderr.splitlines()
             if line.startswith("[")]
    assert order == ["large", "medium", "small"], run.stderr
    assert main(["run", *map(str, shots), "-o", str(tmp_path / "jobs1")]) == 0
    assert _images(tmp_path / "cluster") == _images(tmp_path / "jobs1")


def _psf_model(folder: Path) -> Path:
    from napari_dslrxr.core.psf import PSFModel, save_psf

    return save_psf(PSFModel(pixel_pitch_mm=0.1, source_fwhm_x_mm=0.3, source_fwhm_y_mm=0.3,
                             detector_fwhm_core_mm=0.15, detector_fwhm_tail_mm=0.4,
                             detector_weight_core=0.8, shape_power=1.5), folder / "psf.json")


def test_a_worker_prepares_the_references_once_even_with_two_threads(tmp_path, small_batch, monkeypatch):
    """Two worker threads in one process (as a worker started with two threads) read the flats,
    darks and PSF model once for the batch, not once per thread or file."""
    from distributed import LocalCluster

    from napari_dslrxr._cli import cluster as cli_cluster
    from napari_dslrxr.core import files as core_files
    from napari_dslrxr.core import psf as core_psf

    psf = _psf_model(tmp_path)
    frame_reads, psf_reads = [], []
    real_load_frames, real_load_psf = core_files.load_frames, core_psf.load_psf
    monkeypatch.setattr(core_files, "load_frames", lambda paths: frame_reads.append(list(paths)) or real_load_frames(paths))
    monkeypatch.setattr(core_psf, "load_psf", lambda path: psf_reads.append(path) or real_load_psf(path))
    monkeypatch.setattr(cli_cluster, "_worker_references", {})
    monkeypatch.setattr(cli_cluster, "_prepared_sets", set())
    shots = small_batch["shots"]
    common = [*map(str, shots), "--flat", str(small_batch["flat"]), "--dark", str(small_batch["dark"]), "--psf",
              str(psf), "--source-to-object-mm", "500", "--source-to-detector-mm", "1000"]
    # workers as threads of this process, so the counters see their reads too
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        assert main(["run", *common, "-o", str(tmp_path / "cluster"), "--scheduler", cluster.scheduler_address]) == 0
    assert frame_reads == [[str(small_batch["flat"])], [str(small_batch["dark"])]]
    assert len(psf_reads) == 1
    kinds = sorted(str(key[0]) for key in cli_cluster._worker_references)
    assert len(kinds) == 2 and "psf" in kinds  # one flat reference, one kernel
    assert main(["run", *common, "-o", str(tmp_path / "jobs1")]) == 0
    assert _images(tmp_path / "cluster") == _images(tmp_path / "jobs1")


@pytest.mark.slow
def test_worker_processes_map_the_commands_reference_and_read_the_psf_at_most_once(tmp_path, small_batch):
    """Real worker processes: none reads the flat or the dark (the command prepared the
    reference once and they map it), each reads the PSF model at most once however many files it
    runs; the outputs are those of --jobs 1 and the shared reference is gone at the end."""
    # defined here so that dask sends it to the workers by value (they cannot import the tests)
    def _count_reference_reads() -> None:
        """In a worker process: count the reference frames and PSF models it reads from now on."""
        from napari_dslrxr.core import files as core_files
        from napari_dslrxr.core import psf as core_psf

        reads = core_files.__dict__.setdefault("_test_reference_reads", [])
        real_load_frames, real_load_psf = core_files.load_frames, core_psf.load_psf
        core_files.load_frames = lambda paths: reads.append(tuple(paths)) or real_load_frames(paths)
        core_psf.load_psf = lambda path: reads.append(("psf", str(path))) or real_load_psf(path)

    psf = _psf_model(tmp_path)
    shots = small_batch["shots"] * 2  # 8 files for 2 workers: each runs several
    copies = tmp_path / "inputs"
    copies.mkdir()
    inputs = [copies / f"f{i}.tif" for i in range(len(shots))]
    for src, dst in zip(shots, inputs, strict=True):
        dst.write_bytes(src.read_bytes())
    refs = ["--flat", str(small_batch["flat"]), "--dark", str(small_batch["dark"]), "--psf", str(psf),
            "--source-to-object-mm", "500", "--source-to-detector-mm", "1000"]
    with _external_cluster(tmp_path, 2) as (address, _, client):
        client.run(_count_reference_reads)
        run = _dslrxr("run", *map(str, inputs), *refs, "-o", str(tmp_path / "cluster"), "--scheduler", address)
        reads = client.run(lambda: __import__("napari_dslrxr.core.files", fromlist=["x"]).__dict__.get(
            "_test_reference_reads", []))
    assert run.returncode == 0, run.stderr
    for worker, worker_reads in reads.items():  # the PSF once with its first file, or never (no file)
        assert worker_reads in ([("psf", str(psf))], []), (worker, worker_reads)
    assert any(reads.values())  # 8 files on 2 workers: one of them ran at least 4 with one read each
    assert not [p.name for p in (tmp_path / "cluster").iterdir() if p.name.startswith(".")]
    assert main(["run", *map(str, inputs), *refs, "-o", str(tmp_path / "jobs1")]) == 0
    assert _images(tmp_path / "cluster") == _images(tmp_path / "jobs1")


@pytest.mark.slow
def test_a_killed_worker_loses_nothing(tmp_path, slow_batch):
    shots, refs = slow_batch["shots"], ["--flat", str(slow_batch["flat"]), "--dark", str(slow_batch["dark"])]
    out = tmp_path / "out"
    with _external_cluster(tmp_path, 2) as (address, _, client):
        run = _start_run(shots, refs, out, address)
        deadline = time.monotonic() + 90
        busy = []
        while not busy:
            assert time.monotonic() < deadline and run.poll() is None, "no task started"
            busy = [(w, k) for w, keys in client.processing().items() for k in keys if "dslrxr-run" in str(k)]
            time.sleep(0.05)
        worker, key = busy[0]
        name = str(key).rsplit("-", 1)[1]  # the key ends with the input's file name
        pid = client.run(os.getpid, workers=[worker])[worker]
        time.sleep(0.3)  # into the file's pipeline
        assert not (out / (Path(name).stem + "_dslrxr.png.json")).exists()  # its outputs are not finished
        os.kill(pid, signal.SIGKILL)
        _, stderr = run.communicate(timeout=RUN_TIMEOUT_S)
        story = client.run_on_scheduler(lambda dask_scheduler: [t[2] for t in dask_scheduler.story(key)])
    assert run.returncode == 0, stderr
    assert story.count("processing") >= 2  # the killed worker's file was scheduled again
    leftovers = [p.name for p in out.iterdir() if p.name.startswith(".")]
    assert not leftovers, leftovers  # a worker killed mid-write leaves no temporary file behind
    _assert_nothing_partial(out)
    assert _images(out) == slow_batch["reference"]


@pytest.mark.slow
def test_a_lost_scheduler_ends_the_run_with_a_clear_message(tmp_path, slow_batch):
    shots, refs = slow_batch["shots"], ["--flat", str(slow_batch["flat"]), "--dark", str(slow_batch["dark"])]
    out = tmp_path / "out"
    with _external_cluster(tmp_path, 1) as (address, scheduler, _):
        run = _start_run(shots, refs, out, address)
        deadline = time.monotonic() + 90
        while not (out.exists() and list(out.glob("*.png.json"))):
            assert time.monotonic() < deadline and run.poll() is None, "no file finished"
            time.sleep(0.05)
        os.killpg(scheduler.pid, signal.SIGKILL)
        _, stderr = run.communicate(timeout=RUN_TIMEOUT_S)
    assert run.returncode == 2, stderr
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("dslrxr: error: lost the connection to the dask scheduler at " + address)
    assert "run the same command again" in last and "Traceback" not in stderr
    _assert_nothing_partial(out)
    finished = {p.name for p in out.glob("*_dslrxr.png.json")}
    assert 1 <= len(finished) < len(shots)
    # the rerun (here without a cluster) does the rest and keeps what was finished
    rerun = _dslrxr("run", *map(str, shots), *refs, "-o", str(out))
    assert rerun.returncode == 0 and f"skipped {len(finished)} file(s)" in rerun.stderr
    assert _images(out) == slow_batch["reference"]


def test_without_dask_the_scheduler_option_says_how_to_install_it(tmp_path, small_batch):
    code = ("import sys; sys.modules['distributed'] = None\n"  # as if the extra were not installed
            "from napari_dslrxr.cli import main\n"
            f"sys.exit(main(['run', {str(small_batch['shots'][0])!r}, '-o', {str(tmp_path / 'o')!r},"
            " '--scheduler', 'local']))\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2
    assert run.stderr.strip() == ("dslrxr: error: --scheduler needs dask.distributed, which is not installed: "
                                  "pip install 'napari-dslrxr[distributed]'")
    assert not (tmp_path / "o").exists()


def test_bad_or_unreachable_scheduler_is_one_line(tmp_path, small_batch, capsys, monkeypatch):
    from napari_dslrxr._cli import cluster as cli_cluster

    shot = str(small_batch["shots"][0])
    assert main(["run", shot, "-o", str(tmp_path / "o"), "--scheduler", "my-cluster"]) == 2
    assert "batch.scheduler: expected" in capsys.readouterr().err
    monkeypatch.setattr(cli_cluster, "CONNECT_TIMEOUT_S", 2)
    with __import__("socket").socket() as sock:  # a port nobody listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    assert main(["run", shot, "-o", str(tmp_path / "o"), "--scheduler", f"tcp://127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"dslrxr: error: cannot reach the dask scheduler at tcp://127.0.0.1:{port}")
    assert err.count("\n") == 0
    assert not list((tmp_path / "o").glob("*_dslrxr*"))



def test_a_worker_that_cannot_see_the_shared_reference_prepares_its_own(tmp_path, small_batch, monkeypatch):
    """A job whose shared reference folder this worker does not see (no shared file system):
    the worker reads the reference files itself, without waiting for the folder, and writes the
    bytes of --jobs 1."""
    from napari_dslrxr._cli import cluster as cli_cluster
    from napari_dslrxr.core import files as core_files
    from napari_dslrxr.core.params import PipelineParams, params_to_dict

    reads = []
    real_load = core_files.load_frames
    monkeypatch.setattr(core_files, "load_frames", lambda paths: reads.append(list(paths)) or real_load(paths))
    monkeypatch.setattr(cli_cluster, "_worker_references", {})
    monkeypatch.setattr(cli_cluster, "_prepared_sets", set())
    shot, flat, dark = small_batch["shots"][0], small_batch["flat"], small_batch["dark"]
    (tmp_path / "w").mkdir()
    job = {"input": str(shot), "out_dir": str(tmp_path / "w"), "params": params_to_dict(PipelineParams()),
           "flats": [str(flat)], "darks": [str(dark)], "psf": None, "sod": None, "sdd": None, "patient": {},
           "shared_reference": str(tmp_path / "not-mounted-here" / ".dslrxr-reference-elsewhere-1-0123abcd")}
    name, ok, message, *_ = cli_cluster._run_on_worker(job)
    assert ok, message
    assert reads == [[str(flat)], [str(dark)]]
    assert main(["run", str(shot), "--flat", str(flat), "--dark", str(dark), "-o", str(tmp_path / "seq")]) == 0
    assert _images(tmp_path / "w") == _images(tmp_path / "seq")


@pytest.mark.slow
def test_a_terminated_local_run_leaves_no_shared_reference_and_nothing_partial(tmp_path, slow_batch):
    """SIGTERM to the command while its LocalCluster works: it ends as an interruption, the
    shared reference folder is removed and every output under a final name is complete."""
    shots, refs = slow_batch["shots"], ["--flat", str(slow_batch["flat"]), "--dark", str(slow_batch["dark"])]
    out = tmp_path / "out"
    run = _start_run(shots * 3, refs, out, "local")
    deadline = time.monotonic() + 120
    while not (out.exists() and any(p.name.startswith(".dslrxr-reference-") for p in out.iterdir())):
        assert time.monotonic() < deadline and run.poll() is None, "no shared reference appeared"
        time.sleep(0.05)
    time.sleep(1.0)  # the workers into their first files
    run.send_signal(signal.SIGTERM)
    _, stderr = run.communicate(timeout=RUN_TIMEOUT_S)
    assert run.returncode == 130 and "Traceback" not in stderr, stderr  # an interruption, as Ctrl-C
    assert not [p.name for p in out.iterdir() if p.name.startswith(".dslrxr-reference-")]
    _assert_nothing_partial(out)


def test_a_long_lived_worker_never_serves_a_reference_from_a_replaced_flat(tmp_path):
    """A dask worker outlives a run and keeps its prepared references; when the flat file is
    replaced between two runs (same path), the second run must use the new flat, as a fresh
    ``--jobs 1`` run does (it had served the old one, with the new flat's checksum recorded)."""
    from napari_dslrxr._cli import cluster
    from napari_dslrxr.core.params import PipelineParams, params_to_dict

    frames = make_dslr_radiograph((160, 240), seed=3)
    shot = write_tiff(tmp_path / "shot.tif", frames.raw_rgb)
    flat = write_tiff(tmp_path / "flat.tif", frames.flat)

    def job(name: str) -> dict:
        (tmp_path / name).mkdir()
        return {"input": str(shot), "out_dir": str(tmp_path / name), "params": params_to_dict(PipelineParams()),
                "flats": [str(flat)], "darks": [], "psf": None, "sod": None, "sdd": None, "patient": {},
                "shared_reference": None}

    assert cluster._run_on_worker(job("first"))[1]
    ramp = np.linspace(0.5, 1.0, frames.flat.shape[1])[None, :, None]
    write_tiff(flat, (frames.flat * ramp).astype(frames.flat.dtype))  # the next day's flat, same name
    assert cluster._run_on_worker(job("second"))[1]  # the same worker process
    assert main(["run", str(shot), "--flat", str(flat), "-o", str(tmp_path / "fresh")]) == 0
    second = (tmp_path / "second" / "shot_dslrxr.tif").read_bytes()
    assert second == (tmp_path / "fresh" / "shot_dslrxr.tif").read_bytes()
    assert second != (tmp_path / "first" / "shot_dslrxr.tif").read_bytes()


@pytest.mark.slow
def test_a_local_worker_that_never_starts_is_one_line_not_a_hang(tmp_path, small_batch, capsys, monkeypatch):
    import distributed

    from napari_dslrxr._cli import cluster as cli_cluster

    monkeypatch.setattr(cli_cluster, "WORKER_START_TIMEOUT_S", 3.0)
    monkeypatch.setattr(distributed.LocalCluster, "scale", lambda self, n=0, **kwargs: None)  # no worker comes up
    shot = str(small_batch["shots"][0])
    started = time.monotonic()
    assert main(["run", shot, "-o", str(tmp_path / "o"), "--scheduler", "local"]) == 2
    assert time.monotonic() - started < 60
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("dslrxr: error: no local dask worker started within 3 s"), err
    assert not list((tmp_path / "o").glob("*_dslrxr*"))


def test_the_dask_internals_of_the_fast_stop_are_still_there():
    # _stop_idle_workers waits on Nanny.process.stopped; a dask without them would lose the fast
    # stop silently (the fallback is dask's own close), so this fails instead
    import inspect

    from distributed.nanny import Nanny, WorkerProcess

    assert "self.process = " in inspect.getsource(Nanny)
    assert "self.stopped = asyncio.Event()" in inspect.getsource(WorkerProcess)


def _worker_state() -> dict:
    """In a task (a worker's thread, as a file runs): its native threads, the page faults of a second
    200 MB array after a first one, and its parent process. The faults are the task thread's own:
    the worker's other threads (heartbeats, the event loop) fault pages meanwhile, 34 once on CI."""
    import resource

    import cv2

    big = np.ones(25_000_000)
    del big
    before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
    again = np.ones(25_000_000)
    faults = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before
    del again
    return {"cv2_threads": cv2.getNumThreads(), "faults": faults, "parent": os.getppid()}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's heap settings, the fork server")
def test_local_workers_are_forked_with_the_pipeline_imported_and_keep_the_heap_and_thread_settings():
    """The workers come from a fork server that imported the pipeline (once, not once per
    worker) and ends with the cluster, and they still get the heap settings (a second large array reuses the first one's memory,
    in the task's thread) and one native thread each for two workers on this machine."""
    from napari_dslrxr._cli.cluster import connect, native_threads_per_process

    def modules_before_any_task():
        return "napari_dslrxr.core.files" in sys.modules and "cv2" in sys.modules

    environ = dict(os.environ)  # dask's nanny sets the workers' variables in this process's environment
    try:
        with connect("local", 2) as client:
            client.wait_for_workers(2, timeout=120)
            imported = client.run(modules_before_any_task)  # in each worker's event loop, before any task
            states = [client.submit(_worker_state, pure=False, workers=[address]).result(timeout=120)
                      for address in client.scheduler_info()["workers"]]
    finally:
        os.environ.clear()
        os.environ.update(environ)
    assert list(imported.values()) == [True, True], imported
    server = states[0]["parent"]
    assert {state["parent"] for state in states} == {server} and server != os.getpid()  # the fork server
    # it ended with the cluster and was reaped (its CPU time counts in the command's)
    assert not Path(f"/proc/{server}").exists()
    for state in states:
        assert state["cv2_threads"] == native_threads_per_process(2), state
        assert state["faults"] < 10, state
