"""One input file of ``dslrxr run``: the job every way of running a batch (one after the other, a
process pool, dask.distributed workers) hands to :func:`~napari_dslrxr.core.files.run_file`."""

from __future__ import annotations

import ctypes
import ctypes.util
import platform
import sys
import time

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
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8  # mallopt's parameter numbers (malloc.h)


def keep_freed_memory() -> bool:
    """Give this process the heap settings of :data:`HEAP_ENVIRON` (glibc only; elsewhere
    nothing changes). Returns whether they were applied. The process holds its peak memory
    until it exits: for processes that only run files (``dslrxr run`` and its workers)."""
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        return all(libc.mallopt(param, value) == 1 for param, value in (
            (_M_MMAP_THRESHOLD, HEAP_THRESHOLD_BYTES), (_M_TRIM_THRESHOLD, HEAP_THRESHOLD_BYTES), (_M_ARENA_MAX, 1)))
    except (OSError, AttributeError):
        return False


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


def process_one(job: dict, reference_cache: dict | None = None) -> tuple[str, bool, str, float, list[str]]:
    """Worker: run one input; returns (input, ok, message, seconds, warnings). Picklable for processes.

    ``reference_cache`` (sequential runs) keeps the prepared flat reference between files.
    """
    from ..core.params import params_from_dict
    from ..core.files import run_file

    t0 = time.perf_counter()
    try:
        params = params_from_dict(job["params"])
        written = run_file(job["input"], job["out_dir"], params=params, flat_paths=job["flats"],
                           dark_paths=job["darks"], psf_path=job["psf"],
                           source_to_object_mm=job["sod"], source_to_detector_mm=job["sdd"],
                           patient=job["patient"], reference_cache=reference_cache,
                           warn=lambda line: print(f"dslrxr: {job['input']}: {line}", file=sys.stderr))
        return (job["input"], True, f"wrote {len(written)} file(s)", time.perf_counter() - t0,
                sidecar_warnings(written))
    except DslrxrError as exc:
        return job["input"], False, str(exc), time.perf_counter() - t0, []
    except MemoryError:
        return job["input"], False, "out of memory", time.perf_counter() - t0, []
