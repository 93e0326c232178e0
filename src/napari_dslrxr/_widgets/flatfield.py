"""Flat-field widget over :mod:`napari_dslrxr.core.stages.flatfield`.

The user picks the radiograph, the flat (open beam) and optionally the dark frame, each as a
layer; a file chosen with the "flat file"/"dark file" pickers is read with the core reader and
added as a layer first, so layers and files take the same path. With "live preview" on, every
change of a parameter or of a picked layer recomputes ``"<layer> flat-fielded"`` (debounced,
in a thread worker); "Apply" does the same on demand.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import CheckBox, Container, FileEdit, PushButton, create_widget

from ..core.errors import ParameterError
from ..core.stages.flatfield import FlatFieldParams, apply_flat_field, prepare_flat_reference, saturated_flat_message
from ..core.io import read_image
from ._controls import param_widget, restore_defaults_button
from ._jobs import JobPanel, guarded, job_done, notify_error, readout_label, run_in_worker, scroll_long_readout
from ._layers import debounced, remove_layer, robust_limits, same_geometry, show_layer, show_layer_steps
from ._registry import register_stage_widget

if TYPE_CHECKING:
    import napari

_DEBOUNCE_MS = 150


def correct_with_layers(image: np.ndarray, flat: np.ndarray | None, dark: np.ndarray | None,
                        params: FlatFieldParams, progress=None) -> tuple[np.ndarray, int, tuple[float, float], str]:
    """Core call of the widget: prepare the reference and apply it (runs in the worker).

    ``progress``: the core's progress callback (the job panel's stops the preparation at
    its next step when Cancel is pressed). Returns the corrected float32 counts, the
    number of pulse pixels cleaned from the reference frames, the result's display range
    (computed here, not on the GUI thread) and a warning ("" when none): a clipped flat.
    """
    reference = prepare_flat_reference(image.shape, flats=[] if flat is None else [flat],
                                       darks=[] if dark is None else [dark], params=params, progress=progress)
    corrected = apply_flat_field(image, reference)
    return corrected, reference.cleaned_pulses, robust_limits(corrected), saturated_flat_message(reference)


class FlatFieldWidget(Container):
    """Flat-field correct an image layer with flat and dark layers (or files)."""

    SECTION = "flatfield"

    def __init__(self, viewer: napari.viewer.Viewer):
        self._viewer = viewer
        self._image = create_widget(annotation="napari.layers.Image", label="radiograph")
        self._image.tooltip = "the radiograph to correct (camera counts, as captured)"
        self._flat = create_widget(annotation="napari.layers.Image | None", label="flat (open beam)")
        self._flat.tooltip = ("open-beam frame: X-rays on, nothing in the beam, same camera settings; "
                              "corrects uneven screen brightness and lens vignetting")
        self._dark = create_widget(annotation="napari.layers.Image | None", label="dark (optional)")
        self._dark.tooltip = "dark frame: X-rays off, same exposure; removes the camera's black level"
        filters = "*.tif *.tiff *.dcm *.dng *.cr2 *.nef *.arw"
        self._flat_file = FileEdit(mode="r", label="or flat file", filter=filters,
                                   tooltip="read the flat frame from a file (added as a hidden layer)")
        self._dark_file = FileEdit(mode="r", label="or dark file", filter=filters,
                                   tooltip="read the dark frame from a file (added as a hidden layer)")
        self._smoothing = param_widget(FlatFieldParams, "flat_smoothing_px", label="flat smoothing (px)",
                                       section="flatfield", step=0.5)
        self._min_fraction = param_widget(FlatFieldParams, "min_flat_fraction", label="min flat fraction",
                                          section="flatfield")
        self._clean = param_widget(FlatFieldParams, "clean_flat_pulses", label="clean pulses in flat/dark",
                                   section="flatfield")
        self._preview = CheckBox(value=False, label="live preview",
                                 tooltip="recompute '<radiograph> flat-fielded (preview)' on every change; "
                                         "off removes the preview layer")
        self._apply = PushButton(text="Apply flat field",
                                 tooltip="correct the radiograph: (R - D) / (F - D) x mean(F - D); "
                                         "adds '<radiograph> flat-fielded'")
        self._restore = restore_defaults_button(lambda: self.set_params(FlatFieldParams()))
        self._job = JobPanel()
        self._readout = readout_label()
        super().__init__(widgets=[self._image, self._flat, self._flat_file, self._dark, self._dark_file,
                                  self._smoothing, self._min_fraction, self._clean, self._preview,
                                  self._apply, *self._job.widgets, self._readout, self._restore])
        scroll_long_readout(self._readout)  # a long result scrolls, the window keeps its size
        self._extra: dict = {}
        self.result: np.ndarray | None = None
        self._worker = None
        self._preview_layer: str | None = None
        self._flat_file.changed.connect(lambda: self._load_file(self._flat_file.value, self._flat, "flat"))
        self._dark_file.changed.connect(lambda: self._load_file(self._dark_file.value, self._dark, "dark"))
        self._apply.changed.connect(self.run)
        self._preview.changed.connect(self._preview_toggled)
        self._image.changed.connect(self._drop_preview)
        self._debounced_preview = debounced(self, self._preview_if_on, _DEBOUNCE_MS)
        for widget in (self._image, self._flat, self._dark, self._smoothing, self._min_fraction,
                       self._clean, self._preview):
            widget.changed.connect(self._debounced_preview)
        register_stage_widget(viewer, self)

    # -- parameters (TOML section [flatfield]) ----------------------------------------------
    def get_params(self) -> FlatFieldParams:
        values = dict(self._extra)
        values.update(flat_smoothing_px=float(self._smoothing.value),
                      min_flat_fraction=float(self._min_fraction.value),
                      clean_flat_pulses=bool(self._clean.value))
        return FlatFieldParams(**values)

    def set_params(self, params: FlatFieldParams) -> None:
        values = asdict(params)
        self._smoothing.value = values.pop("flat_smoothing_px")
        self._min_fraction.value = values.pop("min_flat_fraction")
        self._clean.value = values.pop("clean_flat_pulses")
        self._extra = values

    # -- files become layers ---------------------------------------------------------------------
    def _load_file(self, path, combo, role: str) -> None:
        path = Path(path) if path else None
        if path is None or not path.is_file():
            return
        try:
            loaded = read_image(path, with_raw_planes=False)
        except Exception as exc:  # noqa: BLE001
            notify_error(exc, context=f"{role} file")
            return
        layer = show_layer(self._viewer, loaded.data, f"{role}: {path.stem}", "image",
                           rgb=loaded.is_colour, visible=False)
        combo.reset_choices()
        combo.value = layer

    # -- actions ---------------------------------------------------------------------------------
    def _preview_toggled(self, on: bool) -> None:
        if not on:
            self._drop_preview()

    def _drop_preview(self, *_args) -> None:
        """Remove the preview layer (preview turned off, or another radiograph chosen)."""
        if self._preview_worker_running():
            self._worker.quit()
        if self._preview_layer is not None:
            remove_layer(self._viewer, self._preview_layer)
            self._preview_layer = None

    def _preview_worker_running(self) -> bool:
        return self._worker is not None and not getattr(self._worker, "dslrxr_finished", True)

    def _preview_if_on(self) -> None:
        if self._preview.value and self._image.value is not None and self._flat.value is not None:
            self._start(preview=True)

    @guarded("flat field")
    def run(self):
        """Correct the radiograph in a thread worker; return the worker (None if not started)."""
        return self._start(preview=False)

    def _start(self, *, preview: bool):
        layer = self._image.value
        if layer is None:
            raise ParameterError("choose the radiograph layer")
        if self._flat.value is None:
            raise ParameterError("choose a flat (open-beam) layer or file")
        if self._preview_worker_running():
            self._worker.quit()  # superseded by newer parameters; its result is ignored
        image = np.asarray(layer.data)
        flat = np.asarray(self._flat.value.data)
        dark = None if self._dark.value is None else np.asarray(self._dark.value.data)
        params = self.get_params()
        if preview:
            worker = run_in_worker(correct_with_layers, image, flat, dark, params, desc="flat field preview",
                                   progress_bar=False, on_returned=lambda out: self._show(layer, out, True))
            self._worker = worker
            return worker
        self._apply.enabled = False
        self._readout.value = "running..."
        return run_in_worker(correct_with_layers, image, flat, dark, params, desc="flat field",
                             progress=self._job.callback, on_returned=lambda out: self._show(layer, out, False),
                             on_finished=job_done(self._apply, self._job, self._readout),
                             panel=self._job, readout=self._readout)

    def _show(self, layer: napari.layers.Image, out: tuple[np.ndarray, int, tuple[float, float], str],
              preview: bool) -> Iterator[None]:
        """Show the result (a new layer over two event-loop turns, :func:`show_layer_steps`)."""
        corrected, cleaned, limits, warning = out
        if preview and not self._preview.value:
            return  # turned off while it computed
        name = f"{layer.name} flat-fielded" + (" (preview)" if preview else "")
        yield from show_layer_steps(self._viewer, corrected, name, "image",
                   rgb=bool(getattr(layer, "rgb", False)) and corrected.ndim == 3, contrast_limits=limits,
                   **same_geometry(layer))
        if preview:
            self._preview_layer = name
        else:
            self.result = corrected
        self._readout.value = (f"{'preview: ' if preview else ''}corrected {corrected.shape[1]}x{corrected.shape[0]} "
                               f"px; {cleaned} pulse px cleaned in the reference frames"
                               + (f"\nwarning: {warning}" if warning else ""))
