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
