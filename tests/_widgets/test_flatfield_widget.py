"""Flat-field widget end to end: vignetting divided out, files load as layers, preview updates."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dslrxr._widgets.flatfield import FlatFieldWidget
from napari_dslrxr.core.io import write_tiff

pytestmark = pytest.mark.gui

DARK_COUNTS = 200.0


def vignetted_frames(rng, shape=(160, 200)):
    """Object transmission, a vignetted gain map, and radiograph/flat/dark frames (counts)."""
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    r2 = ((yy - h / 2) ** 2 + (xx - w / 2) ** 2) / (0.6 * max(h, w)) ** 2
    gain = (1.0 - r2) ** 2  # cos^4-like fall-off, 1 in the centre
    transmission = np.where((xx // 25) % 2 == 0, 0.4, 0.9)  # bars
    exposure = 3000.0
    radiograph = rng.poisson(exposure * gain * transmission) + DARK_COUNTS
    flat = rng.poisson(exposure * gain) + DARK_COUNTS
    dark = rng.normal(DARK_COUNTS, 2.0, shape)
    return transmission, gain, radiograph.astype(np.float32), flat.astype(np.float32), dark.astype(np.float32)


def test_flat_field_removes_vignetting(make_napari_viewer, wait_for_worker, rng):
    transmission, gain, radiograph, flat, dark = vignetted_frames(rng)
    viewer = make_napari_viewer()
    widget = FlatFieldWidget(viewer)
    viewer.window.add_dock_widget(widget)
    image_layer = viewer.add_image(radiograph, name="chest")
    widget._image.value = image_layer
    widget._flat.value = viewer.add_image(flat, name="flat")
    widget._dark.value = viewer.add_image(dark, name="dark")
    wait_for_worker(widget.run())

    corrected = viewer.layers["chest flat-fielded"].data
    # Before: the bars' brightness follows the vignetting (std of value/transmission ~ gain
    # spread). After: value/transmission is flat up to photon noise.
    before = (radiograph - DARK_COUNTS) / transmission
    after = corrected / transmission
    inner = gain > 0.3
    assert np.std(before[inner]) / np.mean(before[inner]) > 0.15
    assert np.std(after[inner]) / np.mean(after[inner]) < 0.05
    assert "corrected 200x160 px" in widget._readout.value
    assert "saturated" not in widget._readout.value

    clipped = np.minimum(flat, np.percentile(flat, 80))  # the flat's brightest fifth at a white level
    widget._flat.value = viewer.add_image(clipped, name="clipped flat")
    wait_for_worker(widget.run())
    assert "warning: flat frame saturated: 2" in widget._readout.value  # 20 % of its pixels at the maximum


def test_flat_and_dark_from_files_and_live_preview(make_napari_viewer, wait_for_worker, qtbot, tmp_path, rng):
    transmission, gain, radiograph, flat, dark = vignetted_frames(rng, shape=(96, 128))
    flat_path = write_tiff(tmp_path / "flat.tif", flat.astype(np.uint16))
    dark_path = write_tiff(tmp_path / "dark.tif", dark.astype(np.uint16))
    viewer = make_napari_viewer()
    widget = FlatFieldWidget(viewer)
    viewer.window.add_dock_widget(widget)
    widget._image.value = viewer.add_image(radiograph, name="hand")
    widget._flat_file.value = flat_path
    widget._dark_file.value = dark_path
    assert widget._flat.value is viewer.layers["flat: flat"]
    assert widget._dark.value is viewer.layers["dark: dark"]
    # Live preview: switching it on (and any later change) recomputes after the debounce.
    widget._preview.value = True
    preview = "hand flat-fielded (preview)"
    qtbot.waitUntil(lambda: preview in viewer.layers, timeout=20_000)
    wait_for_worker(widget._worker)
    first = viewer.layers[preview].data.copy()
    widget._smoothing.value = 0.0  # no smoothing: the flat's photon noise now enters the result
    qtbot.waitUntil(lambda: not np.array_equal(viewer.layers[preview].data, first), timeout=20_000)
    assert widget.get_params().flat_smoothing_px == 0.0
    assert "hand flat-fielded" not in viewer.layers  # only "Apply" makes the result layer
    # Turning the preview off removes its layer.
    widget._preview.value = False
    assert preview not in viewer.layers


def test_missing_flat_and_bad_file_are_notifications(make_napari_viewer, errors_shown, tmp_path, rng):
    viewer = make_napari_viewer()
    widget = FlatFieldWidget(viewer)
    viewer.window.add_dock_widget(widget)
    widget._image.value = viewer.add_image(rng.random((32, 32)).astype(np.float32), name="x")
    assert widget.run() is None and "flat" in errors_shown[-1]
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00garbage")
    widget._flat_file.value = bad
    assert "bad.tif" in errors_shown[-1] and widget._flat.value is None


def test_sample_set_vignetting_removed(make_napari_viewer, wait_for_worker):
    """On the DSLR sample: after the flat field, signal / (expected / gain map) is flat."""
    from napari.layers import Layer

    from napari_dslrxr import _sample_data as samples

    viewer = make_napari_viewer()
    dark, flat, radiograph = (viewer.add_layer(Layer.create(*t)) for t in samples.make_sample_dslr_set())
    widget = FlatFieldWidget(viewer)
    viewer.window.add_dock_widget(widget)
    widget._image.value, widget._flat.value, widget._dark.value = radiograph, flat, dark
    wait_for_worker(widget.run())
    frames = samples._phantom()
    truth = frames.truth
    inner = truth.screen_mask & (truth.gain_map > 0.4)
    inner[:, :40] = inner[:, -40:] = False
    object_light = truth.clean_rgb[..., 1] / truth.gain_map  # green, without the vignetting
    keep = inner & (object_light > 0.3 * object_light[inner].max())
    before = (radiograph.data[..., 1].astype(float) - frames.black_level)[keep] / object_light[keep]
    after = viewer.layers["DSLR radiograph flat-fielded"].data[..., 1][keep] / object_light[keep]
    spread = [np.percentile(v, 90) / np.percentile(v, 10) for v in (before, after)]
    assert spread[0] > 1.5 and spread[1] < 1.15
