"""The PSF file (``psf.json``): writing a :class:`~.model.PSFModel` and reading it back, validated."""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..errors import InputError, ParameterError
from ..io import atomic_write
from .model import CORE_MTF_NAMES, PARAMETER_NAMES, PSF_FORMAT, PSFModel

#: Format versions :func:`load_psf` reads (version 1: exponential-power core, source always given).
READABLE_FORMAT_VERSIONS = (1, 2)


def save_psf(model: PSFModel, path: str | os.PathLike, *, inputs=()) -> Path:
    """Write ``model`` to ``path`` (``psf.json``) atomically.

    Parameters
    ----------
    model : PSFModel
    path : path-like
        Destination; refused when it is one of ``inputs``.
    inputs : iterable of path-like
        Input files of the fit (never overwritten).

    Returns
    -------
    Path
    """
    from ..io.provenance import to_jsonable

    text = json.dumps(to_jsonable(model.to_dict()), indent=2, allow_nan=False) + "\n"
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"), inputs=inputs)


def load_psf(path: str | os.PathLike) -> PSFModel:
    """Read and validate a ``psf.json`` written by :func:`save_psf`.

    Raises
    ------
    InputError
        When the file is missing, not JSON, not a PSF file, or a field is missing, ill-typed or
        out of range (the one-line message names the file and the key).
    """
    from ..io import read_structured_file

    path = Path(path)
    record = read_structured_file(path, what="PSF file", fmt="json")
    if record.get("format") != PSF_FORMAT:
        raise InputError(path, f"not a PSF file (expected \"format\": \"{PSF_FORMAT}\")")
    version = record.get("format_version")
    if isinstance(version, bool) or version not in READABLE_FORMAT_VERSIONS:
        raise InputError(path, f"unsupported format_version {version!r} "
                               f"(this version reads {', '.join(map(str, READABLE_FORMAT_VERSIONS))})")
    kwargs = {}
    source_fitted = record.get("source_fitted", True)
    if not isinstance(source_fitted, bool):
        raise InputError(path, f"key 'source_fitted' must be true or false, got {source_fitted!r}")
    kwargs["source_fitted"] = source_fitted
    keys = ("pixel_pitch_mm",) + PARAMETER_NAMES + ("shape_power",) + (CORE_MTF_NAMES if version >= 2 else ())
    for key in keys:
        if key not in record:
            raise InputError(path, f"missing key {key!r}")
        value = record[key]
        if value is None and ((key.startswith("source_fwhm") and not source_fitted)
                              or key == "detector_fwhm_core_mm"):
            kwargs[key] = 0.0
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(path, f"key {key!r} must be a number, got {value!r}")
        kwargs[key] = float(value)
    for key in ("uncertainty", "fit_report"):
        value = record.get(key, {})
        if not isinstance(value, dict):
            raise InputError(path, f"key {key!r} must be an object, got {type(value).__name__}")
        kwargs[key] = value
    try:
        return PSFModel(**kwargs)
    except ParameterError as exc:
        raise InputError(path, str(exc)) from None
