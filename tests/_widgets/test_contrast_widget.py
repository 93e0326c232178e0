"""Contrast widget: sliders change the look as the core says; preview matches the full result."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from napari_dslrxr._widgets.contrast import DISPLAY, LINEAR, ContrastWidget
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph

pytestmark = pytest.mark.gui


def _split(display, mask, size_px=31):
    """Std of the large-area part and of the detail inside the mask (display units)."""
    low = cv2.blur(display.astype(np.float32), (size_px, size_px))
    return float(np.std(low[mask])), float(np.std((display - low)[mask]))


@pytest.fixture
def phantom():
    return make_dslr_radiograph((240, 320), seed=3, pulse_rate=0.0)


@pytest.fixture
def docked(make_napari_viewer, phantom):
    viewer = make_napari_viewer()
    widget = ContrastWidget(viewer, preview_max_pixels=20_000)  # force a downsampled preview
    viewer.window.add_dock_widget(widget)
    clean = phantom.raw_rgb.astype(np.float32) - phantom.black_level
    widget._live.value = False
    widget._image.value = viewer.add_image(clean, name="frame", rgb=False, channel_axis=None)
    return viewer, widget


def _apply(widget, wait_for_worker, **values):
    for (section, name), slider in widget._sliders.items():
        if name in values:
            slider.value = values[name]
    wait_for_worker(widget.run())
    return widget.result.copy()


@pytest.mark.slow
def test_latitude_and_bone_contrast_sliders(docked, phantom, wait_for_worker, errors_shown):
    viewer, widget = docked
    assert widget._kind.value == LINEAR
    # the sliders' own effects: without the compression that keeps the anatomy off the display's ends
    import dataclasses

    from napari_dslrxr.core.params import PipelineParams

    # and with the power-law mapping in the coarse bands (coarse_halo_step 0), which bone contrast and
    # the halo guard act on everywhere; the default coarse remapping leaves the phantom's strong
    # edges alone (tests/core/stages/test_contrast.py)
    defaults = PipelineParams()
    widget.set_params({"dynamic_range": dataclasses.replace(defaults.dynamic_range, max_clipped_percent=100.0),
                       "contrast": dataclasses.replace(defaults.contrast, coarse_halo_step=0.0)})
    inner = cv2.erode(phantom.truth.screen_mask.astype(np.uint8), np.ones((25, 25), np.uint8)).astype(bool)
    plain = _apply(widget, wait_for_worker, latitude=1.0, detail_gain=1.0, bone_contrast=1.0,
                   detail_contrast=0.0, edge_sharpness=1.0)
    assert plain.shape == phantom.raw_rgb.shape[:2] and 0.0 <= plain.min() and plain.max() <= 1.0
    assert viewer.layers["frame contrast"].data is widget.result
    low_lat = _apply(widget, wait_for_worker, latitude=0.3)
    # The phantom's structures are mostly strong edges, which the halo guard keeps at unit
    # gain; with the guard off, bone contrast boosts them all.
    bone = _apply(widget, wait_for_worker, latitude=1.0, bone_contrast=3.0, halo_step=0.0)
    guarded = _apply(widget, wait_for_worker, halo_step=0.3)
    assert not errors_shown, errors_shown
    plain_low, plain_detail = _split(plain, inner)
    lat_low, _ = _split(low_lat, inner)
    _, bone_detail = _split(bone, inner)
    _, guarded_detail = _split(guarded, inner)
    assert lat_low < 0.8 * plain_low  # latitude compresses large-area variation
    assert bone_detail > 1.3 * plain_detail  # bone contrast boosts mid-size structure
    assert plain_detail < guarded_detail < bone_detail  # the guard holds back strong edges only
    params = widget.get_params()
    assert params["contrast"].bone_contrast == pytest.approx(3.0)
    assert params["contrast"].halo_step == pytest.approx(0.3)
    assert params["dynamic_range"].latitude == pytest.approx(1.0)


@pytest.mark.slow
def test_live_preview_is_downsampled_and_matches_the_full_result(docked, qtbot, wait_for_worker):
    viewer, widget = docked
    full = _apply(widget, wait_for_worker, bone_contrast=2.5)
    widget._live.value = True
    qtbot.waitUntil(lambda: widget.preview is not None, timeout=20_000)
    wait_for_worker(widget._preview_worker)
    preview_layer = viewer.layers["frame contrast (preview)"]
    small = preview_layer.data
    assert small.size <= 20_000 < full.size
    # Drawn over the input: its world extent equals the full image's.
    extent = np.asarray(small.shape) * np.asarray(preview_layer.scale)
    np.testing.assert_allclose(extent, full.shape, rtol=0.02)
    reference = cv2.resize(full, small.shape[::-1], interpolation=cv2.INTER_AREA)
    assert np.corrcoef(small.ravel(), reference.ravel())[0, 1] > 0.95
    # A slider move updates the preview.
    before = small.copy()
    widget._sliders[("dynamic_range", "lut_width")].value = 0.2
    qtbot.waitUntil(lambda: not np.array_equal(viewer.layers["frame contrast (preview)"].data, before),
                    timeout=20_000)
    assert widget.last_preview_s is not None and "ms" in widget._readout.value


def test_display_radiograph_input(make_napari_viewer, wait_for_worker, rng):
    viewer = make_napari_viewer()
    widget = ContrastWidget(viewer)
    viewer.window.add_dock_widget(widget)
    widget._live.value = False
    yy, xx = np.mgrid[:128, :160]
    radiograph = (1000 + 2000 * (xx / 160) + 300 * ((yy // 16) % 2)).astype(np.uint16)
    layer = viewer.add_image(radiograph, name="cr", metadata={"format": "dicom"})
    widget._image.value = layer
    assert widget._kind.value == DISPLAY

    def ramp_and_stripes(out):
        ramp = out[:, 120:140].mean() - out[:, 20:40].mean()
        stripes = np.abs(out[8:120, 60:100] - out[16:128, 60:100]).mean()  # 16 px period, half shift
        return ramp, stripes

    wide = _apply(widget, wait_for_worker, latitude=1.0)
    narrow = _apply(widget, wait_for_worker, latitude=0.3)
    assert wide.shape == radiograph.shape
    (ramp_wide, stripes_wide), (ramp_narrow, stripes_narrow) = ramp_and_stripes(wide), ramp_and_stripes(narrow)
    # Latitude compresses the slow left-right ramp more than the 16 px stripes.
    assert ramp_narrow < 0.7 * ramp_wide
    assert ramp_narrow / stripes_narrow < 0.7 * ramp_wide / stripes_wide


def _clipped_percent(readout: str) -> float:
    import re

    match = re.search(r"([0-9.]+) % of the anatomy clipped", readout)
    assert match, readout
    return float(match.group(1))


def test_readout_reports_the_clipped_anatomy(docked, phantom, qtbot, wait_for_worker, errors_shown):
    """The read-out's clipped share follows the picture: strong gains without the fit clip much."""
    from qtpy.QtCore import Qt

    from napari_dslrxr.core.params import PipelineParams

    viewer, widget = docked
    truth = phantom.truth
    h, w = phantom.raw_rgb.shape[:2]
    # independent reference: body pixels (truth attenuation above the direct exposure's 0.1) well
    # inside the screen, clipped when at the 8-bit preview's 0 or 255
    attenuation = cv2.warpPerspective(truth.attenuation, truth.homography, (w, h), flags=cv2.INTER_LINEAR)
    inner = cv2.erode(truth.screen_mask.astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
    body = inner & (attenuation > 0.6)

    def click_apply(where=body) -> float:
        qtbot.mouseClick(widget._apply.native, Qt.MouseButton.LeftButton)
        qtbot.waitUntil(lambda: widget._apply.enabled and widget._readout.value.startswith("applied"), timeout=60_000)
        shown = widget.result[where]
        return float(np.mean((shown <= 0.5 / 255) | (shown >= 254.5 / 255)))

    import dataclasses

    # strong gains push the anatomy beyond the value-of-interest range; without the fit it burns out
    defaults = PipelineParams()
    widget.set_params({"dynamic_range": dataclasses.replace(defaults.dynamic_range, max_clipped_percent=100.0,
                                                            latitude=1.0, detail_gain=3.0),
                       "contrast": dataclasses.replace(defaults.contrast, bone_contrast=3.0, halo_step=0.0,
                                                       coarse_halo_step=0.0)})
    steep = click_apply()  # share of the body clipped (independent of the core's anatomy rule)
    assert steep > 0.05, (widget._readout.value, steep)  # the strong gains burn out part of the body
    # The widget's linear input has no flat field: the open beam keeps its vignetting, spreads
    # as widely as the uniform body, and is not told apart from it (the safe side), so the
    # anatomy the read-out counts is the whole screen: compare with the screen's clipped share
    reported = _clipped_percent(widget._readout.value) / 100
    screen = click_apply(inner)
    assert abs(reported - screen) < 0.3 * screen, (reported, screen)
    # the self-check says so in the read-out, as the command line and the sidecar do
    assert "warning: display implausible" in widget._readout.value, widget._readout.value
    widget.set_params({"dynamic_range": defaults.dynamic_range, "contrast": defaults.contrast})
    # the lung fields (truth geometry, 2 px inside their outline) are attenuated anatomy, not
    # direct exposure: with the defaults they are shown, not burned black (the level-only
    # direct-exposure rule left them out of the anatomy: 52 % of their interior was black while
    # the read-out said 0.5 %)
    hs, ws = truth.attenuation.shape
    v, u = (np.mgrid[0:hs, 0:ws] / np.array([hs, ws])[:, None, None]).astype(np.float32)
    fields = np.zeros((hs, ws), np.uint8)
    for cx in (0.33, 0.67):  # make_object's lung fields
        fields |= (((u - cx) / 0.11) ** 2 + ((v - 0.36) / 0.17) ** 2 < 1).astype(np.uint8)
    lungs = cv2.warpPerspective(fields, truth.homography, (w, h), flags=cv2.INTER_NEAREST)
    lung_interior = cv2.distanceTransform(lungs, cv2.DIST_L2, 5) > 2
    assert lung_interior.sum() > 500
    assert click_apply(lung_interior) <= 0.01
    # the defaults keep the anatomy the core counts (direct exposure left out) within 1 %
    assert _clipped_percent(widget._readout.value) <= 1.0
    assert "warning" not in widget._readout.value, widget._readout.value
