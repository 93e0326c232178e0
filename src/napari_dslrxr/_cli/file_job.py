"""One input file of ``dslrxr run``: the job every way of running a batch (one after the other, a
process pool, dask.distributed workers) hands to :func:`~napari_dslrxr.core.files.run_file`."""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import platform
import sys
import time
from collections.abc import Iterator

from ..core.errors import DslrxrError

#: glibc's heap settings for a process that runs files. By default an array above 32 MB (every
#: 24 MP temporary of the pipeline) is a fresh memory mapping, which the kernel zeroes page by
#: page on first touch and unmaps when freed: 15-25 % of a run's CPU time went to those page
#: faults. Served from the heap, and the freed memory kept (not trimmed) for the next array, a
#: file after the first faults almost no page in. One arena: a dask worker runs its tasks in a
#: thread, and a thread's own arena maps every large array afresh whatever the threshold.
HEAP_THRESHOLD_BYTES = 2**31 - 1  # the largest value mallopt takes; larger arrays are mapped as before
HEAP_ENVIRON = {"MALLOC_MMAP_THRESHOLD_": str(HEAP_THRESHOLD_BYTES),
                "MALLOC_TRIM_THRESHOLD_": str(HEAP_THRESHOLD_BYTES), "MALLOC_ARENA_MAX": "1"}
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt's parameter numbers (malloc.h)


def _glibc():
    """The C library, when it is glibc (whose heap settings these are); else None."""
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
    except (OSError, AttributeError):
        return None
    return libc


def keep_freed_memory() -> bool:
    """Give this process the heap thresholds of :data:`HEAP_ENVIRON` (glibc only; elsewhere
    nothing changes); returns whether they were applied. Large arrays allocated from then on come
    from the heap, and freed memory stays in the process: for a process that runs files (a pool
    worker) until it ends, or within :func:`freed_memory_kept`. Its main thread uses the main
    arena, so the arena limit (for threads that start later) is left alone."""
    libc = _glibc()
    return libc is not None and all(libc.mallopt(param, HEAP_THRESHOLD_BYTES) == 1
                                    for param in (_M_MMAP_THRESHOLD, _M_TRIM_THRESHOLD))


#: glibc's largest dynamic mapping threshold (32 MiB on 64-bit) and the trim threshold it pairs with
#: it, set back after :func:`freed_memory_kept` (a dynamic threshold, once fixed, cannot be restored).
_DEFAULT_MMAP_THRESHOLD_BYTES = 32 * 2**20
_DEFAULT_TRIM_THRESHOLD_BYTES = 2 * _DEFAULT_MMAP_THRESHOLD_BYTES


@contextlib.contextmanager
def freed_memory_kept() -> Iterator[bool]:
    """:func:`keep_freed_memory` for a batch run in this process (``--jobs 1``, which may be a
    longer-lived process calling the command): afterwards the thresholds are set back to glibc's
    usual large-array values and the freed memory is returned to the system."""
    applied = keep_freed_memory()
    try:
        yield applied
    finally:
        if applied:
            libc = _glibc()
            libc.mallopt(_M_MMAP_THRESHOLD, _DEFAULT_MMAP_THRESHOLD_BYTES)
            libc.mallopt(_M_TRIM_THRESHOLD, _DEFAULT_TRIM_THRESHOLD_BYTES)
            libc.malloc_trim(0)


def sidecar_warnings(written: list) -> list[str]:
    """The warnings a run recorded in its sidecar (stages skipped or guessed)."""
    import json

    from ..core.io.provenance import sidecar_path

    for path in written:
        try:
            return list(json.loads(sidecar_path(path).read_text(encoding="utf-8"))["results"].get("warnings", []))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return []


def process_one(job: dict, reference_cache: dict | None = None,
                reference=None) -> tuple[str, bool, str, float, list[str]]:
    """Worker: run one input; returns (input, ok, message, seconds, warnings). Picklable for processes.

    ``reference_cache`` keeps the prepared flat reference between files; ``reference`` (a
    worker's) gives the batch's shared one (:func:`~.shared_reference.worker_reference`).
    """
    from ..core.params import params_from_dict
    from ..core.files import run_file

    t0 = time.perf_counter()
    try:
        params = params_from_dict(job["params"])
        written = run_file(job["input"], job["out_dir"], params=params, flat_paths=job["flats"],
                           dark_paths=job["darks"], psf_path=job["psf"],
                           source_to_object_mm=job["sod"], source_to_detector_mm=job["sdd"],
                           patient=job["patient"], reference_cache=reference_cache, reference=reference,
                           warn=lambda line: print(f"dslrxr: {job['input']}: {line}", file=sys.stderr))
        return (job["input"], True, f"wrote {len(written)} file(s)", time.perf_counter() - t0,
                sidecar_warnings(written))
    except DslrxrError as exc:
        return job["input"], False, str(exc), time.perf_counter() - t0, []
    except MemoryError:
        return job["input"], False, "out of memory", time.perf_counter() - t0, []


def remove_unfinished_outputs(jobs: list[dict]) -> None:
    """After an interruption, for the files ``jobs`` not reported finished: remove the temporary
    files of stopped writes, and an output its sidecar does not describe (renamed into place,
    then stopped before its sidecar), so only outputs a sidecar vouches for are left. Ctrl-C and
    SIGTERM wait meanwhile (a second one would leave the clean-up half done)."""
    import json
    import signal
    import threading

    from ..core.files import output_paths
    from ..core.io import file_sha256
    from ..core.io.provenance import sidecar_path
    from ..core.io.writers import remove_partial_writes
    from ..core.params import params_from_dict

    in_main_thread = threading.current_thread() is threading.main_thread()  # where signals are set
    held = ({sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
            if in_main_thread else {})
    try:
        for job in jobs:
            for path in output_paths(job["input"], job["out_dir"], params_from_dict(job["params"])).values():
                remove_partial_writes(path)
                if not path.exists():
                    continue
                try:
                    described = json.loads(sidecar_path(path).read_text())["output"]["sha256"] == file_sha256(path)
                except (OSError, ValueError, KeyError, TypeError):
                    described = False
                if not described:
                    path.unlink(missing_ok=True)
    finally:
        for sig, handler in held.items():
            signal.signal(sig, handler)
