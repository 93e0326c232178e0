"""``dslrxr run --scheduler``: the batch as one dask.distributed task per input file.

The per-file work is :func:`napari_dslrxr.core.files.run_file`, exactly as with ``--jobs``
(same atomic writes and sidecars, so the outputs have the same bytes). The command prepares the
flat/dark reference once, in a thread while the workers start, and writes it into a hidden folder
of the output folder; each worker maps it read-only from there (a 24 MP reference is 576 MB:
scattered through the scheduler it kept the workers idle for longer than preparing it takes, and
each worker preparing its own spent that CPU time once per worker). A worker that cannot see the
folder (no shared file system) prepares the reference from the reference files with its first
file, as the process pool's workers do. Each worker computes the PSF kernel (small) once and keeps
both in its ``reference_cache`` for its later files. The folder is removed when the command ends.

The workers of ``--scheduler local`` share the cores out to their native libraries (OpenCV, BLAS:
one thread each on a 2-core machine with 2 workers), run without dask's statistical profiler and
get the heap settings of every process that runs files (:data:`~.file_job.HEAP_ENVIRON`, in place
of dask's ``MALLOC_TRIM_THRESHOLD_``, under which every large temporary array of the pipeline was
a fresh mapping: about 9 times the page faults of one process). Workers started otherwise
(``dask worker``, dask-jobqueue) keep their own settings.

dask reschedules the task of a worker that dies (a file is written under a temporary name and
renamed, so a killed worker leaves no partial output); a task that kills
``distributed.scheduler.allowed-failures`` + 1 workers fails alone. A lost connection to the
scheduler ends the command with :class:`ClusterError` after the files already finished.

dask is optional (``pip install 'napari-dslrxr[distributed]'``) and imported only here. The
client, the LocalCluster and their threads live in the command line, never in the core.
"""

from __future__ import annotations

import contextlib
import logging
import os
import resource
import shutil
import signal
import socket
import sys
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

from ..core.errors import DslrxrError, ParameterError
from .file_job import HEAP_ENVIRON

#: Seconds to wait for an address given with ``--scheduler`` to answer.
CONNECT_TIMEOUT_S = 20

#: The flat references and PSF kernels this worker process prepared (keyed as ``run_file`` looks
#: them up), kept for its later files.
_worker_references: dict = {}

#: Reference sets (flats, darks, PSF, geometry, dark offset, parameters) this worker has prepared;
#: the first file of a set runs under ``_first_file_lock``, so a worker with several threads
#: prepares a set once, not once per thread.
_prepared_sets: set = set()
_first_file_lock = threading.Lock()


class ClusterError(DslrxrError):
    """The dask scheduler cannot be reached, or the connection to it was lost."""


def import_distributed():
    try:
        import distributed
    except ImportError:
        raise ParameterError("--scheduler needs dask.distributed, which is not installed: "
                             "pip install 'napari-dslrxr[distributed]'") from None
    return distributed


def _reference_set(job: dict) -> tuple:
    """What a job's prepared references depend on: the same tuple, the same references."""
    from ..core.params import params_from_dict
    from ..core.files import input_black_level

    params = params_from_dict(job["params"])
    return (tuple(job["flats"]), tuple(job["darks"]), job["psf"], job["sod"], job["sdd"],
            repr(input_black_level(job["input"], params)), repr(params.flatfield))


def _run_on_worker(job: dict) -> tuple[str, bool, str, float, list[str]]:
    """The task of one file: :func:`~.file_job.process_one` with this worker's prepared references
    (the command's shared flat reference mapped with the first file, when this worker sees it)."""
    from .file_job import process_one

    shared = job.get("shared_reference")
    if shared is not None and shared["key"] not in _worker_references:
        from ..core.files import load_flat_reference

        with contextlib.suppress(OSError, ValueError, KeyError):  # not visible here: run_file prepares it
            _worker_references[shared["key"]] = load_flat_reference(shared["folder"])
    key = _reference_set(job)
    if key in _prepared_sets:
        return process_one(job, _worker_references)
    with _first_file_lock:  # the first file of a reference set prepares it, once per worker
        outcome = process_one(job, _worker_references)
        if outcome[1]:
            _prepared_sets.add(key)
    return outcome


#: Name of the hidden folder of the output folder that holds a running batch's shared flat
#: reference: this prefix, the host name and the command's process id.
SHARED_REFERENCE_PREFIX = ".dslrxr-reference-"


