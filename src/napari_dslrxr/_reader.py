"""napari reader: camera raw (linear RGB), DICOM and TIFF radiographs; the CFA planes on request.

Thin adapters over :func:`napari_dslrxr.core.io.read_image`. ``get_reader`` only looks at the
file name, returns ``None`` for anything it does not claim and never raises. The reader
functions turn a core :class:`~napari_dslrxr.core.errors.DslrxrError` (corrupt file, wrong
shape, NaN...) into a napari notification and skip that file, so a bad file never crashes the
viewer.

There is one reader per extension, so napari never asks which of this plugin's readers to use.
The four Bayer (CFA) planes of a camera raw file are not a reader: :func:`read_cfa_planes` is
called by the menu commands of :mod:`napari_dslrxr._cfa_planes` (and ``dslrxr view
--cfa-planes``).

Each layer's metadata holds the source file, its format, the format facts and the input kind
(:func:`napari_dslrxr.core.io.input_kind.decide_input_kind`, under ``"input_kind"``), so the
contrast widget treats a CR/DX DICOM as a display radiograph and a raw file as a camera frame.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

from .core.errors import DslrxrError
from .core.io.input_kind import input_kind_of
from .core.io import DICOM_EXTENSIONS, RAW_EXTENSIONS, TIFF_EXTENSIONS, LoadedImage, read_image

#: Extensions claimed by the main reader (raw files open as linear RGB).
CLAIMED_EXTENSIONS = frozenset(RAW_EXTENSIONS | DICOM_EXTENSIONS | TIFF_EXTENSIONS)
#: Colour of each CFA plane layer, in the order of ``RawFrame.cfa_names``.
CFA_COLORMAPS = {"R": "red", "G1": "green", "G2": "green", "B": "blue"}

LayerDataTuple = tuple
ReaderFunction = Callable[[str | Sequence[str]], list[LayerDataTuple]]


def _as_paths(path: str | os.PathLike | Sequence[str | os.PathLike]) -> list[str] | None:
    """Return the list of paths napari passed, or None when it is not a path or list of paths."""
    if isinstance(path, (str, os.PathLike)):
        return [os.fspath(path)]
    if isinstance(path, (list, tuple)) and path and all(isinstance(p, (str, os.PathLike)) for p in path):
        return [os.fspath(p) for p in path]
    return None


def _claims(paths: list[str] | None, extensions: frozenset[str]) -> bool:
    return bool(paths) and all(Path(p).suffix.lower() in extensions for p in paths)


def get_reader(path) -> ReaderFunction | None:
    """Return the reader for radiographs and camera raw files, or None if not claimed.

    Parameters
    ----------
    path : str or list of str
        What napari asks about. Claimed when every path ends in a camera raw, DICOM or TIFF
        extension (see :data:`CLAIMED_EXTENSIONS`).

    Returns
    -------
    callable or None
        :func:`read_radiographs`, or None. Never raises.
    """
    try:
        return read_radiographs if _claims(_as_paths(path), CLAIMED_EXTENSIONS) else None
    except Exception:  # noqa: BLE001 - a reader probe must never raise into napari
        return None


def _notify_error(message: str) -> None:
    """Show a one-line error in napari (or warn when napari is not running)."""
    try:
        from napari.utils.notifications import show_error
    except ImportError:  # pragma: no cover - napari is present whenever a reader runs
        import warnings

        warnings.warn(message, stacklevel=3)
        return
    show_error(message)


def _load_each(path, **read_kwargs) -> list[LoadedImage]:
    paths = _as_paths(path) or []
    loaded = []
    for p in paths:
        try:
            loaded.append(read_image(p, **read_kwargs))
        except DslrxrError as exc:
            _notify_error(f"napari-dslrxr could not open {exc}")
    return loaded


def _layer_metadata(image: LoadedImage) -> dict:
    kind = input_kind_of(image)
    return {"source_path": str(image.path), "format": image.format, "file_metadata": dict(image.metadata),
            "input_kind": kind.as_record()}


def image_layer_tuple(image: LoadedImage) -> LayerDataTuple:
    """The image layer for one loaded file: grey, or RGB for colour and camera raw (linear)."""
    kwargs = {"name": image.path.stem, "metadata": _layer_metadata(image)}
    if image.is_colour:
        kwargs["rgb"] = True
    spacing = image.metadata.get("pixel_spacing_mm")
    if spacing:
        kwargs["scale"] = tuple(float(s) for s in spacing[:2])
        kwargs["units"] = ("mm", "mm")
    return (image.data, kwargs, "image")


def read_radiographs(path) -> list[LayerDataTuple]:
    """Read TIFF, DICOM or camera raw files into image layers.

    Camera raw opens as linear demosaiced RGB (uint16, gamma 1, camera white balance).
    DICOM pixel spacing becomes the layer scale in millimetres. Files that fail to read are
    reported as napari notifications and skipped.

    Returns
    -------
    list of (data, kwargs, "image")
        One tuple per file read; ``[(None,)]`` (claimed, nothing added) if none could be read.
    """
    layers = [image_layer_tuple(img) for img in _load_each(path, with_raw_planes=False)]
    return layers or [(None,)]


def read_cfa_planes(path) -> list[LayerDataTuple]:
    """Read camera raw files as four CFA plane layers each (R, G1, G2, B).

    Not a reader contribution (one reader per extension avoids napari's reader dialog): the
    menu commands of :mod:`napari_dslrxr._cfa_planes` call it.

    The planes are float32 counts above the black level. Each layer has scale 2 and is
    translated by its offset in the Bayer cell, so it overlays the demosaiced image in world
    coordinates.
    """
    layers = []
    for img in _load_each(path, with_raw_planes=True):
        raw = img.raw
        if raw is None:  # pragma: no cover - read_image always gives planes for raw input
            _notify_error(f"napari-dslrxr: {img.path} has no CFA planes")
            continue
        for plane, name, offset in zip(raw.cfa_planes, raw.cfa_names, raw.plane_offsets, strict=True):
            meta = _layer_metadata(img) | {
                "cfa_plane": name,
                "black_level": float(raw.black_level[raw.cfa_names.index(name)]),
                "white_level": int(raw.white_level),
            }
            kwargs = {
                "name": f"{img.path.stem} {name}",
                "colormap": CFA_COLORMAPS.get(name, "gray"),
                "blending": "additive",
                "scale": (2.0, 2.0),
                "translate": (float(offset[0]), float(offset[1])),
                "metadata": meta,
            }
            layers.append((plane, kwargs, "image"))
    return layers or [(None,)]
