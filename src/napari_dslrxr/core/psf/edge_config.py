"""The edge configuration file of ``dslrxr psf fit``: which edge radiographs, at which geometry."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .edge_images import EdgeImage


@dataclass
class EdgeConfig:
    """Parsed ``dslrxr psf fit`` configuration."""

    path: Path
    pixel_pitch_mm: float
    edges: list[EdgeImage]
    input_files: list[Path] = field(default_factory=list)
    shape_power: float = 1.0
    detector_core: str = "generalised"
    detector_tail: bool | None = None


def _number(config: Path, key: str, value, *, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(config, f"{key} must be a number, got {value!r}")
    if positive and value <= 0:
        raise InputError(config, f"{key} must be > 0, got {value!r}")
    return float(value)


def load_edge_config(path: str | os.PathLike) -> EdgeConfig:
    """Read a TOML edge-fit configuration and load its images.

    The file holds ``pixel_pitch_mm`` (mm, > 0), optional ``shape_power`` (1 or 2),
    ``detector_core`` (``"generalised"``, the default, or ``"exponential_power"``) and
    ``detector_tail`` (true/false; see :func:`~.edge_fit.fit_edges`), and one or more
    ``[[edges]]`` tables with ``image``, ``source_to_object_mm``, ``source_to_detector_mm`` and
    optional ``bright``, ``dark`` (file paths, relative to the config's folder) and
    ``roi = [r0, c0, r1, c1]``.

    Raises
    ------
    InputError
        Missing file, bad TOML, missing or ill-typed key (message names the file and the key),
        or an unreadable image.
    """
    from ..io import read_image, read_structured_file

    config = Path(path)
    record = read_structured_file(config, what="edge configuration")
    unknown_top = set(record) - {"pixel_pitch_mm", "shape_power", "detector_core", "detector_tail", "edges"}
    if unknown_top:
        raise InputError(config, f"unknown key {sorted(unknown_top)[0]!r} (expected pixel_pitch_mm, "
                                 f"shape_power, detector_core, detector_tail, [[edges]])")
    detector_core = record.get("detector_core", "generalised")
    if detector_core not in ("generalised", "exponential_power"):
        raise InputError(config, f"detector_core must be \"generalised\" or \"exponential_power\", "
                                 f"got {detector_core!r}")
    detector_tail = record.get("detector_tail")
    if detector_tail is not None and not isinstance(detector_tail, bool):
        raise InputError(config, f"detector_tail must be true or false, got {detector_tail!r}")
    if "pixel_pitch_mm" not in record:
        raise InputError(config, "missing key 'pixel_pitch_mm'")
    pitch = _number(config, "pixel_pitch_mm", record["pixel_pitch_mm"])
    shape_power = _number(config, "shape_power", record.get("shape_power", 1.0))
    if shape_power not in (1.0, 2.0):
        raise InputError(config, f"shape_power must be 1 or 2, got {shape_power!r}")
    entries = record.get("edges")
    if not isinstance(entries, list) or not entries or not all(isinstance(e, dict) for e in entries):
        raise InputError(config, "needs one or more [[edges]] tables")
    known = {"image", "source_to_object_mm", "source_to_detector_mm", "bright", "dark", "roi"}
    base = config.parent
    cache: dict[Path, np.ndarray] = {}
    inputs: list[Path] = []

    def load(key: str, value) -> np.ndarray:
        if not isinstance(value, str) or not value:
            raise InputError(config, f"{key} must be a file path string, got {value!r}")
        file = (base / value) if not Path(value).is_absolute() else Path(value)
        if file not in cache:
            if not file.is_file():
                raise InputError(config, f"{key}: no such file {file}")
            cache[file] = read_image(file).data
            inputs.append(file)
        return cache[file]

    edges = []
    for i, entry in enumerate(entries):
        where = f"edges[{i}]"
        unknown = set(entry) - known
        if unknown:
            raise InputError(config, f"{where}: unknown key {sorted(unknown)[0]!r}")
        for key in ("image", "source_to_object_mm", "source_to_detector_mm"):
            if key not in entry:
                raise InputError(config, f"{where}: missing key {key!r}")
        sod = _number(config, f"{where}.source_to_object_mm", entry["source_to_object_mm"])
        sdd = _number(config, f"{where}.source_to_detector_mm", entry["source_to_detector_mm"])
        if sdd < sod:
            raise InputError(config, f"{where}.source_to_detector_mm ({sdd:g}) is smaller than "
                                     f"source_to_object_mm ({sod:g})")
        roi = entry.get("roi")
        if roi is not None:
            if (not isinstance(roi, list) or len(roi) != 4
                    or not all(isinstance(v, int) and not isinstance(v, bool) for v in roi)):
                raise InputError(config, f"{where}.roi must be [r0, c0, r1, c1] integers, got {roi!r}")
            if roi[2] <= roi[0] or roi[3] <= roi[1] or min(roi) < 0:
                raise InputError(config, f"{where}.roi needs 0 <= r0 < r1 and 0 <= c0 < c1, got {roi!r}")
            roi = tuple(roi)
        image = load(f"{where}.image", entry["image"])
        bright = load(f"{where}.bright", entry["bright"]) if "bright" in entry else None
        dark = load(f"{where}.dark", entry["dark"]) if "dark" in entry else None
        edges.append(EdgeImage(image=image, source_to_object_mm=sod, source_to_detector_mm=sdd,
                               bright=bright, dark=dark, roi=roi, name=str(entry["image"])))
    return EdgeConfig(path=config, pixel_pitch_mm=pitch, edges=edges, input_files=inputs, shape_power=shape_power,
                      detector_core=detector_core, detector_tail=detector_tail)
