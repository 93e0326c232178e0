"""Menu commands that show the four Bayer (CFA) planes of a camera raw file.

The planes are not a second reader for the raw extensions (two readers from one plugin make
napari ask which to use); they are reached from the menus:

* *Layers > Data > Show Bayer (CFA) planes of the selected raw layer*: reads the planes of the
  file the selected layer was opened from (its ``source_path`` metadata);
* *File > IO Utilities > Open camera raw as Bayer (CFA) planes...*: asks for the files.

Both go through :func:`napari_dslrxr._reader.read_cfa_planes`, so the planes are float32 counts
above black, each scaled by 2 and offset within the Bayer cell so they overlay the RGB image.
"""

from __future__ import annotations

from pathlib import Path

import napari
from napari.layers import Layer

from ._reader import _notify_error, read_cfa_planes
from .core.io import RAW_EXTENSIONS

#: File-dialog filter for camera raw files.
RAW_FILTER = "Camera raw (" + " ".join(f"*{e}" for e in sorted(RAW_EXTENSIONS)) + ")"


def add_cfa_planes(viewer: napari.viewer.Viewer, paths: list[str]) -> list[Layer]:
    """Read the CFA planes of ``paths`` and add them to ``viewer``; return the layers added.

    Files that cannot be read are reported as napari notifications (nothing raises).
    """
    added = []
    for layer_tuple in read_cfa_planes([str(p) for p in paths]):
        if layer_tuple[0] is None:  # nothing readable (already notified)
            continue
        added.append(viewer.add_layer(Layer.create(*layer_tuple)))
    return added


def _raw_source(layer) -> str | None:
    meta = getattr(layer, "metadata", None) or {}
    source = meta.get("source_path")
    if meta.get("format") == "raw" and source and Path(source).suffix.lower() in RAW_EXTENSIONS:
        return str(source)
    return None


def show_cfa_planes(viewer: napari.viewer.Viewer) -> list[Layer]:
    """Show the CFA planes of the file the selected layer came from (a camera raw layer).

    Refuses with a notification when the selected layer was not opened from a camera raw file.
    """
    layer = viewer.layers.selection.active
    source = _raw_source(layer) if layer is not None else None
    if source is None:
        name = f"'{layer.name}' was not" if layer is not None else "no layer is"
        _notify_error(f"Bayer planes: {name} opened from a camera raw file (CR2, NEF, DNG...); "
                      "select such a layer, or use File > IO Utilities > Open camera raw as Bayer (CFA) planes")
        return []
    if not Path(source).is_file():
        _notify_error(f"Bayer planes: {source}: the source file is gone")
        return []
    return add_cfa_planes(viewer, [source])


def open_cfa_planes(viewer: napari.viewer.Viewer) -> list[Layer]:
    """Ask for camera raw files and show their CFA planes."""
    from qtpy.QtWidgets import QFileDialog

    paths, _ = QFileDialog.getOpenFileNames(None, "Open camera raw as Bayer (CFA) planes", "", RAW_FILTER)
    return add_cfa_planes(viewer, list(paths)) if paths else []
