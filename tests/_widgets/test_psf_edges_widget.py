"""PSF edge ROI picker: rectangles set as Shapes data over the two sample edges -> fitted PSF near truth."""

from __future__ import annotations

import numpy as np
import pytest
from napari.layers import Layer

from napari_dslrxr import _sample_data as samples
from napari_dslrxr._widgets.psf_edges import PSFEdgeWidget, rectangles_to_rois
from napari_dslrxr.core.psf import PSFModel, load_psf

pytestmark = pytest.mark.gui


def rectangle(r0, c0, r1, c1):
    return np.array([[r0, c0], [r0, c1], [r1, c1], [r1, c0]], float)


@pytest.fixture
def edges_docked(make_napari_viewer):
    viewer = make_napari_viewer()
    layers = [viewer.add_layer(Layer.create(*t)) for t in samples.make_sample_edges()]
    widget = PSFEdgeWidget(viewer)
    viewer.window.add_dock_widget(widget)
    return viewer, widget, layers


def test_rois_from_rectangles_fit_the_true_psf(edges_docked, wait_for_worker, tmp_path, errors_shown):
    viewer, widget, layers = edges_docked
    truth = samples.EDGE_TRUTH
    for layer in layers:
        widget._image.value = layer  # distances and pitch come from the layer metadata
        assert widget._sod.value == layer.metadata["source_to_object_mm"]
        assert widget._pitch.value == truth["pixel_pitch_mm"]
        shapes = widget.roi_layer()
        # One ROI around the vertical edge (left half), one around the horizontal one (right half).
        shapes.data = [rectangle(32, 32, 96, 96), rectangle(32, 160, 96, 224)]
        assert rectangles_to_rois(shapes, layer) == [(32, 32, 96, 96), (32, 160, 96, 224)]
    assert "edge SOD 500 mm: 2 ROI(s), SOD 500.0 mm, SDD 1000.0 mm" in widget._status.value
    wait_for_worker(widget.run(), timeout_ms=120_000)
    assert not errors_shown
    model = widget.model
    assert model.fit_report["n_images"] == 4
    # Focal spot recovered from two distances (truth 0.4 mm); the generalised detector core follows
    # the true core + tail (SABER, exponential profiles): MTF within 0.03 up to Nyquist (5 c/mm).
    assert model.source_fwhm_x_mm == pytest.approx(truth["source_fwhm_x_mm"], rel=0.1)
    assert model.source_fwhm_y_mm == pytest.approx(truth["source_fwhm_y_mm"], rel=0.1)
    f = np.linspace(0.0, 5.0, 26)
    assert np.abs(model.detector_mtf(f) - PSFModel(**truth).detector_mtf(f)).max() < 0.03
    assert f"focal spot FWHM x, y: {model.source_fwhm_x_mm:.3g} ± " in widget._readout.value
    assert "core MTF (1 + u (f s)^q)^(-1/u)" in widget._readout.value and "MTF50" in widget._readout.value
    # Fitted vs measured profiles are plotted (two axes, a measured and a fitted line per ROI).
    esf_axis, lsf_axis = widget._figure.axes
    assert len(esf_axis.lines) == len(lsf_axis.lines) == 8
    # The kernel shown is the model's at the chosen image's geometry, normalised.
    kernel = viewer.layers["PSF kernel"].data
    np.testing.assert_allclose(kernel, model.kernel(900.0, 1000.0, max_radius_px=64))
    assert kernel.sum() == pytest.approx(1.0, abs=1e-3)
    widget._path.value = tmp_path / "psf.json"
    assert widget.save() == tmp_path / "psf.json"
    loaded = load_psf(tmp_path / "psf.json")
    assert loaded.source_fwhm_x_mm == pytest.approx(model.source_fwhm_x_mm)


def test_no_roi_and_cancel(edges_docked, wait_for_worker, errors_shown, monkeypatch):
    viewer, widget, layers = edges_docked
    assert widget.run() is None and "draw at least one rectangle" in errors_shown[-1]
    import napari.utils.notifications as notifications

    infos = []
    monkeypatch.setattr(notifications, "show_info", infos.append)
    widget._image.value = layers[0]
    widget.roi_layer().data = [rectangle(32, 32, 96, 96)]
    worker = widget.run()
    widget.cancel()
    wait_for_worker(worker)
    assert widget.model is None and any("cancelled" in m for m in infos)
    assert widget._fit.enabled and not widget._cancel.enabled


# --------------------------------------------------------------------------- Cancel or a failing step while shown


def _draw_one_roi_per_image(widget, layers) -> None:
    for layer in layers:
        widget._image.value = layer
        widget.roi_layer().data = [rectangle(32, 32, 96, 96)]


def _cancel_at(qtbot, widget, event) -> list[bool]:
    """Press Cancel in the event-loop turn after ``event`` fires (between two display steps,
    before the next step's timer); returns the list the press is recorded in."""
    from qtpy.QtCore import Qt, QTimer

    pressed: list[bool] = []

    def press(*_args) -> None:
        if not pressed:
            pressed.append(True)
            QTimer.singleShot(0, lambda: qtbot.mouseClick(widget._cancel.native, Qt.MouseButton.LeftButton))

    event.connect(press)
    return pressed


