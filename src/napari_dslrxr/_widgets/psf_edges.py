"""Edge ROI picker for PSF fitting, over :func:`napari_dslrxr.core.psf.edge_fit.fit_edges`.

Workflow: choose an edge radiograph, enter its source-to-object and source-to-detector
distances (kept in the layer's metadata, so each image keeps its own), press "Draw ROIs" and
draw rectangles, each around one straight edge, in the Shapes layer ``"<image> ROIs"``. Do
this for every image (at least two object distances to separate focal spot and detector
blur). "Fit PSF" fits every rectangle of every image jointly in a thread worker (progress
bar with cancel). The widget then shows the fitted parameters with their uncertainties, a
plot of the measured versus fitted edge (ESF) and line (LSF) spread profiles of each ROI,
and the blur kernel at the chosen image's geometry as the image layer ``"PSF kernel"``;
"Save psf.json" writes the model with :func:`napari_dslrxr.core.psf.save_psf`.
"""

from __future__ import annotations

import dataclasses

from collections.abc import Generator, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from magicgui.widgets import ComboBox, Container, FileEdit, PushButton, create_widget

from ..core.psf.edge_fit import EdgeImage, fit_edges
from ..core.psf.edge_images import MIN_ROI_PX
from ..core.psf.fit_params import EdgeFitSettings
from ..core.errors import ParameterError
from ..core.psf import PSFModel, save_psf
from ._controls import param_tooltip, param_widget, restore_defaults_button
from ._jobs import JobPanel, guarded, job_done, notify_info, readout_label, run_in_worker, scroll_long_readout
from ._layers import ShownLayers, finish_steps, show_layer_steps
from ._plots import ShownFigureMixin, render_figure, worker_plot

if TYPE_CHECKING:
    import napari

SOD_KEY, SDD_KEY = "source_to_object_mm", "source_to_detector_mm"
SHAPES = {"exponential (p = 1, SABER)": 1.0, "Gaussian (p = 2)": 2.0}
#: Half-width cap of the "PSF kernel" layer (the kernel the Deconvolution widget can take).
KERNEL_RADIUS_PX = 64
#: Height of the profile plot (fixed: a read-out changing its length must not move it).
PLOT_HEIGHT_PX = 210


def roi_layer_name(image_name: str) -> str:
    """Name of the Shapes layer holding the ROIs of an image layer."""
    return f"{image_name} ROIs"


def rectangles_to_rois(shapes: napari.layers.Shapes, image: napari.layers.Image) -> list[tuple[int, int, int, int]]:
    """Pixel ROIs ``(r0, c0, r1, c1)`` (end exclusive) of the rectangles of ``shapes`` over ``image``.

    Vertices go through world coordinates, so ROI layers with another scale or translation
    than the image still land on the right pixels; each ROI is clipped to the image. An ROI
    smaller than :data:`MIN_ROI_PX` (after clipping) is refused with a message naming it.
    """
    h, w = np.shape(image.data)[:2]
    rois = []
    number = 0
    for vertices, kind in zip(shapes.data, shapes.shape_type, strict=True):
        if kind not in ("rectangle", "polygon"):
            continue
        number += 1
        points = np.array([image.world_to_data(shapes.data_to_world(v)) for v in np.asarray(vertices)])[:, -2:]
        lo, hi = points.min(axis=0), points.max(axis=0)
        r0, c0 = (int(np.clip(np.floor(v + 0.5), 0, n)) for v, n in zip(lo, (h, w), strict=True))
        r1, c1 = (int(np.clip(np.floor(v + 0.5), 0, n)) for v, n in zip(hi, (h, w), strict=True))
        if r1 - r0 < MIN_ROI_PX or c1 - c0 < MIN_ROI_PX:
            raise ParameterError(f"ROI {number} on '{image.name}' is {c1 - c0}x{r1 - r0} px inside the image; "
                                 f"draw it at least {MIN_ROI_PX}x{MIN_ROI_PX} px, across one edge")
        rois.append((r0, c0, r1, c1))
    return rois