def _prepare_shared_reference(job: dict, folder: Path) -> dict | None:
    """Prepare the flat reference of ``job`` (its reference files, parameters and its input's dark
    offset) and write it to ``folder``. Returns what a worker needs to map it, or None when
    there is nothing to prepare or it cannot be prepared here: the workers then prepare it from
    the reference files themselves, and report a bad reference file with each input."""
    from ..core.files import flat_reference_key, input_black_level, load_frames, save_flat_reference
    from ..core.params import params_from_dict, validate_params
    from ..core.stages.flatfield import prepare_flat_reference

    if not job["flats"] and not job["darks"]:
        return None  # the reference is the dark offset alone: nothing worth sharing
    try:
        params = validate_params(params_from_dict(job["params"]))
        flats, darks = load_frames(job["flats"]), load_frames(job["darks"])
        shapes = {frame.shape for frame in (*flats, *darks)}
        if len(shapes) != 1:
            return None
        shape = shapes.pop()
        offset = input_black_level(job["input"], params)
        reference = prepare_flat_reference(shape, flats=flats, darks=darks, black_level=offset,
                                           params=params.flatfield)
        del flats, darks
        save_flat_reference(reference, folder)
    except Exception:  # noqa: BLE001 - the workers prepare it and report what is wrong, file by file
        return None
    return {"key": flat_reference_key(job["flats"], job["darks"], shape, offset, params), "folder": str(folder)}


def _remove_stale_references(out_dir: Path) -> None:
    """Remove shared reference folders left in ``out_dir`` by commands on this host that no
    longer run (killed with SIGKILL, or the machine stopped)."""
    host = socket.gethostname()
    for folder in out_dir.glob(SHARED_REFERENCE_PREFIX + "*"):
        parts = folder.name[len(SHARED_REFERENCE_PREFIX):].removesuffix(".partial").rsplit("-", 2)
        if len(parts) == 3 and parts[0] == host and parts[1].isdigit() and not _process_alive(int(parts[1])):
            shutil.rmtree(folder, ignore_errors=True)


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, someone else's
        return True
    return True


def _terminate_as_interrupt(signum, frame):  # noqa: ARG001 - a signal handler's signature
    raise KeyboardInterrupt


@contextlib.contextmanager
def shared_reference(todo: list[dict]) -> Iterator[Callable[[], dict | None]]:
    """Prepare the batch's flat reference (that of its first file) in a thread of this command,
    into a hidden folder of the output folder, while the caller starts the workers. Yields a
    function that waits for it and returns what the jobs carry to the workers (None: nothing
    shared). The folder is removed at the end, also after an error, Ctrl-C or SIGTERM (which
    ends the command as an interruption meanwhile); one left by a killed command on this host
    is removed by the next run into the same folder."""
    out_dir = Path(todo[0]["out_dir"])
    _remove_stale_references(out_dir)
    folder = out_dir / f"{SHARED_REFERENCE_PREFIX}{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    prepared: dict = {}
    thread = threading.Thread(target=lambda: prepared.update(shared=_prepare_shared_reference(todo[0], folder)),
                              name="dslrxr-shared-reference", daemon=True)
    thread.start()

    def wait() -> dict | None:
        thread.join()
        return prepared.get("shared")

    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate_as_interrupt) if in_main_thread else None
    try:
        yield wait
    finally:
        thread.join()  # a preparation under way finishes (seconds) so that its folder goes too
        for path in (folder, folder.with_name(folder.name + ".partial")):
            shutil.rmtree(path, ignore_errors=True)
        if in_main_thread:
            signal.signal(signal.SIGTERM, previous)