def test_cancel_while_a_first_fit_is_shown_leaves_no_kernel_no_model_no_result_read_out(
        edges_docked, qtbot, wait_for_worker, errors_shown, tmp_path):
    """Cancel once the kernel layer was added (hidden, before its reveal and the read-out's
    step): no kernel layer, nothing "Save psf.json" could write, a read-out that says cancelled
    and no fitted values."""
    viewer, widget, layers = edges_docked
    _draw_one_roi_per_image(widget, layers)
    pressed = _cancel_at(qtbot, widget, viewer.layers.events.inserted)
    worker = widget.run()
    qtbot.waitUntil(lambda: worker.dslrxr_finished, timeout=120_000)
    qtbot.wait(200)  # longer than the steps' timers: none is left to run
    assert pressed and worker.dslrxr_cancelled
    assert "PSF kernel" not in viewer.layers and widget.model is None
    assert not widget._save.enabled and widget._figure is None
    assert "cancelled" in widget._readout.value and "focal spot" not in widget._readout.value
    assert widget._fit.enabled and not errors_shown
    widget._path.value = tmp_path / "psf.json"
    assert widget.save() is None and "fit the PSF first" in errors_shown[-1]
    assert not (tmp_path / "psf.json").exists()


def _fitted_once(viewer, widget, layers, wait_for_worker):
    """A first fit shown in full; what it shows."""
    _draw_one_roi_per_image(widget, layers)
    wait_for_worker(widget.run(), timeout_ms=120_000)
    kernel = viewer.layers["PSF kernel"]
    shown = {"model": widget.model, "readout": widget._readout.value, "figure": widget._figure,
             "data": kernel.data, "scale": tuple(kernel.scale), "translate": tuple(kernel.translate),
             "contrast_limits": tuple(kernel.contrast_limits), "psf": kernel.metadata["psf"]}
    assert shown["model"] is not None and "focal spot" in shown["readout"]
    # the re-fit shows another kernel: another profile, at the other image's geometry
    widget._shape.value = "Gaussian (p = 2)"
    widget._image.value = layers[0]
    return kernel, shown


def _assert_previous_fit_kept(viewer, widget, kernel, shown) -> None:
    assert viewer.layers["PSF kernel"] is kernel and kernel.visible
    assert kernel.data is shown["data"] and tuple(kernel.scale) == shown["scale"]
    assert tuple(kernel.translate) == shown["translate"]
    assert tuple(kernel.contrast_limits) == shown["contrast_limits"]
    assert kernel.metadata["psf"] == shown["psf"] and kernel.gamma == 0.4
    assert widget.model is shown["model"] and widget._save.enabled and widget._figure is shown["figure"]
    # the read-out says what happened and shows the fit the kernel layer shows
    assert widget._readout.value.endswith(shown["readout"])


def test_a_re_fit_cancelled_while_shown_keeps_the_previous_kernel_read_out_and_model(
        edges_docked, qtbot, wait_for_worker, errors_shown, tmp_path):
    """Cancel after the re-fit updated the kernel layer in place, before its read-out's step:
    the kernel layer shows the previous kernel again, the model, plot and read-out are the
    previous fit's, and "Save psf.json" writes that fit."""
    viewer, widget, layers = edges_docked
    kernel, shown = _fitted_once(viewer, widget, layers, wait_for_worker)
    pressed = _cancel_at(qtbot, widget, kernel.events.data)
    worker = widget.run()
    qtbot.waitUntil(lambda: worker.dslrxr_finished, timeout=120_000)
    qtbot.wait(200)
    assert pressed and worker.dslrxr_cancelled and not errors_shown
    _assert_previous_fit_kept(viewer, widget, kernel, shown)
    assert widget._readout.value.startswith("PSF edge fit: cancelled")
    widget._path.value = tmp_path / "psf.json"
    widget.save()
    assert load_psf(tmp_path / "psf.json").shape_power == shown["model"].shape_power == 1.0  # not the Gaussian


@pytest.mark.parametrize("first", [True, False], ids=["first fit", "re-fit"])
def test_a_failing_display_step_leaves_the_previous_fit_or_none(edges_docked, wait_for_worker, errors_shown,
                                                                monkeypatch, first):
    """The display's last step (the plot) raises after the kernel layer was shown: one
    notification, the kernel layer removed (first fit) or put back (re-fit), the model and the
    read-out the previous fit's or none, the read-out and the status saying it failed."""
    from napari_dslrxr._widgets._plots import WorkerPlot

    viewer, widget, layers = edges_docked
    if first:
        _draw_one_roi_per_image(widget, layers)
    else:
        kernel, shown = _fitted_once(viewer, widget, layers, wait_for_worker)

    def broken(*_args, **_kwargs):
        raise RuntimeError("no plot today")

    monkeypatch.setattr(WorkerPlot, "show", broken)
    wait_for_worker(widget.run(), timeout_ms=120_000)
    assert len(errors_shown) == 1 and "no plot today" in errors_shown[0]
    assert widget._readout.value.startswith("failed") and widget._job.status.value.startswith("failed")
    assert widget._fit.enabled
    if first:
        assert "PSF kernel" not in viewer.layers and widget.model is None and not widget._save.enabled
        assert "focal spot" not in widget._readout.value
    else:
        _assert_previous_fit_kept(viewer, widget, kernel, shown)
