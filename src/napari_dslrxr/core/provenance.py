"""Provenance: the JSON sidecar written beside every output.

A sidecar records what is needed to reproduce an output: the package version, the command
or stage, every parameter, and the SHA-256 of every input and of the output itself. Stage
timings are recorded too (they are the only field that changes between identical runs).
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from .io import atomic_write, file_sha256


def sidecar_path(output: str | os.PathLike) -> Path:
    """The sidecar of ``out.tif`` is ``out.tif.json``."""
    output = Path(output)
    return output.with_name(output.name + ".json")


def to_jsonable(value: Any) -> Any:
    """Convert dataclasses, paths and numpy values into plain JSON types."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def describe_inputs(inputs: Iterable[str | os.PathLike]) -> list[dict]:
    """Path, size and SHA-256 of each input file."""
    return [{"path": str(p), "bytes": Path(p).stat().st_size, "sha256": file_sha256(p)} for p in inputs]


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
    record = {
        "software": "napari-dslrxr",
        "version": __version__,
        "stage": stage,
        "parameters": to_jsonable(parameters),
        "inputs": describe_inputs(inputs),
        "output": {"path": output.name, "sha256": file_sha256(output)},
        "results": to_jsonable(dict(results or {})),
        "timings_s": {k: round(float(v), 4) for k, v in (timings_s or {}).items()},
        "environment": {"python": platform.python_version(), "numpy": np.__version__},
    }
    text = json.dumps(record, indent=2, sort_keys=False, allow_nan=False) + "\n"
    target = sidecar_path(output)
    return atomic_write(target, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
