"""``dslrxr run --scheduler``: the batch as one dask.distributed task per input file.

The per-file work is :func:`napari_dslrxr.core.files.run_file`, exactly as with ``--jobs``
(same atomic writes and sidecars, so the outputs have the same bytes). The flat/dark reference is
prepared once by the command, as for the process pool (:mod:`.shared_reference`): in a thread
started before the workers; the tasks are submitted, largest input first, as soon as the client is
connected (the workers of ``--scheduler local`` start meanwhile), and their first files' impulse
removal runs while the reference is prepared. Each worker computes the PSF kernel (small) once and
keeps both in its ``reference_cache`` for its later files.

The workers of ``--scheduler local`` share the cores out to their native libraries (OpenCV, BLAS:
one thread each on a 2-core machine with 2 workers), run without dask's statistical profiler and
get the heap settings of every process that runs files (:data:`~.file_job.HEAP_ENVIRON`, in place
of dask's ``MALLOC_TRIM_THRESHOLD_``, under which every large temporary array of the pipeline was
a fresh mapping: about 9 times the page faults of one process); its servers check their event
loops once a second, and once the batch is finished its idle workers are killed rather than
closed step by step. Workers started otherwise (``dask worker``, dask-jobqueue) keep their own
settings.

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
import signal
import sys
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

from ..core.errors import DslrxrError, ParameterError
from .file_job import HEAP_ENVIRON, remove_unfinished_outputs
from .shared_reference import shared_reference, worker_reference

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


def require_distributed() -> None:
    """Say how to install dask.distributed when it is not installed (without importing it: the
    command imports it once its other work is under way)."""
    import importlib.util

    if importlib.util.find_spec("distributed") is None:
        import_distributed()


def import_distributed():
    try:
        import distributed
    except ImportError:
        raise ParameterError("--scheduler needs dask.distributed, which is not installed: "
                             "pip install 'napari-dslrxr[distributed]'") from None
    return distributed


def _reference_set(job: dict) -> tuple:
    """What the references a job prepares depend on: its flat reference's key but for the input's
    shape (read with the file), and its PSF kernel's key. The same set, the same references."""
    from ..core.files import flat_reference_key, input_black_level, psf_kernel_key
    from ..core.params import params_from_dict

    params = params_from_dict(job["params"])
    return (flat_reference_key(job["flats"], job["darks"], (), input_black_level(job["input"], params), params),
            psf_kernel_key(job["psf"], job["sod"], job["sdd"]) if job["psf"] else None)


def _run_on_worker(job: dict) -> tuple[str, bool, str, float, list[str]]:
    """The task of one file: :func:`~.file_job.process_one` with this worker's prepared references
    and the command's shared flat reference (waited for when the file's flat-field stage starts)."""
    from .file_job import process_one

    reference = worker_reference(job.get("shared_reference"))
    key = _reference_set(job)
    if key in _prepared_sets:
        return process_one(job, _worker_references, reference)
    with _first_file_lock:  # the first file of a reference set prepares it, once per worker
        outcome = process_one(job, _worker_references, reference)
        if outcome[1]:
            _prepared_sets.add(key)
    return outcome