def native_threads_per_process(n_processes: int) -> int:
    """Threads each of ``n_processes`` worker processes on this machine gives its native
    libraries (OpenCV, BLAS, OpenMP): the cores shared out, at least one. One process alone
    uses every core in OpenCV; several each doing so would oversubscribe the cores."""
    return max(1, (os.cpu_count() or 1) // max(1, n_processes))


def _peak_rss_mb() -> float:
    """Peak resident memory of this (worker) process, MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@contextlib.contextmanager
def connect(scheduler: str, n_workers: int) -> Iterator:
    """A dask ``Client``: on a LocalCluster of ``n_workers`` processes (``"local"``), closed
    at the end, or on the scheduler at the address ``scheduler``."""
    distributed = import_distributed()
    if scheduler == "local":
        import dask

        threads = str(native_threads_per_process(n_workers))
        # read at the workers' start by glibc (the heap settings of a process running files, in
        # place of dask's trim threshold, under which each large array is a fresh mapping) and
        # their native libraries (OpenCV, BLAS, OpenMP)
        environ = {**HEAP_ENVIRON, "OPENCV_FOR_THREADS_NUM": threads, "OMP_NUM_THREADS": threads,
                   "OPENBLAS_NUM_THREADS": threads, "MKL_NUM_THREADS": threads}
        settings = {f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in environ.items()}
        # the workers' statistical profiler samples their threads 100 times a second (about 1 % of
        # a core each) for a dashboard page nobody reads during a batch
        settings["distributed.worker.profile.enabled"] = False
        with dask.config.set(settings):
            cluster = distributed.LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                               dashboard_address=":0", silence_logs=logging.ERROR)
        try:
            with distributed.Client(cluster, set_as_default=False) as client:
                yield client
        finally:
            cluster.close()
        return
    if not os.environ.get("DSLRXR_DEBUG"):  # a lost scheduler gets one line from us, not its tracebacks
        for name in ("distributed", *(n for n in logging.root.manager.loggerDict if n.startswith("distributed."))):
            logging.getLogger(name).setLevel(logging.CRITICAL)
    try:
        client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise ClusterError(f"cannot reach the dask scheduler at {scheduler} ({_short(exc)})") from None
    try:
        yield client
    finally:
        with contextlib.suppress(Exception):
            client.close(timeout=5)


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) < 200 else text[:197] + "..."


def _dashboard(client) -> str | None:
    """The scheduler's dashboard link, when it serves one (without bokeh it only says to install it)."""
    import urllib.request

    try:
        if "dashboard" not in client.scheduler_info().get("services", {}):
            return None
        link = client.dashboard_link
        with urllib.request.urlopen(link, timeout=3) as page:
            text = page.read(4096).decode("utf-8", "replace")
    except Exception:
        return None
    return None if "needs bokeh" in text else link


def _failed_task_message(exc: BaseException) -> str:
    if type(exc).__name__ == "KilledWorker":
        return "a dask worker died each time it processed this file (out of memory?)"
    if isinstance(exc, OSError):  # the worker's file system refused (disk full, permissions...)
        return f"{exc.filename + ': ' if exc.filename else ''}{exc.strerror or _short(exc)}"
    return f"internal error on a worker ({type(exc).__name__}: {_short(exc)})"


def run_on_cluster(todo: list[dict], *, scheduler: str, n_workers: int,
                   report: Callable[[int, tuple[str, bool, str, float, list[str]]], None]) -> None:
    """Run each job of ``todo`` as one task; call ``report(i, outcome)`` as files finish.

    Raises
    ------
    ParameterError
        dask.distributed is not installed.
    ClusterError
        The scheduler cannot be reached, or the connection was lost (files that finished
        before are complete; a rerun does the rest).
    """
    distributed = import_distributed()
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    where = "a local dask cluster" if scheduler == "local" else f"the dask scheduler at {scheduler}"
    finished = 0
    # the reference is prepared while the workers start; the tasks are submitted when it is ready
    with shared_reference(todo) as wait_for_reference, connect(scheduler, n_workers) as client:
        n = len(client.scheduler_info().get("workers", {}))
        print(f"dslrxr: {len(todo)} file(s) on {where} ({n} worker(s) now)", file=sys.stderr)
        link = _dashboard(client)
        print(f"dslrxr: dask dashboard: {link}" if link else
              "dslrxr: no dask dashboard (install bokeh>=3.1 for one)", file=sys.stderr)
        try:
            run_id = uuid.uuid4().hex[:8]
            shared = wait_for_reference()
            futures = [client.submit(_run_on_worker, {**job, "shared_reference": shared}, pure=False,
                                     key=f"dslrxr-run-{run_id}-{i}-{Path(job['input']).name}")
                       for i, job in enumerate(todo)]
            by_key = {f.key: job for f, job in zip(futures, todo, strict=True)}
            console = Console(stderr=True, highlight=False)
            columns = (TextColumn("files"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
            # a bar on a terminal; logs and pipes get the per-file lines only
            with Progress(*columns, console=console, transient=True, disable=not console.is_terminal) as bar:
                task = bar.add_task("files", total=len(todo))
                for future in distributed.as_completed(futures, loop=client.loop):
                    if future.status == "error":  # the task raised on the worker: this file only
                        outcome = (by_key[future.key]["input"], False, _failed_task_message(future.exception()), 0.0)
                    elif future.status == "finished":
                        try:
                            outcome = future.result()
                        except (OSError, TimeoutError, distributed.client.FutureCancelledError) as exc:
                            raise ClusterError(f"lost the connection to {where} ({_short(exc)})") from None
                    else:  # cancelled or lost: the client is no longer connected to the scheduler
                        raise ClusterError(f"lost the connection to {where}")
                    finished += 1
                    report(finished, outcome)
                    bar.advance(task)
                    future.release()
            with contextlib.suppress(Exception):
                peaks = sorted(client.run(_peak_rss_mb, wait=True).values())
                print("dslrxr: peak memory per worker: " + ", ".join(f"{p:.0f}" for p in peaks) + " MiB",
                      file=sys.stderr)
        except ClusterError as exc:
            raise ClusterError(f"{exc}: {_after_loss(finished, len(todo))}") from None
        except (OSError, TimeoutError) as exc:  # comm errors while submitting
            raise ClusterError(f"lost the connection to {where} ({_short(exc)}): "
                               f"{_after_loss(finished, len(todo))}") from None


def _after_loss(finished: int, total: int) -> str:
    return (f"{finished} of {total} file(s) reported finished (files being processed then are either complete "
            "or absent, never partial); run the same command again to do the rest")

