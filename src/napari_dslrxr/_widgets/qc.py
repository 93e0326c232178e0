"""Detector quality widget (IEC 62220-1-1) over :func:`napari_dslrxr.core.qc.measure_detector_quality`.

Pick the flat (open-beam) layers and the dark layers (one channel each: for a camera raw file,
one of its Bayer planes), the slanted-edge layer, the beam quality, the air kerma at the detector
and the pixel pitch. The edge is analysed inside the rectangles of its ROI layer (``"<edge> ROIs"``,
the same layer the PSF widget uses; "Draw edge ROI" makes it), one edge per rectangle (a
near-vertical and a near-horizontal edge give both directions), or over the whole frame without
one. "Measure" runs in a thread worker (progress bar with Cancel); the widget then plots the
presampled MTF, the NNPS and the DQE with their ±1 standard-uncertainty bands, lists the
values at a quarter, half and three quarters of the Nyquist frequency, and "Write report"
writes ``qc.json``, ``qc.csv`` and ``qc.html`` with :func:`napari_dslrxr.core.qc.write_qc_outputs`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import ComboBox, Container, FileEdit, Label, PushButton, Select

from ..core.errors import ParameterError
from ..core.qc import DetectorQuality, QcParams, measure_detector_quality, write_qc_outputs
from ._controls import param_widget, restore_defaults_button
from ._jobs import JobPanel, ReportButtonsMixin, guarded, readout_label, run_in_worker, scroll_long_readout
from ._layers import reset_choices, single_channel_layers
from ._plots import ShownFigureMixin, render_figure, worker_plot
from .psf_edges import edge_roi_layer, rectangles_to_rois, roi_layer_name

if TYPE_CHECKING:
    import napari

#: Where along the frequency axis the read-out lists the numbers (fractions of Nyquist).
READOUT_FRACTIONS = (0.25, 0.5, 0.75)
_STYLE = {"horizontal": ("C0", "-"), "vertical": ("C3", "--")}
#: Rows the flat and dark layer lists show without scrolling.
LIST_ROWS = 5
#: Height of the curves' plot (fixed: a read-out changing its length must not move it).
PLOT_HEIGHT_PX = 200


def quality_summary(result: DetectorQuality) -> str:
    """The read-out: MTF, NNPS and DQE (± standard uncertainty) at fractions of Nyquist, q,
    the edges found and the warnings."""
    f = result.frequency_cy_per_mm
    lines = [f"q = {result.q_photons_per_mm2:.5g} photons/mm² ({result.beam}, {result.air_kerma_ugy:g} µGy); "
             f"Nyquist {result.nyquist_cy_per_mm:.3g} cycles/mm; direction {result.direction}"]
    for fraction in READOUT_FRACTIONS:
        i = result.index_at(fraction)
        lines.append(f"{f[i]:.3g} c/mm: MTF {result.mtf[i]:.3f} ± {result.mtf_uncertainty[i]:.3f}, "
                     f"NNPS {result.nnps_mm2[i]:.3g} ± {result.nnps_uncertainty_mm2[i]:.2g} mm², "
                     f"DQE {result.dqe[i]:.3f} ± {result.dqe_uncertainty[i]:.3f}")
    lines += [f"edge {k + 1}: {e.direction}, {e.angle_deg:.2f}°" for k, e in enumerate(result.edges)]
    lines += [f"warning: {w}" for w in result.warnings]
    return "\n".join(lines)


def draw_curves(figure, result: DetectorQuality) -> None:
    """MTF and DQE (left) and NNPS (right, log) against frequency, each measured direction,
    with ±1 standard-uncertainty bands."""
    left, right = figure.subplots(1, 2)
    f = result.frequency_cy_per_mm
    for direction, curves in result.per_direction.items():
        colour, style = _STYLE.get(direction, ("C2", "-"))
        for ax, value, unc, width, label in (
                (left, curves.mtf, curves.mtf_uncertainty, 1.4, f"MTF {direction}"),
                (left, curves.dqe, curves.dqe_uncertainty, 0.8, f"DQE {direction}"),
                (right, curves.nnps_mm2, curves.nnps_uncertainty_mm2, 1.2, direction)):
            ax.plot(f, value, color=colour, ls=style, lw=width, label=label,
                    marker="" if width > 1 or ax is right else ".", ms=3)
            ax.fill_between(f, value - np.nan_to_num(unc), value + np.nan_to_num(unc), color=colour, alpha=0.25)
    left.set_title("MTF (line), DQE (dots)", fontsize=9)
    right.set_title("NNPS (mm²)", fontsize=9)
    left.set_ylim(0, 1.05)
    right.set_yscale("log")
    for ax in (left, right):
        ax.axvline(result.nyquist_cy_per_mm, color="0.5", lw=0.8, ls=":")
        ax.set_xlim(0, 1.02 * result.nyquist_cy_per_mm)
        ax.set_xlabel("cycles/mm", fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
    left.legend(fontsize=6, loc="upper right")


def measure_for_display(flats, darks, edges, *, plot_size_px: tuple[int, int] | None = None,
                        **kwargs) -> tuple[DetectorQuality, tuple | None]:
    """Worker job: the measurement and its curves rendered at ``plot_size_px`` (none without),
    so the GUI thread only shows the pixels."""
    result = measure_detector_quality(flats, darks, edges, **kwargs)
    plot = None if plot_size_px is None else render_figure(lambda figure: draw_curves(figure, result), plot_size_px)
    return result, plot


def _titled(widget) -> Container:
    """``widget`` with its label above it (a list keeps the column's width)."""
    column = Container(widgets=[Label(value=widget.label), widget], labels=False)
    column.margins = (0, 0, 0, 0)
    return column


def _row(*widgets, labels: bool = False) -> Container:
    row = Container(widgets=list(widgets), layout="horizontal", labels=labels)
    row.margins = (0, 0, 0, 0)
    return row


class QCWidget(ShownFigureMixin, ReportButtonsMixin, Container):
    """Measure a detector's MTF, NNPS and DQE from flat, dark and slanted-edge layers."""

    REPORT_PAGE = "html"
    REPORT_NAME = "QC report"

    def __init__(self, viewer: napari.viewer.Viewer):
        self._viewer = viewer
        self._flats = Select(choices=self._single_channel_names, label="flat layers",
                             tooltip="open-beam frames at the air kerma below (linear counts, one channel; "
                                     "ctrl-click for several)")
        self._darks = Select(choices=self._single_channel_names, label="dark layers",
                             tooltip="frames with the X-rays off (none: no dark subtracted)")
        self._edge = ComboBox(choices=self._single_channel_layers, label="edge layer",
                              tooltip="a slanted edge (1.5-3° from the pixel axis), same exposure as the flats")
        self._draw = PushButton(text="Draw edge ROI", tooltip="adds (or selects) the shapes layer '<edge> ROIs': "
                                                              "drag one rectangle around each edge (none: whole frame)")
        self._beam = param_widget(QcParams, "beam", label="beam", section="qc")
        self._kerma = param_widget(QcParams, "air_kerma_ugy", label="air kerma (µGy)", section="qc", step=0.1)
        self._pitch = param_widget(QcParams, "pixel_pitch_mm", label="pixel pitch (mm)", section="qc", step=0.001)
        self._roi_size = param_widget(QcParams, "roi_size_px", label="NNPS ROI (px)", section="qc")
        self._run = PushButton(text="Measure MTF, NNPS, DQE", tooltip="measure per IEC 62220-1-1 in the background")
        self._job = JobPanel(tooltip="stop the measurement at its next step")
        self._cancel = self._job.cancel_button
        self._readout = readout_label()
        self._report_dir = FileEdit(mode="d", label="report folder", value="qc_report",
                                    tooltip="folder qc.json, qc.csv and qc.html are written to")
        self._write = PushButton(text="Write report", enabled=False, tooltip="write qc.json, qc.csv and qc.html")
        self._open = PushButton(text="Open report", enabled=False, tooltip="show qc.html in the web browser")
        self._restore = restore_defaults_button(self.restore_defaults)
        from qtpy.QtCore import Qt

        # Side by side, each titled above its list so the list has the column's whole width,
        # LIST_ROWS rows high (more scroll): names are elided in the middle, not cut at the end.
        for choice in (self._flats, self._darks):
            native = choice.native
            native.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
            native.setTextElideMode(Qt.TextElideMode.ElideMiddle)
            native.setFixedHeight(LIST_ROWS * (native.fontMetrics().lineSpacing() + 2) + 2 * native.frameWidth())
        layers = _row(*(_titled(choice) for choice in (self._flats, self._darks)))
        actions = _row(self._draw, self._run)
        report = _row(self._write, self._open, self._restore)
        super().__init__(widgets=[layers, self._edge, self._beam, self._kerma, self._pitch, self._roi_size, actions,
                                  *self._job.widgets, self._readout, self._report_dir, report])
        scroll_long_readout(self._readout)  # a long result scrolls, the window keeps its size
        self.result: DetectorQuality | None = None
        self.report_paths: dict[str, Path] = {}
        self._input_names: list[str] = []
        self._plot = worker_plot(self, PLOT_HEIGHT_PX, self._readout, "the curves")
        self._draw.changed.connect(self.roi_layer)
        self._run.changed.connect(self.run)
        self._write.changed.connect(self.write)
        self._open.changed.connect(self.open_report)
        self._edge.changed.connect(self._edge_chosen)
        viewer.layers.events.inserted.connect(self._reset_choices)
        viewer.layers.events.removed.connect(self._reset_choices)
        self._edge_chosen()

    def restore_defaults(self) -> None:
        """Beam, NNPS ROI size, air kerma and pixel pitch back to the [qc] defaults (the pitch
        then from the edge layer's metadata when it has one)."""
        defaults = QcParams()
        self._beam.value, self._roi_size.value = defaults.beam, defaults.roi_size_px
        self._kerma.value, self._pitch.value = defaults.air_kerma_ugy, defaults.pixel_pitch_mm
        self._edge_chosen()

    # -- layer choices -----------------------------------------------------------------------------
    def _single_channel_layers(self, *_args) -> list:
        """Image layers holding one 2-D channel (colour layers are not a detector's linear pixels)."""
        return single_channel_layers(self._viewer)

    def _single_channel_names(self, *_args) -> list[str]:
        return [name for name, _ in self._single_channel_layers()]

    def _reset_choices(self, *_args) -> None:
        reset_choices(self._flats, self._darks, self._edge)

    def _edge_chosen(self, *_args) -> None:
        layer = self._edge.value
        meta = {} if layer is None else layer.metadata
        pitch = meta.get("pixel_pitch_mm") or (meta.get("file_metadata", {}).get("pixel_spacing_mm") or [None])[0]
        if pitch:
            self._pitch.value = float(pitch)
        truth = meta.get("detector_truth", {})
        if truth.get("air_kerma_ugy"):  # the sample says what it was exposed to
            self._kerma.value = float(truth["air_kerma_ugy"])

    @guarded("QC edge ROI")
    def roi_layer(self):
        """The Shapes layer of the edge's ROIs (created if needed), in rectangle mode."""
        edge = self._edge.value
        if edge is None:
            raise ParameterError("choose the edge layer")
        return edge_roi_layer(self._viewer, edge)

    def _frames(self, names: list[str], what: str) -> list[np.ndarray]:
        layers = self._viewer.layers
        missing = [n for n in names if n not in layers]
        if missing:
            raise ParameterError(f"{what} layer '{missing[0]}' is no longer in the viewer")
        return [np.asarray(layers[n].data) for n in names]

    # -- measure -----------------------------------------------------------------------------------
    @guarded("detector quality")
    def run(self):
        """Measure in a thread worker; return the worker."""
        flat_names, dark_names = list(self._flats.value), list(self._darks.value)
        edge = self._edge.value
        if not flat_names:
            raise ParameterError("choose at least one flat layer")
        if edge is None:
            raise ParameterError("choose the edge layer")
        if edge.name in flat_names or edge.name in dark_names:
            raise ParameterError(f"'{edge.name}' is chosen as the edge and as a flat or dark")
        flats, darks = self._frames(flat_names, "flat"), self._frames(dark_names, "dark")
        rois = None
        shapes_name = roi_layer_name(edge.name)
        if shapes_name in self._viewer.layers:
            rois = rectangles_to_rois(self._viewer.layers[shapes_name], edge) or None
        edges = [np.asarray(edge.data)] * (len(rois) if rois else 1)
        settings = QcParams(beam=self._beam.value, air_kerma_ugy=float(self._kerma.value),
                            pixel_pitch_mm=float(self._pitch.value), roi_size_px=int(self._roi_size.value))
        edge_names = [f"edge layer '{edge.name}'" + (f" ROI {k + 1}" if rois else "") for k in range(len(edges))]
        self._input_names = ([f"flat layer '{n}'" for n in flat_names] + [f"dark layer '{n}'" for n in dark_names]
                             + edge_names)
        self._run.enabled = False
        self._readout.value = "measuring..."
        return run_in_worker(measure_for_display, flats, darks, edges, params=settings, edge_rois=rois,
                             plot_size_px=None if self._plot is None else self._plot.size_px(),
                             names={"flats": flat_names, "darks": dark_names, "edges": edge_names},
                             progress=self._job.callback, desc="detector quality",
                             on_returned=lambda out: self._show(*out),
                             on_finished=self._done, panel=self._job, readout=self._readout)

    def cancel(self) -> None:
        """Stop the measurement at its next step (the Cancel button)."""
        self._job.cancel()

    def _show(self, result: DetectorQuality, plot: tuple | None = None) -> None:
        self.result = result
        # say what was measured from (the lists scroll)
        self._readout.value = f"from {'; '.join(self._input_names)}\n{quality_summary(result)}"
        if plot is not None:
            self._plot.show(*plot)
        self._write.enabled = True

    # -- report ------------------------------------------------------------------------------------
    @guarded("QC report")
    def write(self):
        """Write qc.json, qc.csv and qc.html into the chosen folder (in a worker: the report's
        figures take a second); return the worker."""
        if self.result is None:
            raise ParameterError("measure first")
        folder = Path(self._report_dir.value)
        self._write.enabled = False
        return run_in_worker(write_qc_outputs, self.result, folder, input_names=list(self._input_names),
                             desc="QC report", on_returned=lambda paths: self._written(folder, paths),
                             on_finished=self._write_done, panel=self._job, readout=self._readout)
