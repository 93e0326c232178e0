"""napari writers: an image layer as a DICOM DX radiograph or a 16-bit TIFF, each with its sidecar.

Thin adapters over the core writers (:func:`napari_dslrxr.core.io.dicom.write_dicom_dx`,
:func:`napari_dslrxr.core.io.write_tiff`) and the core provenance
(:func:`napari_dslrxr.core.io.provenance.write_sidecar`), so a result tuned in napari is exported
as ``dslrxr run`` would export it: the JSON sidecar ``<file>.json`` records the package version,
the pipeline parameters of the stage widgets docked in the viewer (the defaults for sections
without a widget), the checksum of the layer's source file when the layer was opened from one,
and how the layer's values were mapped to 16 bits.

Values: ``uint16`` data is written unchanged; ``uint8`` is scaled by 257; other integers in
0..65535 are written unchanged; anything else (float results, wider integers) is mapped
through the layer's contrast limits (what the user sees) to 0..65535. A DICOM DX holds one
grey image, so a colour layer is refused for DICOM (save it as TIFF). A layer the reader marked
as a camera frame is written with ``PixelIntensityRelationship = LIN`` (linear counts), any other
as ``LOG`` (a display image); a TIFF's description records the same (``input_kind``), so the
input-kind rule reads either file back as what it is.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from .core.errors import OutputError
from .core.params import PipelineParams, params_to_toml
from .core.pipeline import to_uint16

#: Units napari may report for a layer scale in millimetres.
_MM_UNITS = ("mm", "millimeter", "millimetre")


def layer_to_uint16(data: Any, attributes: dict, path: str | Path) -> tuple[np.ndarray, dict]:
    """The layer's pixels as a 2-D (or RGB) uint16 array and how they were mapped.

    Raises
    ------
    OutputError
        Not a single 2-D image (a stack or volume), or non-finite values.
    """
    if attributes.get("multiscale"):
        data = data[0]  # the full-resolution level
    arr = np.asarray(data)
    rgb = bool(attributes.get("rgb")) and arr.ndim == 3 and arr.shape[-1] in (3, 4)
    if rgb:
        arr = arr[..., :3]
    if arr.ndim != (3 if rgb else 2):
        raise OutputError(f"{path}: saves one 2-D image; layer '{attributes.get('name', '')}' has shape "
                          f"{arr.shape}")
    if arr.dtype == np.uint16:
        return arr, {"kind": "unchanged (uint16)"}
    if arr.dtype == np.uint8 or arr.dtype == bool:
        return arr.astype(np.uint16) * np.uint16(257 if arr.dtype == np.uint8 else 65535), {
            "kind": "scaled to 16 bits", "factor": 257 if arr.dtype == np.uint8 else 65535}
    if arr.dtype.kind in "iu" and arr.size and arr.min() >= 0 and arr.max() <= 65535:
        return arr.astype(np.uint16), {"kind": f"unchanged ({arr.dtype} within 0..65535)"}
    values = arr.astype(np.float64)
    if not np.all(np.isfinite(values)):
        raise OutputError(f"{path}: layer '{attributes.get('name', '')}' holds NaN or infinite values")
    lo, hi = (float(v) for v in attributes.get("contrast_limits") or (values.min(), values.max()))
    if not hi > lo:
        hi = lo + 1.0
    mapped = to_uint16((values - lo) / (hi - lo))  # float64: no float32 rounding at the steps
    return mapped, {"kind": "contrast limits to 0..65535", "contrast_limits": [lo, hi]}


def _pixel_spacing_mm(attributes: dict) -> tuple[float, float] | None:
    units = attributes.get("units") or ()
    scale = attributes.get("scale")
    if scale is None or len(units) < 2 or len(scale) < 2:
        return None
    if not all(str(u).strip().lower() in _MM_UNITS for u in list(units)[-2:]):
        return None
    spacing = tuple(float(s) for s in list(scale)[-2:])
    return spacing if all(np.isfinite(s) and s > 0 for s in spacing) else None


def _viewer_params() -> PipelineParams:
    """The parameters of the stage widgets docked in the current viewer (defaults without one)."""
    try:
        import napari

        viewer = napari.current_viewer()
    except ImportError:  # pragma: no cover - writers run inside napari
        viewer = None
    if viewer is None:
        return PipelineParams()
    from ._widgets.params_file import collect_params

    return collect_params(viewer)


def _source(attributes: dict, out: Path) -> tuple[list[Path], dict]:
    """The layer's source file (an input to checksum, if it still exists) and its facts."""
    meta = attributes.get("metadata") or {}
    facts = {key: meta[key] for key in ("source_path", "format", "input_kind", "cfa_plane") if key in meta}
    source = meta.get("source_path")
    if source and Path(source).is_file() and Path(source).resolve() != out.resolve():
        return [Path(source)], facts
    facts["source"] = "no source file (a layer made in napari)" if not source else f"{source} not found"
    return [], facts


def _write(path: str, data: Any, attributes: dict, fmt: str) -> list[str]:
    from . import __version__
    from .core.io.provenance import write_sidecar

    out = Path(path)
    pixels, mapping = layer_to_uint16(data, attributes, out)
    params = _viewer_params()
    inputs, source = _source(attributes, out)
    spacing = _pixel_spacing_mm(attributes)
    name = str(attributes.get("name", out.stem))
    # A layer the reader marked as a camera frame holds linear counts; say so in the DICOM, so
    # reopening it (or dslrxr run on it) takes the camera path. Layers made in napari (results)
    # are display images.
    linear = (source.get("input_kind") or {}).get("kind") == "camera"
    if fmt == "dicom":
        if pixels.ndim != 2:
            raise OutputError(f"{out}: a DICOM DX holds one grey image; layer '{name}' is colour "
                              "(save it as TIFF)")
        from .core.io.dicom import write_dicom_dx

        seed = hashlib.sha256(pixels.tobytes() + name.encode() + params_to_toml(params, comments=False).encode())
        write_dicom_dx(out, pixels, uid_seed=seed.hexdigest(), pixel_spacing_mm=spacing, inputs=inputs,
                       series_description=f"napari-dslrxr: {name}"[:64], linear=linear)
    else:
        from .core.io import write_tiff

        description = json.dumps({"software": "napari-dslrxr", "version": __version__, "stage": "napari-save",
                                  "layer": name, "input_kind": "camera" if linear else "display"}, sort_keys=True)
        write_tiff(out, pixels, description=description, inputs=inputs,
                   resolution_px_per_mm=(1.0 / spacing[1]) if spacing else None)
    results = {"layer": name, "shape": list(pixels.shape), "value_mapping": mapping, "source": source,
               "pixel_spacing_mm": list(spacing) if spacing else None,
               "format": "DICOM DX (For Presentation)" if fmt == "dicom" else "16-bit TIFF"}
    if fmt == "dicom":
        results["pixel_intensity_relationship"] = "LIN" if linear else "LOG"
    write_sidecar(out, stage="napari-save", parameters=params, inputs=inputs, results=results)
    return [str(out)]


def write_dicom(path: str, data: Any, attributes: dict) -> list[str]:
    """npe2 single-layer writer: an image layer as a DICOM DX file plus ``<file>.json``."""
    return _write(path, data, attributes, "dicom")


def write_tiff(path: str, data: Any, attributes: dict) -> list[str]:
    """npe2 single-layer writer: an image layer as a 16-bit TIFF plus ``<file>.json``."""
    return _write(path, data, attributes, "tiff")
