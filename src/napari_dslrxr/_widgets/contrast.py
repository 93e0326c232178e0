"""Contrast widget: dynamic range, latitude, detail and bone-contrast sliders with live preview.

Wraps the display stages of the core, as :func:`napari_dslrxr.core.pipeline.enhance_radiograph`
chains them: value-of-interest scaling, then
:func:`~napari_dslrxr.core.display.apply_display_stages` (:mod:`~napari_dslrxr.core.stages.dynamic_range`
latitude reduction, :mod:`~napari_dslrxr.core.stages.contrast` MUSICA-style multiscale contrast and the
sigmoid display curve). The value-of-interest scaling does not depend on the sliders, so it is done
once per input and cached; a slider move runs only the three later stages. Two kinds of input:

* **linear counts** (a camera frame, flat-fielded or not): converted once to the
  value-of-interest scaled attenuation image and the screen mask by the core pipeline with
  the display stages switched off (:func:`napari_dslrxr.core.pipeline.process_frame`);
* **display radiograph** (DICOM CR/DR, bright = bone): used as it is; a collimated field
  (:func:`napari_dslrxr.core.stages.collimation.detect_collimation`) is its region, as in the core.

The live preview runs on the whole image, area-downsampled to at most ``preview_max_pixels``
(default one megapixel, about what a screen shows), in a thread worker, debounced and
coalesced; it is drawn over the input at full size (layer scale). The low-pass kernel and the
pyramid depth of the core are relative to the image size, so the preview looks like the
full-resolution result that "Apply" computes.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np
from magicgui.widgets import CheckBox, ComboBox, Container, FloatSlider, PushButton, create_widget

from ..core.errors import ParameterError
from ..core.io.input_kind import InputKind, decide_input_kind
from ..core.params import PipelineParams
from ..core.display import apply_display_stages, scale_display_radiograph
from ..core.pipeline import process_frame
from ..core.stages.contrast import ContrastParams
from ..core.stages.dynamic_range import DynamicRangeParams
from ._controls import param_widget, restore_defaults_button
from ._jobs import JobPanel, guarded, job_done, readout_label, run_in_worker, scroll_long_readout
from ._layers import LivePreviewMixin, debounced, show_layer_steps
from ._registry import register_stage_widget

if TYPE_CHECKING:
    import napari

LINEAR, DISPLAY = "linear counts (camera frame)", "display radiograph (bright = bone)"
_DEBOUNCE_MS = 60

#: (section, field, label in the radiologist's words, technical term) of each slider; range,
#: default and help come from the field's metadata.
SLIDERS = (
    ("dynamic_range", "lut_width", "window width", "width of the sigmoid display curve (LUT)"),
    ("dynamic_range", "lut_center", "window level", "centre of the sigmoid display curve (LUT)"),
    ("dynamic_range", "latitude", "latitude", "low-frequency gain of dynamic-range reduction"),
    ("dynamic_range", "detail_gain", "detail gain", "gain above the low-pass kernel (unsharp masking)"),
    ("contrast", "detail_contrast", "fine detail", "MUSICA coefficient power p = 1 - 0.7 x value"),
    ("contrast", "bone_contrast", "bone contrast", "gain of coarse detail below the coarse halo step "
                                                   "(local Laplacian remapping of the coarse bands)"),
    ("contrast", "edge_sharpness", "edge enhancement", "gain of the finest Laplacian-pyramid band"),
    ("contrast", "halo_step", "halo guard", "edge-step threshold of unit gain (0 = off)"),
)
SECTION_CLASSES = {"dynamic_range": DynamicRangeParams, "contrast": ContrastParams}


@dataclass
class PreparedInput:
    """The value-of-interest scaled image the sliders act on, its region and a preview copy."""

    image: np.ndarray  # float32 (H, W), about 0..1 over the values of interest
    mask: np.ndarray | None  # bool (H, W) screen region, or None (all pixels)
    small: np.ndarray  # area-downsampled image for the preview
    small_mask: np.ndarray | None
    factor: float  # full-size pixels per preview pixel


def prepare_input(data: np.ndarray, kind: str, max_pixels: int, params: PipelineParams | None = None) -> PreparedInput:
    """Bring a layer's data to the value-of-interest scaled form the display stages take.

    Runs once per input (in the worker); the sliders do not change it. Linear counts go
    through the core pipeline with impulse removal, flat field, dynamic range and contrast
    switched off (no black level subtracted: the layer is taken as counts above black), giving
    the VOI-scaled attenuation and the screen mask. A display radiograph is VOI-scaled inside
    its collimated field by :func:`~napari_dslrxr.core.display.scale_display_radiograph`, as
    :func:`~napari_dslrxr.core.pipeline.enhance_radiograph` does (the mask; None when no blade
    is found).
    """
    params = params or PipelineParams()
    data = np.asarray(data)
    if kind == LINEAR:
        linear = dataclasses.replace(params, impulse=dataclasses.replace(
            params.impulse, passes_h=0, passes_s=0, passes_v=0, passes_grey=0))
        linear.flatfield = dataclasses.replace(params.flatfield, enabled=False)
        linear.region = dataclasses.replace(params.region, rectify=False)
        linear.dynamic_range = dataclasses.replace(params.dynamic_range, enabled=False)
        linear.contrast = dataclasses.replace(params.contrast, enabled=False)
        result = process_frame(data, black_level=0.0, params=linear, keep_intermediates=True)
        image, mask = result.intermediates["attenuation"], result.region.mask
        if mask.all():
            mask = None
    else:
        image, mask, _ = scale_display_radiograph(data.mean(axis=2) if data.ndim == 3 else data, params)
    factor = max(1.0, float(np.sqrt(image.size / max_pixels)))
    if factor > 1.0:
        size = (max(8, round(image.shape[1] / factor)), max(8, round(image.shape[0] / factor)))
        small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        small_mask = None if mask is None else cv2.resize(
            mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
        factor = image.shape[0] / small.shape[0]
    else:
        small, small_mask = image, mask
    return PreparedInput(image, mask, small, small_mask, factor)


def render(prepared: PreparedInput | None, data: np.ndarray, kind: str, params: PipelineParams,
           max_pixels: int, full: bool, progress=None) -> tuple[PreparedInput, np.ndarray, dict]:
    """Worker job: prepare the input if needed, then the core display stages on it.

    The stages after value-of-interest scaling, exactly as the pipeline runs them
    (:func:`~napari_dslrxr.core.display.apply_display_stages`): latitude reduction,
    multiscale contrast and the display curve; outside the screen region is black (or
    white), as in the pipeline's output. Also returns the display report (the share of the
    anatomy clipped, as the pipeline's sidecar records it).
    """
    if progress is not None:
        progress(0, 2)
    if prepared is None:
        prepared = prepare_input(data, kind, max_pixels, params)
    if progress is not None:
        progress(1, 2)
    image, mask = (prepared.image, prepared.mask) if full else (prepared.small, prepared.small_mask)
    report: dict = {}
    display = apply_display_stages(image, mask, params, report=report)
    return prepared, display, report


def clipped_text(fraction: float) -> str:
    """The read-out's clipping figure: the share of the anatomy at pure black or white."""
    return f"{100.0 * fraction:.1f} % of the anatomy clipped"


