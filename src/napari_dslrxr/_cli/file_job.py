"""One input file of ``dslrxr run``: the job every way of running a batch (one after the other, a
process pool, dask.distributed workers) hands to :func:`~napari_dslrxr.core.files.run_file`."""

from __future__ import annotations

import sys
import time

from ..core.errors import DslrxrError


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