def edge_roi_layer(viewer: napari.Viewer, image: napari.layers.Image, on_new=None) -> napari.layers.Shapes:
    """The Shapes layer ``"<image> ROIs"`` over ``image`` (created, and passed to ``on_new``,
    when there is none), made active in rectangle mode for the user to draw."""
    name = roi_layer_name(image.name)
    if name in viewer.layers:
        shapes = viewer.layers[name]
    else:
        shapes = viewer.add_shapes(name=name, shape_type="rectangle", edge_color="yellow", face_color="transparent",
                                   edge_width=2, scale=tuple(image.scale[-2:]), translate=tuple(image.translate[-2:]))
        if on_new is not None:
            on_new(shapes)
    viewer.layers.selection.active = shapes
    shapes.mode = "add_rectangle"
    return shapes


def fit_summary(model: PSFModel) -> str:
    """The read-out of a fit: what was fitted, with uncertainties, and what was not."""
    report = model.fit_report
    lines = model.describe()
    lines.append(f"residual rms {report.get('residual_rms', float('nan')):.3g} "
                 f"(noise {report.get('noise_rms_estimate', float('nan')):.3g}), "
                 f"{report.get('n_images', 0)} ROIs")
    return "\n".join(lines)


def draw_profiles(figure, model: PSFModel) -> None:
    """Measured (dots) versus fitted (lines) ESF and LSF of every ROI."""
    ax_esf, ax_lsf = figure.subplots(1, 2)
    for i, edge in enumerate(model.fit_report.get("edges", [])):
        prof = edge["profile"]
        colour = f"C{i % 10}"
        label = f"{edge['name']}"
        ax_esf.plot(prof["distance_px"], prof["esf_measured"], ".", ms=2, color=colour, alpha=0.5)
        ax_esf.plot(prof["distance_px"], prof["esf_fitted"], "-", lw=1, color=colour, label=label)
        ax_lsf.plot(prof["distance_px"], prof["lsf_measured"], ".", ms=2, color=colour, alpha=0.5)
        ax_lsf.plot(prof["distance_px"], prof["lsf_fitted"], "-", lw=1, color=colour)
    ax_esf.set(title="edge spread (dots: measured)", xlabel="distance (px)", xlim=(-15, 15))
    ax_lsf.set(title="line spread", xlabel="distance (px)", xlim=(-15, 15))
    ax_esf.legend(fontsize=6, loc="lower right")


def fit_for_display(edges, pixel_pitch_mm: float, *, shape_power: float, progress,
                    source_to_object_mm: float, source_to_detector_mm: float,
                    plot_size_px: tuple[int, int] | None = None) -> tuple[PSFModel, np.ndarray, str, tuple | None]:
    """The joint edge fit, and what the widget shows of it: the kernel at the chosen image's
    geometry, the read-out, and the profile plot rendered at ``plot_size_px`` (none without).
    Runs in the worker: on the GUI thread the kernel alone took about half a second and the
    plot a few tenths, with the viewer frozen."""
    # the layers' data as grey float images, here and not on the GUI thread (a 24 MP colour
    # layer took 1.2 s); an image with several ROIs is converted once
    greys: dict[int, np.ndarray] = {}
    for edge in edges:
        if id(edge.image) not in greys:
            greys[id(edge.image)] = grey(edge.image)
    edges = [dataclasses.replace(edge, image=greys[id(edge.image)]) for edge in edges]
    model = fit_edges(edges, pixel_pitch_mm, shape_power=shape_power, progress=progress)
    kernel = model.kernel(source_to_object_mm, source_to_detector_mm, max_radius_px=KERNEL_RADIUS_PX)
    plot = None if plot_size_px is None else render_figure(lambda figure: draw_profiles(figure, model), plot_size_px)
    return model, kernel, fit_summary(model), plot