def layer_input_kind(layer) -> InputKind:
    """The input kind of a layer: the reader's decision in its metadata, else the core rule on its data."""
    meta = layer.metadata or {}
    if isinstance(meta.get("input_kind"), dict):
        return InputKind.from_record(meta["input_kind"])
    return decide_input_kind(meta.get("format"), meta.get("file_metadata"), np.asarray(layer.data))


class ContrastWidget(LivePreviewMixin, Container):
    """Latitude, detail and bone-contrast sliders with a live preview, and a full-size apply."""

    SECTION = "contrast"  # also saves/loads [dynamic_range]
    SECTIONS = ("dynamic_range", "contrast")

    def __init__(self, viewer: napari.viewer.Viewer, preview_max_pixels: int = 1_000_000):
        self._viewer = viewer
        self.preview_max_pixels = int(preview_max_pixels)
        self._image = create_widget(annotation="napari.layers.Image", label="image")
        self._image.tooltip = "the radiograph to display (a flat-fielded camera frame, or a DICOM CR/DX)"
        self._kind = ComboBox(choices=[LINEAR, DISPLAY], value=LINEAR, label="input",
                              tooltip="linear counts: a camera frame (more X-rays = brighter), converted to "
                                      "attenuation first; display radiograph: a CR/DX image already shown "
                                      "bone-bright")
        defaults = PipelineParams()
        self._sliders: dict[tuple[str, str], FloatSlider] = {}
        for section, name, label, term in SLIDERS:
            self._sliders[(section, name)] = param_widget(SECTION_CLASSES[section], name, label=label,
                                                          section=section, term=term, slider=True, step=0.01)
        self._live = CheckBox(value=False, label="live preview",
                              tooltip="show '<image> contrast (preview)' at screen resolution while you move "
                                      "the sliders; off removes the preview layer")
        self._apply = PushButton(text="Apply at full resolution",
                                 tooltip="compute '<image> contrast' at full resolution with these settings")
        self._restore = restore_defaults_button(self.restore_defaults)
        self._job = JobPanel()
        self._readout = readout_label()
        super().__init__(widgets=[self._image, self._kind, *self._sliders.values(), self._live, self._apply,
                                  *self._job.widgets, self._readout, self._restore])
        scroll_long_readout(self._readout)  # a long result scrolls, the window keeps its size
        self._base = defaults  # keeps the fields without a slider (and the other sections)
        self._prepared: tuple | None = None  # (key, PreparedInput)
        self.last_preview_s: float | None = None
        self.preview: np.ndarray | None = None
        self.result: np.ndarray | None = None
        trigger = debounced(self, self.update_preview, _DEBOUNCE_MS)
        for widget in (*self._sliders.values(), self._live, self._kind):
            widget.changed.connect(trigger)
        self._init_live_preview()
        self._image.changed.connect(self._input_changed)
        self._image.changed.connect(trigger)
        self._apply.changed.connect(self.run)
        register_stage_widget(viewer, self)
        self._input_changed()  # the layer preselected at creation emits no change

    def restore_defaults(self) -> None:
        """Sliders back to the defaults of the parameter dataclasses."""
        defaults = PipelineParams()
        self.set_params({"dynamic_range": defaults.dynamic_range, "contrast": defaults.contrast})

    # -- parameters (TOML sections [dynamic_range] and [contrast]) ------------------------------
    def pipeline_params(self) -> PipelineParams:
        """Full pipeline parameters with this widget's slider values."""
        dr = dataclasses.replace(self._base.dynamic_range, **{n: float(w.value) for (s, n), w in self._sliders.items()
                                                              if s == "dynamic_range"})
        ct = dataclasses.replace(self._base.contrast, **{n: float(w.value) for (s, n), w in self._sliders.items()
                                                        if s == "contrast"})
        return dataclasses.replace(self._base, dynamic_range=dr, contrast=ct)

    def get_params(self) -> dict[str, object]:
        params = self.pipeline_params()
        return {"dynamic_range": params.dynamic_range, "contrast": params.contrast}

    def set_params(self, sections: dict[str, object]) -> None:
        """Take ``dynamic_range`` and ``contrast`` sections (dataclasses) and show them."""
        self._base = dataclasses.replace(self._base, **{k: v for k, v in sections.items() if k in self.SECTIONS})
        for (section, name), widget in self._sliders.items():
            widget.value = float(getattr(getattr(self._base, section), name))

    # -- input -------------------------------------------------------------------------------------
    def _input_changed(self, *_args) -> None:
        """Set the input kind by the core's rule whenever a layer is chosen (and at start)."""
        layer = self._image.value
        if layer is None:
            return
        kind = layer_input_kind(layer)
        self._kind.value = DISPLAY if kind.kind == "display" else LINEAR
        self._readout.value = f"input: {kind.kind} ({kind.evidence})" + ("" if kind.certain else "; a guess")

    def _layer(self) -> napari.layers.Image:
        layer = self._image.value
        if layer is None:
            raise ParameterError("choose an image layer")
        return layer

    def _cached(self, layer) -> PreparedInput | None:
        key = (id(layer), id(layer.data), self._kind.value, self.preview_max_pixels, repr(self._base.region))
        if self._prepared is not None and self._prepared[0] == key:
            return self._prepared[1]
        return None

    def _store(self, layer, kind: str, prepared: PreparedInput) -> None:
        self._prepared = ((id(layer), id(layer.data), kind, self.preview_max_pixels, repr(self._base.region)),
                          prepared)

    # -- live preview (LivePreviewMixin) ----------------------------------------------------------
    def _start_preview(self):
        return self._start(full=False)

    @guarded("contrast")
    def run(self):
        """Apply the display stages at full resolution in a thread worker; return the worker."""
        return self._start(full=True)

    def _start(self, *, full: bool):
        layer = self._layer()
        kind, params = self._kind.value, self.pipeline_params()
        started = time.perf_counter()
        if full:
            self._apply.enabled = False
            self._readout.value = "running..."
        else:
            self._preview_pending = False

        def returned(out) -> None:
            prepared, display, report = out
            self._store(layer, kind, prepared)
            return self._show(layer, prepared, display, full, started, report)

        if full:
            return run_in_worker(render, self._cached(layer), np.asarray(layer.data), kind, params,
                                 self.preview_max_pixels, True, progress=self._job.callback, desc="contrast",
                                 on_returned=returned, on_finished=job_done(self._apply, self._job, self._readout),
                                 panel=self._job,
                                 readout=self._readout)
        worker = run_in_worker(render, self._cached(layer), np.asarray(layer.data), kind, params,
                               self.preview_max_pixels, False, desc="contrast preview", progress_bar=False,
                               on_returned=returned, on_finished=self._preview_done)
        self._preview_worker = worker
        return worker

    def _show(self, layer, prepared: PreparedInput, display: np.ndarray, full: bool, started: float,
              report: dict) -> Iterator[None]:
        """Show the result (a new layer over two event-loop turns, :func:`show_layer_steps`)."""
        scale = np.asarray(layer.scale[-2:], float) * (1.0 if full else prepared.factor)
        # Pixel centres: a preview pixel covers `factor` input pixels.
        translate = np.asarray(layer.translate[-2:], float)
        if not full:
            translate = translate + np.asarray(layer.scale[-2:], float) * (prepared.factor - 1.0) / 2.0
        if not full and (not self._live.value or layer is not self._image.value):
            return  # preview turned off, or another image chosen, while it computed
        name = f"{layer.name} contrast" if full else f"{layer.name} contrast (preview)"
        if not full:
            self._preview_layer = name
        yield from show_layer_steps(self._viewer, display, name, "image", scale=tuple(scale),
                                    translate=tuple(translate), contrast_limits=(0.0, 1.0), colormap="gray")
        elapsed = time.perf_counter() - started
        clipped_fraction = report.get("clipped_fraction", 0.0)
        # the display's self-check (as the pipeline's sidecar and the command line say it)
        warning = f"\nwarning: {report['warning']}" if "warning" in report else ""
        if full:
            self.result = display
            self._readout.value = (f"applied at {display.shape[1]}x{display.shape[0]} px in {elapsed:.2f} s; "
                                   f"{clipped_text(clipped_fraction)}{warning}")
        else:
            self.preview = display
            self.last_preview_s = elapsed
            self._readout.value = (f"preview {display.shape[1]}x{display.shape[0]} px "
                                   f"(1/{prepared.factor:.2g} scale) in {elapsed * 1000:.0f} ms; "
                                   f"{clipped_text(clipped_fraction)}{warning}")
