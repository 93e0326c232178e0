"""Provenance: the JSON sidecar written beside every output.

A sidecar records what is needed to reproduce an output: the package version, the command
or stage, every parameter, and the SHA-256 of every input and of the output itself. Stage
timings are recorded too (they are the only field that changes between identical runs).
"""

from __future__ import annotations

import dataclasses
import enum
import importlib.metadata
import json
import math
import os
import platform
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ... import __version__
from ..errors import InputError, OutputError
from .writers import atomic_write, file_sha256

#: Distributions whose versions can change an output's bytes; recorded in every sidecar.
_RECORDED_LIBRARIES = ("numpy", "scipy", "scikit-image", "tifffile", "pydicom", "rawpy",
                       "opencv-contrib-python-headless", "opencv-python-headless", "opencv-python")


def sidecar_path(output: str | os.PathLike) -> Path:
    """The sidecar of ``out.tif`` is ``out.tif.json``."""
    output = Path(output)
    return output.with_name(output.name + ".json")


def to_jsonable(value: Any) -> Any:
    """Convert dataclasses, paths, enums, sets and numpy values into plain JSON types.

    Non-finite floats (also inside numpy arrays and scalars) become ``None``, because JSON
    has no NaN; anything else unknown is recorded by its ``str``.
    """
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, enum.Enum):
        return to_jsonable(value.value)
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, (set, frozenset)):
        return sorted((to_jsonable(v) for v in value), key=repr)
    if isinstance(value, (Path, os.PathLike)):
        return os.fspath(value)
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        return to_jsonable(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if value is None or isinstance(value, (bool, int, str)):
        return value
    return str(value)


def describe_inputs(inputs: Iterable[str | os.PathLike]) -> list[dict]:
    """Path, size and SHA-256 of each input file.

    Raises
    ------
    InputError
        If an input cannot be read (for example, it vanished during the run).
    """
    described = []
    for p in inputs:
        try:
            described.append({"path": os.fspath(p), "bytes": Path(p).stat().st_size,
                              "sha256": file_sha256(p)})
        except OSError as exc:
            raise InputError(p, f"cannot checksum input ({exc.strerror or exc})") from None
    return described


def library_versions() -> dict[str, str]:
    """Versions of Python, the platform and the libraries that decode and process images."""
    versions = {"python": platform.python_version(), "platform": platform.platform(terse=True)}
    for dist in _RECORDED_LIBRARIES:
        try:
            versions[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            continue
    try:
        import rawpy

        versions["libraw"] = str(rawpy.libraw_version)
    except (ImportError, AttributeError):
        pass
    return versions


def write_sidecar(output: str | os.PathLike, *, stage: str, parameters: Any,
                  inputs: Iterable[str | os.PathLike] = (), timings_s: Mapping[str, float] | None = None,
                  results: Mapping[str, Any] | None = None) -> Path:
    """Write ``<output>.json`` atomically and return its path.

    Parameters
    ----------
    output : path-like
        The output file the sidecar describes (it must exist already).
    stage : str
        The command or stage that produced it, e.g. ``"denoise"``.
    parameters : dataclass or mapping
        Every parameter used.
    inputs : iterable of path-like
        Input files (checksummed).
    timings_s : mapping, optional
        Wall time per stage in seconds.
    results : mapping, optional
        Numbers worth keeping (estimated gain, pulse counts...).
    """
    output = Path(output)
    try:
        output_sha256 = file_sha256(output)
    except OSError as exc:
        raise OutputError(f"{output}: cannot checksum the output ({exc.strerror or exc})") from None
    record = {
        "software": "napari-dslrxr",
        "version": __version__,
        "stage": stage,
        "parameters": to_jsonable(parameters),
        "inputs": describe_inputs(inputs),
        "output": {"path": output.name, "sha256": output_sha256},
        "results": to_jsonable(dict(results or {})),
        "timings_s": {k: round(float(v), 4) for k, v in (timings_s or {}).items()},
        "environment": library_versions(),
    }
    text = json.dumps(record, indent=2, sort_keys=False, allow_nan=False) + "\n"
    target = sidecar_path(output)
    return atomic_write(target, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
