"""Screenshots of the viewer with each widget docked and its result shown (docs/screenshots/).

Each test drives a widget on the sample data, then saves the whole window (layer list,
canvas, dock) at 1300x800 and checks the canvas is not black (a broken GL set-up under the
virtual X server renders black). The images committed in docs/screenshots/ and shown in the
README are refreshed only on request (DSLRXR_UPDATE_SCREENSHOTS=1), so an ordinary test run
leaves the working tree clean; otherwise they go to a temporary folder.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import napari
import numpy as np
import pytest

from napari_dslrxr import _sample_data as samples
from napari_dslrxr._widgets._common import viewer_camera

pytestmark = pytest.mark.gui

DOCS_SHOTS = Path(__file__).resolve().parents[2] / "docs" / "screenshots"


@pytest.fixture(autouse=True)
def _shots_folder(tmp_path, monkeypatch):
    folder = DOCS_SHOTS if os.environ.get("DSLRXR_UPDATE_SCREENSHOTS") == "1" else tmp_path / "screenshots"
    monkeypatch.setattr(sys.modules[__name__], "SHOTS", folder)


SHOTS = DOCS_SHOTS


def snap(viewer, name: str) -> Path:
    """Resize, let Qt lay out and draw, save the window; assert the canvas shows something."""
    from qtpy.QtWidgets import QApplication

    viewer.window.resize(1300, 800)
    for _ in range(5):
        QApplication.processEvents()
    SHOTS.mkdir(parents=True, exist_ok=True)
    path = SHOTS / f"{name}.png"
    window = viewer.screenshot(str(path), canvas_only=False, flash=False)
    canvas = viewer.screenshot(canvas_only=True, flash=False)
    assert window.shape[0] >= 700 and window.shape[1] >= 1200
    assert canvas[..., :3].mean() > 10, "canvas rendered black (GL under the virtual display?)"
    assert path.stat().st_size > 10_000
    return path


def _viewer(make_napari_viewer):
    return make_napari_viewer(show=True)


def _add(viewer, tuples):
    return [viewer.add_layer(napari.layers.Layer.create(*t)) for t in tuples]


def test_screenshot_impulse(make_napari_viewer, wait_for_worker):
    from napari_dslrxr._widgets.impulse import ImpulseWidget

    viewer = _viewer(make_napari_viewer)
    (layer,) = _add(viewer, samples.make_sample_radiograph())
    widget = ImpulseWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Impulse removal", area="right")
    widget._image.value = layer
    wait_for_worker(widget.run())
    layer.visible = False
    viewer_camera(viewer).center = (0, 200, 330)
    viewer_camera(viewer).zoom = 3.0
    assert any(np.count_nonzero(viewer.layers[f"DSLR radiograph pulses {c}"].data) for c in "HSV")
    snap(viewer, "impulse")


def test_screenshot_flatfield(make_napari_viewer, wait_for_worker):
    from napari_dslrxr._widgets.flatfield import FlatFieldWidget

    viewer = _viewer(make_napari_viewer)
    dark, flat, radiograph = _add(viewer, samples.make_sample_dslr_set())
    widget = FlatFieldWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Flat field", area="right")
    widget._image.value, widget._flat.value, widget._dark.value = radiograph, flat, dark
    wait_for_worker(widget.run())
    for layer in (dark, flat, radiograph):
        layer.visible = False
    snap(viewer, "flatfield")


def test_screenshot_deconvolution(make_napari_viewer, wait_for_worker, qtbot):
    from napari_dslrxr._widgets.deconvolution import DeconvolutionWidget

    viewer = _viewer(make_napari_viewer)
    from napari_dslrxr.core.stages.impulse import remove_impulses

    frames = samples._phantom()
    cleaned = remove_impulses(frames.raw_rgb).image  # pulses would ring in the deconvolution
    green = cleaned[..., 1].astype(np.float32) - frames.black_level
    image = viewer.add_image(green, name="green, cleaned", colormap="gray")
    r = np.arange(-8, 9)
    sigma = frames.truth.blur_sigma_px
    kernel = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma**2))
    kernel_layer = viewer.add_image((kernel / kernel.sum()).astype(np.float32), name="kernel", visible=False)
    widget = DeconvolutionWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Deconvolution", area="right")
    widget._image.value, widget._kernel_layer.value = image, kernel_layer
    widget._method.value = "rls"
    widget._reg.value = 30.0
    viewer_camera(viewer).center = (0, 240, 300)
    viewer_camera(viewer).zoom = 2.5
    widget._live.value = True
    qtbot.waitUntil(lambda: widget.last_preview is not None, timeout=30_000)
    wait_for_worker(widget._preview_worker)
    snap(viewer, "deconvolution")


def test_screenshot_contrast(make_napari_viewer, wait_for_worker):
    from napari_dslrxr._widgets.contrast import ContrastWidget
    from napari_dslrxr._widgets.flatfield import correct_with_layers
    from napari_dslrxr.core.stages.flatfield import FlatFieldParams
    from napari_dslrxr.core.stages.impulse import remove_impulses

    viewer = _viewer(make_napari_viewer)
    frames = samples._phantom()
    cleaned = remove_impulses(frames.raw_rgb).image  # the chain's order: pulses, then flat field
    corrected, _ = correct_with_layers(cleaned, frames.flat, frames.dark, FlatFieldParams())
    source = viewer.add_image(corrected, name="cleaned, flat-fielded", rgb=True, visible=False)
    widget = ContrastWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Contrast", area="right")
    widget._live.value = False
    widget._image.value = source
    widget._sliders[("contrast", "bone_contrast")].value = 2.5
    wait_for_worker(widget.run())
    snap(viewer, "contrast")


@pytest.mark.slow
def test_screenshot_psf_edges(make_napari_viewer, wait_for_worker):
    from napari_dslrxr._widgets.psf_edges import PSFEdgeWidget

    viewer = _viewer(make_napari_viewer)
    layers = _add(viewer, samples.make_sample_edges())
    widget = PSFEdgeWidget(viewer)
    viewer.window.add_dock_widget(widget, name="PSF from edges", area="right")
    for layer in layers:  # one ROI per image keeps the fit short (the widget test fits four)
        widget._image.value = layer
        widget.roi_layer().data = [np.array([[32, 32], [32, 96], [96, 96], [96, 32]], float)]
    layers[0].visible = viewer.layers["edge SOD 500 mm ROIs"].visible = False
    wait_for_worker(widget.run(), timeout_ms=120_000)
    camera = viewer_camera(viewer)
    camera.center, camera.zoom = (0, 64, 200), 1.5  # the edge image and the kernel beside it
    snap(viewer, "psf_edges")


@pytest.mark.slow
def test_screenshot_diagnosis(make_napari_viewer, wait_for_worker):
    from napari_dslrxr._widgets.diagnosis import DiagnosisWidget

    viewer = _viewer(make_napari_viewer)
    thickness, recording = _add(viewer, samples.make_sample_scene())
    widget = DiagnosisWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Diagnosis", area="right")
    widget._recording.value = recording
    widget._max_terms.value = 1
    wait_for_worker(widget.run(), timeout_ms=120_000)
    thickness.visible = False
    viewer.layers["residual z 4x4 (base model)"].visible = True
    after = viewer.layers["residual z 4x4 (final model)"]
    after.translate = (after.translate[0], after.translate[1] + 14.0)  # after, beside before (mm)
    viewer.reset_view()
    viewer_camera(viewer).zoom *= 1.5
    snap(viewer, "diagnosis")


def test_screenshot_all_widgets_docked(make_napari_viewer):
    """``dslrxr view`` layout: the sample radiograph and every widget tabbed on the right."""
    from napari_dslrxr._cli.view import populate_viewer

    viewer = _viewer(make_napari_viewer)
    _add(viewer, samples.make_sample_radiograph())
    docked = populate_viewer(viewer, [])
    assert len(docked) >= 5
    snap(viewer, "all_widgets")
