"""Deconvolution widget over :mod:`napari_dslrxr.core.stages.deconvolution`.

The blur kernel comes from a kernel image layer (for example the one the PSF edge picker
adds) or from a ``psf.json`` plus the geometry of the radiograph (source-to-object and
source-to-detector distances). The regularisation knob is a log slider; with "live preview"
on, each change deconvolves only the part of the image visible on the canvas (plus a margin
of the kernel radius), with the fast closed-form solver, and shows it as
``"<layer> deconvolved (preview)"`` over the image. Updates are debounced and coalesced: at
most one preview computes at a time and only the latest settings are computed next.
"Apply to the whole image" runs the chosen method in a thread worker with a progress bar
and a cancel button, giving ``"<layer> deconvolved"``.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import CheckBox, Container, FileEdit, FloatLogSlider, PushButton, create_widget

from ..core.stages.deconvolution import DeconvolutionParams, deconvolve, deconvolve_steps
from ..core.stages.regularisation import estimate_regularisation
from ..core.psf.fit_params import EdgeFitSettings
from ..core.errors import ParameterError
from ..core.param_fields import field_info
from ..core.params import DeblurParams
from ..core.psf import load_psf
from ._controls import param_tooltip, param_widget, restore_defaults_button
from ._jobs import JobPanel, guarded, job_done, notify_info, readout_label, run_in_worker, scroll_long_readout
from ._layers import (LivePreviewMixin, ShownLayers, debounced, robust_limits, show_layer_steps, viewer_camera,
                      visible_region)
from ._registry import register_stage_widget

if TYPE_CHECKING:
    import napari

#: Solver used for the live preview of each method: the closed-form ones preview themselves;
#: the sparse adaptive prior is previewed by the gradient-regularised solve it starts from.
PREVIEW_METHOD = {"wiener": "wiener", "rls": "rls", "adaptive": "rls"}
#: The slider spans the one valid range of ``reg`` (its field metadata), so every value the
#: parameter file, the command line or the solver accepts can be set and shown.
REG_SLIDER_MIN = float(field_info(DeconvolutionParams, "reg")["min"])
REG_SLIDER_MAX = float(field_info(DeconvolutionParams, "reg")["max"])
#: Where the regularisation slider starts (and returns to with "Restore defaults").
REG_START = 100.0
_DEBOUNCE_MS = 60


def deconvolve_for_display(image: np.ndarray, kernel: np.ndarray | tuple, *, method: str, reg: float):
    """Worker job (generator): the kernel (:func:`resolve_kernel`), the core's steps, then what
    showing the result needs, computed here rather than on the GUI thread: the result, its
    display range, and the value ranges of input and result."""
    out = yield from deconvolve_steps(image, resolve_kernel(kernel), method=method, reg=reg)
    return (out, robust_limits(out), (float(np.min(image)), float(np.max(image))),
            (float(np.min(out)), float(np.max(out))))


@functools.lru_cache(maxsize=4)
def _psf_file_kernel(path: str, mtime_ns: int, source_to_object_mm: float,
                     source_to_detector_mm: float) -> np.ndarray:
    """The kernel of a psf.json at a geometry (cached by file version and geometry: the
    preview asks for it on every slider move; a fitted model's kernel takes up to a second)."""
    kernel = load_psf(path).kernel(source_to_object_mm, source_to_detector_mm)
    kernel.setflags(write=False)  # shared by every job that asks for it
    return kernel


def resolve_kernel(source: np.ndarray | tuple) -> np.ndarray:
    """Worker side of :meth:`DeconvolutionWidget.kernel_source`: a kernel array as it is, or
    ``(psf.json path, mtime_ns, SOD mm, SDD mm)`` computed (cached) here, off the GUI thread."""
    if isinstance(source, np.ndarray):
        return source
    return _psf_file_kernel(*source)


def preview_region(image: np.ndarray, kernel: np.ndarray | tuple, rows: slice, cols: slice, *, method: str,
                   reg: float) -> tuple[np.ndarray, slice, slice]:
    """Deconvolve the visible crop ``image[rows, cols]`` grown by the kernel's radius (the
    margin the solver's edges need; the kernel, hence its size, is made here) with the
    preview solver (core call). Returns the result and the rows and columns it covers."""
    kernel = resolve_kernel(kernel)
    margin = kernel.shape[0] // 2
    height, width = np.shape(image)[:2]
    rows = slice(max(rows.start - margin, 0), min(rows.stop + margin, height))
    cols = slice(max(cols.start - margin, 0), min(cols.stop + margin, width))
    crop = np.ascontiguousarray(image[rows, cols])
    return deconvolve(crop, kernel, method=PREVIEW_METHOD[method], reg=reg), rows, cols


def estimate_for_display(image: np.ndarray, kernel: np.ndarray | tuple, method: str) -> float:
    """Worker job: the core's regularisation estimate, with the kernel made here."""
    return estimate_regularisation(image, resolve_kernel(kernel), method)


class DeconvolutionWidget(LivePreviewMixin, Container):
    """Regularisation slider with a live preview of the visible region, and a full run."""

    SECTION = "deblur"

    def __init__(self, viewer: napari.viewer.Viewer):
        self._viewer = viewer
        self._image = create_widget(annotation="napari.layers.Image", label="image")
        self._image.tooltip = "the radiograph to sharpen (after impulse removal and flat field)"
        self._kernel_layer = create_widget(annotation="napari.layers.Image | None", label="kernel layer")
        self._kernel_layer.tooltip = ("the blur kernel as an image layer, e.g. 'PSF kernel' from the PSF widget; "
                                      "leave empty to use a psf.json")
        self._psf_file = FileEdit(mode="r", filter="*.json", label="or psf.json",
                                  tooltip="a PSF model saved by the PSF widget or 'dslrxr psf'; its kernel is "
                                          "computed at the distances below")
        self._sod = param_widget(EdgeFitSettings, "source_to_object_mm", label="source-object (mm)", step=10.0)
        self._sdd = param_widget(EdgeFitSettings, "source_to_detector_mm", label="source-detector (mm)", step=10.0)
        self._method = param_widget(DeblurParams, "method", label="method", section="deblur",
                                    value="adaptive")
        # 200 slider positions per decade (1.2 % steps); magicgui's default is 100 in all.
        self._reg = FloatLogSlider(min=REG_SLIDER_MIN, max=REG_SLIDER_MAX, base=10,
                                   max_pos=200 * round(np.log10(REG_SLIDER_MAX / REG_SLIDER_MIN)),
                                   label="regularisation",
                                   tooltip=param_tooltip(DeblurParams, "reg", label="regularisation", section="deblur",
                                                         term="precision of the gradient prior relative to the noise; "
                                                              "larger = smoother, less noise, less sharpening")
                                   + f"\nSlider: {REG_SLIDER_MIN:g} to {REG_SLIDER_MAX:g} (log scale).")
        self._reg.value = REG_START  # after the positions are set, or the value is misplaced
        # magicgui's log-slider read-out shows the slider position, not the value: hide it
        # and show the value in the label instead.
        hide_readout = getattr(self._reg._widget, "_mgui_set_readout_visibility", None)
        if hide_readout is not None:
            hide_readout(False)
        self._reg.native.setMinimumWidth(200)
        self._reg.changed.connect(self._label_reg)
        self._label_reg()
        self._auto = PushButton(text="Estimate regularisation",
                                tooltip="set the slider from the noise and detail of the visible region")
        self._live = CheckBox(value=False, label="live preview (visible region)",
                              tooltip="deconvolve only what the canvas shows, with a fast solver, on every change; "
                                      "off removes the preview layer")
        self._apply = PushButton(text="Apply to the whole image",
                                 tooltip="deconvolve the whole image with the chosen method; adds '<image> deconvolved'")
        self._restore = restore_defaults_button(self.restore_defaults)
        self._job = JobPanel()
        self._readout = readout_label()
        super().__init__(widgets=[self._image, self._kernel_layer, self._psf_file, self._sod, self._sdd,
                                  self._method, self._reg, self._auto, self._live, self._apply, *self._job.widgets,
                                  self._readout, self._restore])
        scroll_long_readout(self._readout)  # a long result scrolls, the window keeps its size
        self.result: np.ndarray | None = None
        self.last_preview: dict | None = None
        self._trigger_preview = debounced(self, self.update_preview, _DEBOUNCE_MS)
        for widget in (self._reg, self._method, self._live, self._image, self._kernel_layer, self._psf_file,
                       self._sod, self._sdd):
            widget.changed.connect(self._trigger_preview)
        self._init_live_preview()
        self._auto.changed.connect(self.estimate)
        self._apply.changed.connect(self.run)
        camera = viewer_camera(viewer)
        camera.events.center.connect(self._trigger_preview)
        camera.events.zoom.connect(self._trigger_preview)
        register_stage_widget(viewer, self)

    def restore_defaults(self) -> None:
        """Method back to its default and the slider to its starting value."""
        self._method.value = DeblurParams().method
        self._reg.value = REG_START

    def _label_reg(self, *_args) -> None:
        self._reg.label = f"regularisation {float(self._reg.value):.3g}"

    # -- parameters (TOML section [deblur]) -----------------------------------------------------
    def get_params(self) -> DeconvolutionParams:
        return DeconvolutionParams(method=self._method.value, reg=float(self._reg.value))

    def set_params(self, params: DeconvolutionParams) -> None:
        self._method.value = params.method
        if params.reg != "auto":
            self._reg.value = float(np.clip(float(params.reg), REG_SLIDER_MIN, REG_SLIDER_MAX))

    # -- inputs -----------------------------------------------------------------------------------
    def kernel_source(self) -> np.ndarray | tuple:
        """What the blur kernel is made from, for a worker's :func:`resolve_kernel`: the kernel
        layer's data, else ``(psf.json, its mtime_ns, SOD, SDD)`` (computing a fitted model's
        kernel takes up to a second: never on the GUI thread)."""
        if self._kernel_layer.value is not None:
            return np.asarray(self._kernel_layer.value.data, np.float32)
        path = self._psf_file.value
        if not path or not Path(path).is_file():
            raise ParameterError("choose a kernel layer or a psf.json file")
        return (str(path), Path(path).stat().st_mtime_ns, float(self._sod.value), float(self._sdd.value))

    def kernel(self) -> np.ndarray:
        """The blur kernel: the kernel layer, else the PSF file at the entered geometry (cached;
        computed on the calling thread)."""
        return resolve_kernel(self.kernel_source())

    def _image_layer(self) -> napari.layers.Image:
        layer = self._image.value
        if layer is None:
            raise ParameterError("choose an image layer")
        return layer

    # -- regularisation ---------------------------------------------------------------------------
    @guarded("deconvolution")
    def estimate(self):
        """Set the slider to the core's data-driven estimate for the visible region (in a
        worker); return the worker."""
        layer = self._image_layer()
        image = np.asarray(layer.data)
        rows, cols = visible_region(self._viewer, layer, image.shape)
        kernel, method = self.kernel_source(), self._method.value
        self._auto.enabled = False
        self._readout.value = "estimating the regularisation..."
        return run_in_worker(estimate_for_display, image[rows, cols], kernel, method,
                             desc="regularisation estimate", on_returned=self._estimated,
                             on_finished=job_done(self._auto, self._job, self._readout), panel=self._job,
                             readout=self._readout)

    def _estimated(self, reg: float) -> None:
        self._reg.value = float(np.clip(reg, REG_SLIDER_MIN, REG_SLIDER_MAX))
        self._readout.value = f"estimated regularisation {reg:.3g}"

    # -- live preview -----------------------------------------------------------------------------
    @guarded("deconvolution preview")
    def _start_preview(self) -> None:
        layer = self._image_layer()
        image = np.asarray(layer.data)
        kernel = self.kernel_source()
        rows, cols = visible_region(self._viewer, layer, image.shape)  # the worker adds the kernel's margin
        method, reg = self._method.value, float(self._reg.value)
        self._preview_pending = False
        self._preview_worker = run_in_worker(
            preview_region, image, kernel, rows, cols, method=method, reg=reg, desc="deconvolution preview", progress_bar=False,
            on_returned=lambda out: self._show_preview(layer, *out, method, reg),
            on_finished=self._preview_done)

    def _show_preview(self, layer, out: np.ndarray, rows: slice, cols: slice, method: str,
                      reg: float) -> Iterator[None]:
        if not self._live.value or layer is not self._image.value:
            return  # preview turned off, or another image chosen, while it computed
        scale = np.asarray(layer.scale[-2:], float)
        translate = np.asarray(layer.translate[-2:], float) + scale * (rows.start, cols.start)
        limits = layer.contrast_limits if not getattr(layer, "rgb", False) else None
        self._preview_layer = f"{layer.name} deconvolved (preview)"
        yield from show_layer_steps(self._viewer, out, self._preview_layer, "image",
                                    rgb=out.ndim == 3, scale=tuple(scale), translate=tuple(translate),
                                    **({"contrast_limits": limits} if limits is not None else {}))
        self.last_preview = {"rows": rows, "cols": cols, "method": PREVIEW_METHOD[method], "reg": reg}
        self._readout.value = (f"preview {cols.stop - cols.start}x{rows.stop - rows.start} px, "
                               f"{PREVIEW_METHOD[method]}, reg {reg:.3g}")

    # -- whole image ------------------------------------------------------------------------------
    @guarded("deconvolution")
    def run(self):
        """Deconvolve the whole image in a thread worker (progress bar with cancel); return it."""
        layer = self._image_layer()
        params = self.get_params()
        image = np.asarray(layer.data)
        kernel = self.kernel_source()
        self._apply.enabled = False
        self._readout.value = f"deconvolving with {params.method}..."
        self._full_worker = run_in_worker(
            deconvolve_for_display, image, kernel, method=params.method, reg=params.reg,
            desc=f"deconvolution ({params.method})", panel=self._job, readout=self._readout,
            on_returned=lambda out: self._show_full(layer, *out, params),
            on_finished=job_done(self._apply, self._job, self._readout))
        return self._full_worker

    def cancel(self) -> None:
        """Stop the whole-image run at its next step (the Cancel button)."""
        self._job.cancel()

    def _show_full(self, layer, out: np.ndarray, limits: tuple[float, float], input_range: tuple[float, float],
                   out_range: tuple[float, float], params: DeconvolutionParams) -> Iterator[None]:
        """The result with display limits from its own values, and a warning when they leave
        the input's range (ringing or over-sharpening: try a larger regularisation). Stopped
        midway (Cancel), the layer is put back as it was (:class:`ShownLayers`)."""
        shown = ShownLayers(self._viewer)
        with shown.put_back_if_stopped():
            yield from show_layer_steps(self._viewer, out, f"{layer.name} deconvolved", "image", rgb=out.ndim == 3,
                                        scale=tuple(layer.scale[-2:]), translate=tuple(layer.translate[-2:]),
                                        shown=shown, **({} if out.ndim == 3 else {"contrast_limits": limits}))
        self.result = out
        (in_lo, in_hi), (out_lo, out_hi) = input_range, out_range
        span = max(in_hi - in_lo, 1e-12)
        text = (f"deconvolved with {params.method}, reg {float(params.reg):.3g}; values {out_lo:.4g} to "
                f"{out_hi:.4g} (input {in_lo:.4g} to {in_hi:.4g})")
        if out_lo < in_lo - 0.05 * span or out_hi > in_hi + 0.05 * span:
            warning = ("warning: the result leaves the input's range (ringing or noise amplification); "
                       "try a larger regularisation")
            text += "\n" + warning
            notify_info(f"deconvolution: {warning}")
        self._readout.value = text