def grey(data: np.ndarray) -> np.ndarray:
    """The layer data as a float32 grey image (colour: mean of the channels)."""
    arr = np.asarray(data, np.float32)
    return arr.mean(axis=2) if arr.ndim == 3 else arr


class PSFEdgeWidget(ShownFigureMixin, Container):
    """Draw edge ROIs over radiographs, enter distances, fit the PSF, show profiles and kernel."""

    def __init__(self, viewer: napari.viewer.Viewer):
        self._viewer = viewer
        self._image = create_widget(annotation="napari.layers.Image", label="edge image")
        self._image.tooltip = ("a radiograph of a straight, opaque edge (e.g. a tungsten or lead plate); "
                               "its distances are kept with the layer")
        self._sod = param_widget(EdgeFitSettings, "source_to_object_mm", label="source-object (mm)", step=10.0)
        self._sdd = param_widget(EdgeFitSettings, "source_to_detector_mm", label="source-detector (mm)", step=10.0)
        self._draw = PushButton(text="Draw ROIs on this image",
                                tooltip="adds (or selects) the shapes layer '<image> ROIs' in rectangle mode: "
                                        "drag one rectangle across each straight edge")
        self._pitch = param_widget(EdgeFitSettings, "pixel_pitch_mm", label="pixel pitch (mm)", step=0.01)
        self._shape = ComboBox(choices=list(SHAPES), value=next(iter(SHAPES)), label="profile",
                               tooltip=param_tooltip(EdgeFitSettings, "shape_power", label="profile"))
        self._fit = PushButton(text="Fit PSF",
                               tooltip="fit focal spot and detector blur to every ROI of every image jointly")
        self._job = JobPanel(cancel_text="Cancel fit", tooltip="stop the fit at its next iteration")
        self._cancel = self._job.cancel_button
        self._path = FileEdit(mode="w", filter="*.json", label="save as", value="psf.json",
                              tooltip="file the fitted PSF model is written to (for the Deconvolution widget "
                                      "and 'dslrxr run --psf')")
        self._save = PushButton(text="Save psf.json", enabled=False, tooltip="write the fitted model to the file above")
        self._restore = restore_defaults_button(self.restore_defaults)
        self._status = readout_label()
        self._readout = readout_label()
        super().__init__(widgets=[self._image, self._sod, self._sdd, self._draw, self._pitch, self._shape,
                                  self._status, self._fit, *self._job.widgets, self._readout, self._path,
                                  self._save, self._restore])
        scroll_long_readout(self._readout)  # a long result scrolls, the window keeps its size
        self.model: PSFModel | None = None  # the fit shown (read-out, kernel layer), what "Save psf.json" writes
        self._summary: str | None = None  # its read-out
        self.edges_used: list[tuple[str, tuple[int, int, int, int]]] = []
        self._plot = worker_plot(self, PLOT_HEIGHT_PX, self._readout, "the fitted edge profiles")
        self._image.changed.connect(self._image_chosen)
        self._sod.changed.connect(self._store_distances)
        self._sdd.changed.connect(self._store_distances)
        self._draw.changed.connect(self.roi_layer)
        self._fit.changed.connect(self.run)
        self._save.changed.connect(self.save)
        viewer.layers.events.inserted.connect(self._refresh_status)
        viewer.layers.events.removed.connect(self._refresh_status)
        self._image_chosen()

    def restore_defaults(self) -> None:
        """Pixel pitch and profile back to their defaults. The distances describe the chosen
        image (kept with its layer), not a preference, and stay."""
        defaults = EdgeFitSettings()
        self._pitch.value = defaults.pixel_pitch_mm
        self._shape.value = next(name for name, power in SHAPES.items() if power == defaults.shape_power)

    # -- per-image distances and ROI layers -----------------------------------------------------------
    def _image_chosen(self, *_args) -> None:
        layer = self._image.value
        if layer is None:
            return
        meta = layer.metadata
        with self._sod.changed.blocked(), self._sdd.changed.blocked():
            self._sod.value = float(meta.get(SOD_KEY, self._sod.value))
            self._sdd.value = float(meta.get(SDD_KEY, self._sdd.value))
        pitch = meta.get("pixel_pitch_mm") or (meta.get("file_metadata", {}).get("pixel_spacing_mm") or [None])[0]
        if pitch:
            self._pitch.value = float(pitch)
        self._store_distances()

    def _store_distances(self, *_args) -> None:
        layer = self._image.value
        if layer is not None:
            layer.metadata[SOD_KEY] = float(self._sod.value)
            layer.metadata[SDD_KEY] = float(self._sdd.value)
        self._refresh_status()

    @guarded("PSF edge ROIs")
    def roi_layer(self) -> napari.layers.Shapes:
        """The Shapes layer of the chosen image's ROIs (created if needed), in rectangle mode."""
        image = self._image.value
        if image is None:
            raise ParameterError("choose an edge image layer")
        return edge_roi_layer(self._viewer, image, on_new=lambda shapes: shapes.events.data.connect(
            self._refresh_status))

    def collect_edges(self) -> list[EdgeImage]:
        """One :class:`EdgeImage` per rectangle over every image that has an ROI layer."""
        from napari.layers import Image, Shapes

        edges, used = [], []
        for layer in list(self._viewer.layers):
            if not isinstance(layer, Image):
                continue
            name = roi_layer_name(layer.name)
            if name not in self._viewer.layers or not isinstance(self._viewer.layers[name], Shapes):
                continue
            rois = rectangles_to_rois(self._viewer.layers[name], layer)
            if not rois:
                continue
            sod, sdd = layer.metadata.get(SOD_KEY), layer.metadata.get(SDD_KEY)
            if sod is None or sdd is None:
                raise ParameterError(f"{layer.name}: enter its source-object and source-detector distances")
            for k, roi in enumerate(rois):  # grey(): in the worker (fit_for_display)
                edges.append(EdgeImage(image=layer.data, source_to_object_mm=float(sod), source_to_detector_mm=float(sdd),
                                       roi=roi, name=f"ROI {k + 1} on '{layer.name}'"))
                used.append((layer.name, roi))
        self.edges_used = used
        return edges

    def _refresh_status(self, *_args: Any) -> None:
        try:
            from napari.layers import Image
        except ImportError:  # pragma: no cover
            return
        lines = []
        for layer in list(self._viewer.layers):
            name = roi_layer_name(layer.name)
            if isinstance(layer, Image) and name in self._viewer.layers:
                n = len(self._viewer.layers[name].data)
                lines.append(f"{layer.name}: {n} ROI(s), SOD {layer.metadata.get(SOD_KEY, '?')} mm, "
                             f"SDD {layer.metadata.get(SDD_KEY, '?')} mm")
        try:
            self._status.value = "\n".join(lines) or "no ROIs drawn yet"
        except RuntimeError:  # widget already deleted while napari tears down
            pass

    # -- fit -------------------------------------------------------------------------------------------
    @guarded("PSF fit")
    def run(self):
        """Fit all ROIs jointly in a thread worker; return the worker."""
        edges = self.collect_edges()
        if not edges:
            raise ParameterError("draw at least one rectangle around an edge (press 'Draw ROIs')")
        pitch, power = float(self._pitch.value), SHAPES[self._shape.value]
        self._fit.enabled = False
        self._readout.value = f"fitting {len(edges)} edge ROI(s)..."
        geometry_mm = (float(self._sod.value), float(self._sdd.value))
        return run_in_worker(fit_for_display, edges, pitch, shape_power=power, progress=self._job.callback,
                             source_to_object_mm=geometry_mm[0], source_to_detector_mm=geometry_mm[1],
                             plot_size_px=None if self._plot is None else self._plot.size_px(),
                             desc="PSF edge fit", on_returned=lambda out: self._show(*out, geometry_mm),
                             on_finished=self._fit_done, panel=self._job, readout=self._readout)

    def _fit_done(self) -> None:
        """The fit's job is over (any outcome): :func:`job_done`; when it showed no new result
        (cancelled, failed) and an earlier fit is kept, the read-out says so and shows it."""
        job_done(self._fit, self._job, self._readout)()
        if self.model is not None and self._summary is not None and self._readout.value != self._summary:
            self._readout.value = f"{self._readout.value}\nthe previous fit is kept:\n{self._summary}"

    def cancel(self) -> None:
        """Stop the running fit at its next optimiser iteration (the Cancel button)."""
        self._job.cancel()

    def _show(self, model: PSFModel, kernel: np.ndarray, summary: str, plot: tuple | None,
              geometry_mm: tuple[float, float]) -> Iterator[None]:
        """The kernel layer (over event-loop turns when it is new: :func:`show_layer_steps`),
        then, at the next turn, the read-out, the plot and the model ("Save psf.json").
        Stopped midway (Cancel, or a step failed), the kernel layer is put back as it was
        (:class:`ShownLayers`) and the read-out, plot and model stay at the previous fit, so
        the read-out never describes a PSF the kernel layer does not show, nor is saved."""
        shown = ShownLayers(self._viewer)
        with shown.put_back_if_stopped():
            yield from self._kernel_steps(model, kernel, geometry_mm, shown)
            yield
            if plot is not None:
                self._plot.show(*plot)
        self._readout.value = summary
        self.model, self._summary = model, summary
        self._save.enabled = True

    def show_kernel(self, model: PSFModel, kernel: np.ndarray | None = None,
                    geometry_mm: tuple[float, float] | None = None) -> napari.layers.Image:
        """The kernel at the chosen image's geometry, beside that image (``"PSF kernel"``);
        ``kernel``: that kernel when computed already (off the GUI thread) for ``geometry_mm``
        (SOD, SDD; default: the widget's)."""
        return finish_steps(self._kernel_steps(model, kernel, geometry_mm))

    def _kernel_steps(self, model: PSFModel, kernel: np.ndarray | None, geometry_mm: tuple[float, float] | None,
                      shown: ShownLayers | None = None) -> Generator[None, None, napari.layers.Image]:
        """:meth:`show_kernel` over event-loop turns (:func:`show_layer_steps`); ``shown``:
        the display's record of what it changed."""
        image = self._image.value
        sod_mm, sdd_mm = geometry_mm or (float(self._sod.value), float(self._sdd.value))
        if kernel is None:
            kernel = model.kernel(sod_mm, sdd_mm, max_radius_px=KERNEL_RADIUS_PX)
        scale, translate = (1.0, 1.0), (0.0, 0.0)
        if image is not None:
            scale = tuple(np.asarray(image.scale[-2:], float))
            translate = tuple(np.asarray(image.translate[-2:], float) + np.asarray(scale) * (0, np.shape(image.data)[1] + 8))
        layer = yield from show_layer_steps(self._viewer, kernel, "PSF kernel", "image", colormap="magma",
                                            scale=scale, translate=translate, shown=shown,
                                            contrast_limits=(0.0, float(kernel.max())), gamma=0.4)
        layer.gamma = 0.4  # show the tail (also when an existing layer is updated)
        layer.metadata.update({SOD_KEY: sod_mm, SDD_KEY: sdd_mm,
                               "psf": model.to_dict()})
        return layer

    @guarded("save psf.json")
    def save(self) -> Path | None:
        """Write the fitted model to the chosen path."""
        if self.model is None:
            raise ParameterError("fit the PSF first")
        path = Path(self._path.value)
        written = save_psf(self.model, path)
        notify_info(f"PSF model saved to {written}")
        return written