def native_threads_per_process(n_processes: int) -> int:
    """Threads each of ``n_processes`` worker processes on this machine gives its native
    libraries (OpenCV, BLAS, OpenMP): the cores shared out, at least one. One process alone
    uses every core in OpenCV; several each doing so would oversubscribe the cores."""
    return max(1, (os.cpu_count() or 1) // max(1, n_processes))


def _peak_rss_mb() -> float:
    """Peak resident memory of this (worker) process, MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@contextlib.contextmanager
def _interruptions_deferred() -> Iterator[list[int]]:
    """Ctrl-C and SIGTERM received meanwhile are listed, to act on once dask has started the
    LocalCluster's scheduler and the client is connected (interrupted midway, dask's waits
    fail with internal errors, and its exit hook on half-started workers)."""
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return
    previous = {sig: signal.signal(sig, lambda signum, frame: received.append(signum))
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield received
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


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
        # every server (scheduler, nannies, workers) checks its event loop's health 50 times a
        # second, only to log a warning when it lagged: with 2 workers about 5 % of a core
        settings["distributed.admin.tick.interval"] = "1s"
        # the nannies' and workers' memory checks (psutil, 10 times a second each, for the kill at
        # 95 % of a worker's limit and the pause at 80 %), their system monitors (dashboard figures
        # twice a second) and the scheduler's work stealing (10 times a second; a batch's tasks take
        # seconds): once a second, or every two for the figures
        settings.update({"distributed.worker.memory.monitor-interval": "1s",
                         "distributed.admin.system-monitor.interval": "2s",
                         "distributed.scheduler.work-stealing-interval": "1s"})
        start_method = _worker_start_method()
        settings["distributed.worker.multiprocessing-method"] = start_method
        # set while the cluster lives: its workers start in the background and read them then
        with dask.config.set(settings):
            with _interruptions_deferred() as interrupted:
                # the scheduler alone (at once); the worker processes start in the background,
                # each taking files as soon as it is up, while the command goes on
                cluster = distributed.LocalCluster(n_workers=0, threads_per_worker=1, processes=True,
                                                   memory_limit=1 / n_workers,  # dask's share for n workers
                                                   dashboard_address=":0", silence_logs=logging.ERROR)
                try:
                    cluster.scale(n_workers)
                    client = distributed.Client(cluster, set_as_default=False)  # meanwhile the workers start
                except BaseException:
                    cluster.close()
                    raise
            try:
                with client:
                    if interrupted:
                        raise KeyboardInterrupt
                    yield client
                _stop_idle_workers(cluster)
            finally:
                cluster.close()
                if start_method == "forkserver":
                    _stop_fork_server()
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


#: The modules a LocalCluster's worker imports to run files: imported once, by the fork server its
#: workers are forked from, rather than by each worker started afresh (about 1.5 s of CPU time each).
WORKER_MODULES = ("distributed", "napari_dslrxr._cli.cluster", "napari_dslrxr.core.files",
                  "napari_dslrxr.core.stages.impulse", "napari_dslrxr.core.stages.contrast")


def _worker_start_method() -> str:
    """How a LocalCluster starts its worker processes: forked from a fork server that imported
    :data:`WORKER_MODULES` (where the platform has one), else started afresh ('spawn').

    The fork server is started by the first worker's start, after the nanny has set the workers'
    environment (:data:`~.file_job.HEAP_ENVIRON`, the native libraries' threads), so it and every
    worker forked from it read them; it is single-threaded when it forks. dask's own fork-server
    set-up would import pandas and lz4 into the command, to check they exist, and have the server
    import them: ``distributed.utils._forkserver_preload_set`` (a dask internal, tested in
    tests/_cli/test_cluster.py) tells it the list is set."""
    import multiprocessing

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return "spawn"
    import distributed.utils

    if not hasattr(distributed.utils, "_forkserver_preload_set"):
        return "spawn"  # dask changed how it sets up the fork server: keep its default
    # '__main__': the command's main module, which each worker would import again otherwise
    # and last, the server's fast exit (:mod:`.fork_server`)
    multiprocessing.get_context("forkserver").set_forkserver_preload(
        ["__main__", *WORKER_MODULES, "napari_dslrxr._cli.fork_server"])
    distributed.utils._forkserver_preload_set = True
    return "forkserver"


#: Seconds a LocalCluster's first worker may take to start before the run stops with one line.
WORKER_START_TIMEOUT_S = 120.0

#: Seconds a LocalCluster's worker gets to close by itself at the end of a batch before its
#: process is killed (every file is finished and reported then: nothing else is in it), and the
#: most to wait then for the killed processes to be reaped.
_WORKER_CLOSE_WAIT_S = 0.1
_WORKER_EXIT_WAIT_S = 10.0


def _stop_idle_workers(cluster) -> None:
    """End the worker processes of the LocalCluster ``cluster`` once its batch is finished.
    dask's own close has each worker close its connections and its interpreter free a heap of
    up to 2 GB before it is reaped (about 0.5 s with the cores otherwise idle); killed, they are
    gone at once. Only for a finished batch: after an error or an interruption
    ``cluster.close`` stops workers that may be writing, and the command cleans up after them.

    ``Nanny.process`` and its ``stopped`` event are dask internals (tested in
    tests/_cli/test_cluster.py, so an upgrade that drops them fails there instead of silently
    losing the fast stop); whatever fails here, ``cluster.close`` stops what is left."""
    import asyncio

    async def stop() -> None:
        nannies = list(cluster.workers.values())
        processes = [nanny.process for nanny in nannies if getattr(nanny, "process", None) is not None]
        await asyncio.gather(*(nanny.close(timeout=_WORKER_CLOSE_WAIT_S, reason="dslrxr-batch-finished")
                               for nanny in nannies), return_exceptions=True)
        # each nanny notes its process's end (and removes its scratch folder) once it is reaped
        stopped = [process.stopped.wait() for process in processes if hasattr(process, "stopped")]
        await asyncio.wait_for(asyncio.gather(*stopped), _WORKER_EXIT_WAIT_S)

    with contextlib.suppress(Exception):  # cluster.close() stops whatever is left
        cluster.sync(stop)


def _stop_fork_server() -> None:
    """End the fork server the LocalCluster's workers were forked from, once they are stopped, and
    reap it: it ends with the command's batch, not after the command (a pipe reading the command's
    output waits for it, about 0.8 s more on a loaded machine), and its CPU time and its workers'
    count in the command's. The next LocalCluster of this process starts a new one, with the
    environment of its time. ``ForkServer._stop`` is the standard library's own (for its tests;
    tested in tests/_cli/test_cluster.py)."""
    from multiprocessing import forkserver

    with contextlib.suppress(Exception):
        forkserver._forkserver._stop()


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
    where = "a local dask cluster" if scheduler == "local" else f"the dask scheduler at {scheduler}"
    unreported = {id(job): job for job in todo}  # an input may be listed twice
    try:
        _run_tasks(todo, scheduler, n_workers, report, where, unreported)
    except KeyboardInterrupt:
        if scheduler == "local":  # its workers were stopped with it: clean up after their files
            remove_unfinished_outputs(list(unreported.values()))
        else:  # tasks already running on the cluster's workers may still finish and write
            print(f"dslrxr: files running on {where} may still be finished by its workers", file=sys.stderr)
        raise


def _run_tasks(todo: list[dict], scheduler: str, n_workers: int,
               report: Callable[[int, tuple[str, bool, str, float, list[str]]], None], where: str,
               unreported: dict) -> None:
    """:func:`run_on_cluster`'s work; removes each file from ``unreported`` once reported."""
    finished = 0
    # the reference is prepared while the workers start and run their first files' impulse removal
    with shared_reference(todo, start=True) as shared, connect(scheduler, n_workers) as client:
        distributed = import_distributed()  # imported by connect, once the reference is under way
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        workers = (f"{n_workers} worker(s) starting" if scheduler == "local"
                   else f"{len(client.scheduler_info().get('workers', {}))} worker(s) now")
        print(f"dslrxr: {len(todo)} file(s) on {where} ({workers})", file=sys.stderr)
        link = _dashboard(client)
        print(f"dslrxr: dask dashboard: {link}" if link else
              "dslrxr: no dask dashboard (install bokeh>=3.1 for one)", file=sys.stderr)
        try:
            run_id = uuid.uuid4().hex[:8]
            # the largest files first (submitted first: a worker already idle starts the first one it
            # gets): the last files to start are short ones, so the workers finish together
            order = sorted(range(len(todo)), key=lambda i: _input_bytes(todo[i]), reverse=True)
            futures = [client.submit(_run_on_worker, {**todo[i], "shared_reference": shared.folder}, pure=False,
                                     key=f"dslrxr-run-{run_id}-{i}-{Path(todo[i]['input']).name}",
                                     priority=len(todo) - rank)
                       for rank, i in enumerate(order)]
            by_key = {f.key: todo[i] for f, i in zip(futures, order, strict=True)}
            if scheduler == "local":
                # the workers start in the background, and dask only logs one that cannot start
                # (an import error, no free port): without a worker the batch would wait forever
                try:
                    client.wait_for_workers(1, timeout=WORKER_START_TIMEOUT_S)
                except TimeoutError:
                    raise ClusterError(f"no local dask worker started within {WORKER_START_TIMEOUT_S:.0f} s "
                                       "(set DSLRXR_DEBUG=1 to see dask's log)") from None
            console = Console(stderr=True, highlight=False)
            columns = (TextColumn("files"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
            # a bar on a terminal; logs and pipes get the per-file lines only
            with Progress(*columns, console=console, transient=True, disable=not console.is_terminal) as bar:
                task = bar.add_task("files", total=len(todo))
                for future in distributed.as_completed(futures, loop=client.loop):
                    if future.status == "error":  # the task raised on the worker: this file only
                        outcome = (by_key[future.key]["input"], False, _failed_task_message(future.exception()), 0.0, [])
                    elif future.status == "finished":
                        try:
                            outcome = future.result()
                        except (OSError, TimeoutError, distributed.client.FutureCancelledError) as exc:
                            raise ClusterError(f"lost the connection to {where} ({_short(exc)})") from None
                    else:  # cancelled or lost: the client is no longer connected to the scheduler
                        raise ClusterError(f"lost the connection to {where}")
                    finished += 1
                    report(finished, outcome)
                    unreported.pop(id(by_key[future.key]), None)
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


def _input_bytes(job: dict) -> int:
    """The size of a job's input file (0 when this host cannot see it): its work grows with it."""
    try:
        return os.stat(job["input"]).st_size
    except OSError:
        return 0


def _after_loss(finished: int, total: int) -> str:
    return (f"{finished} of {total} file(s) reported finished (files being processed then are either complete "
            "or absent, never partial); run the same command again to do the rest")

