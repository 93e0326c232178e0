"""Deconvolution widget: live preview of the visible region, whole-image run with progress and cancel."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import fftconvolve

from napari_dslrxr._widgets._layers import viewer_camera
from napari_dslrxr._widgets.deconvolution import DeconvolutionWidget

pytestmark = pytest.mark.gui


def gaussian_kernel(sigma_px: float, radius_px: int) -> np.ndarray:
    r = np.arange(-radius_px, radius_px + 1)
    g = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma_px**2))
    return (g / g.sum()).astype(np.float32)


def blurred_scene(rng, shape=(192, 224), sigma_px=1.5):
    """Sharp bars and discs (counts), the Gaussian kernel and the blurred noisy image."""
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    sharp = np.full(shape, 1000.0)
    sharp[(xx // 6) % 2 == 0] += 800.0  # 6 px-wide bars
    sharp[(yy - 140) ** 2 + (xx - 60) ** 2 < 20**2] = 2500.0
    kernel = gaussian_kernel(sigma_px, 8)
    blurred = fftconvolve(np.pad(sharp, 8, mode="edge"), kernel, mode="valid")
    noisy = blurred + rng.normal(0, 3.0, shape)
    return sharp.astype(np.float32), kernel, noisy.astype(np.float32)


def bar_modulation(image, rows=slice(10, 100), cols=slice(4, 220)):
    """Amplitude of the 12 px bar period in the rows above the disc (18 whole periods)."""
    profile = np.asarray(image)[rows, cols].mean(axis=0)
    x = np.arange(cols.start, cols.stop)
    return 2 * abs(np.mean(profile * np.exp(-2j * np.pi * x / 12)))


def _rms(a, b, margin=16):
    inner = (slice(margin, -margin), slice(margin, -margin))
    return float(np.sqrt(np.mean((a[inner] - b[inner]) ** 2)))


@pytest.fixture
def docked(make_napari_viewer, rng):
    sharp, kernel, blurred = blurred_scene(rng)
    viewer = make_napari_viewer()
    widget = DeconvolutionWidget(viewer)
    viewer.window.add_dock_widget(widget)
    widget._image.value = viewer.add_image(blurred, name="bars")
    widget._kernel_layer.value = viewer.add_image(kernel, name="kernel", visible=False)
    return viewer, widget, sharp, blurred


def test_reg_slider_spans_the_parameter_range(docked):
    """The slider's limits are the [deblur] reg field's range (the file's and the option's), so a
    value the command line accepts (1e7, once refused by the file) can be set here too."""
    from napari_dslrxr.core.param_fields import field_info
    from napari_dslrxr.core.stages.deconvolution import DeconvolutionParams

    _, widget, _, _ = docked
    info = field_info(DeconvolutionParams, "reg")
    assert (widget._reg.min, widget._reg.max) == (info["min"], info["max"])
    for value in (info["min"], 1e7, info["max"]):
        widget._reg.value = value
        assert widget._reg.value == pytest.approx(value, rel=0.02)


@pytest.mark.slow
def test_whole_image_is_sharper_than_the_input(docked, wait_for_worker):
    viewer, widget, sharp, blurred = docked
    widget._method.value = "rls"
    widget._reg.value = 30.0
    wait_for_worker(widget.run())
    out = viewer.layers["bars deconvolved"].data
    assert out.shape == blurred.shape
    # The blur leaves 73 % of the bars' modulation; deconvolution restores it (within 3 %)
    # and brings the image closer to the sharp truth.
    assert bar_modulation(blurred) < 0.75 * bar_modulation(sharp)
    assert bar_modulation(out) == pytest.approx(bar_modulation(sharp), rel=0.03)
    assert _rms(out, sharp) < 0.65 * _rms(blurred, sharp)
    assert "deconvolved with rls" in widget._readout.value


def test_slider_preview_shows_the_visible_region_and_reacts(docked, qtbot, wait_for_worker, errors_shown):
    viewer, widget, sharp, blurred = docked
    layer = viewer.layers["bars"]
    viewer_camera(viewer).center = (0, 120, 140)  # look at part of the image only
    viewer_camera(viewer).zoom = 4.0
    widget._live.value = True
    qtbot.waitUntil(lambda: widget.last_preview is not None or bool(errors_shown), timeout=20_000)
    assert not errors_shown
    wait_for_worker(widget._preview_worker)
    preview = viewer.layers["bars deconvolved (preview)"]
    rows, cols = widget.last_preview["rows"], widget.last_preview["cols"]
    assert preview.data.shape == (rows.stop - rows.start, cols.stop - cols.start)
    # Only the visible part plus a margin of the kernel radius (8 px): the canvas shows
    # size/zoom world pixels around the camera centre.
    height_px, width_px = viewer.canvas.size
    assert rows.start == max(0, round(120 - height_px / 8) - 8)
    assert cols.start == max(0, round(140 - width_px / 8) - 8)
    assert preview.data.size < 0.8 * blurred.size
    # The preview sits over its region in world coordinates.
    assert tuple(preview.translate) == (rows.start, cols.start)
    crop_truth, crop_blur = sharp[rows, cols], blurred[rows, cols]
    assert _rms(preview.data, crop_truth, 10) < 0.7 * _rms(crop_blur, crop_truth, 10)
    # Moving the slider to heavy regularisation recomputes a smoother preview.
    first = preview.data.copy()
    widget._reg.value = 1e5
    assert widget._reg.value == pytest.approx(1e5, rel=0.02)
    qtbot.waitUntil(lambda: widget.last_preview["reg"] == widget._reg.value, timeout=20_000)
    smooth = viewer.layers["bars deconvolved (preview)"].data
    assert np.std(np.diff(smooth, axis=1)) < np.std(np.diff(first, axis=1))


def test_cancel_stops_the_whole_image_run(docked, wait_for_worker, monkeypatch):
    viewer, widget, _, _ = docked
    widget._method.value = "adaptive"
    worker = widget.run()
    widget.cancel()
    wait_for_worker(worker)
    assert "bars deconvolved" not in viewer.layers
    assert widget._apply.enabled


def test_psf_file_and_missing_kernel(docked, tmp_path, errors_shown, wait_for_worker):
    from napari_dslrxr.core.psf import PSFModel, save_psf

    viewer, widget, sharp, blurred = docked
    widget._kernel_layer.value = None
    assert widget.run() is None and "kernel" in errors_shown[-1]
    model = PSFModel(pixel_pitch_mm=0.1, source_fwhm_x_mm=0.0, source_fwhm_y_mm=0.0,
                     detector_fwhm_core_mm=0.1 * 1.5 * 2.3548, detector_fwhm_tail_mm=0.0, detector_weight_core=1.0,
                     shape_power=2.0)
    save_psf(model, tmp_path / "psf.json")
    widget._psf_file.value = tmp_path / "psf.json"
    kernel = widget.kernel()
    assert kernel.sum() == pytest.approx(1.0, abs=1e-4) and kernel.shape[0] % 2 == 1
    widget._method.value = "wiener"
    widget._reg.value = 10.0
    wait_for_worker(widget.run())
    assert _rms(viewer.layers["bars deconvolved"].data, sharp) < _rms(blurred, sharp)


def test_sample_edge_sharpened_with_the_true_psf_file(make_napari_viewer, wait_for_worker, tmp_path):
    """Sample edge (SOD 500 mm) + psf.json of its true blur: the 10-90 % edge rise shrinks."""
    from napari.layers import Layer

    from napari_dslrxr import _sample_data as samples
    from napari_dslrxr.core.psf import PSFModel, save_psf

    def rise_px(image):
        profile = np.asarray(image)[20:108, 30:100].mean(axis=0)
        profile = (profile - profile[:10].mean()) / (profile[-10:].mean() - profile[:10].mean())
        profile = np.maximum.accumulate(profile)  # monotone for the interpolation
        x = np.arange(profile.size)
        return np.interp(0.9, profile, x) - np.interp(0.1, profile, x)

    viewer = make_napari_viewer()
    near, _ = (viewer.add_layer(Layer.create(*t)) for t in samples.make_sample_edges())
    save_psf(PSFModel(**samples.EDGE_TRUTH), tmp_path / "psf.json")
    widget = DeconvolutionWidget(viewer)
    viewer.window.add_dock_widget(widget)
    widget._image.value = near
    widget._psf_file.value = tmp_path / "psf.json"
    widget._sod.value = near.metadata["source_to_object_mm"]
    widget._sdd.value = near.metadata["source_to_detector_mm"]
    assert widget._method.value == "adaptive"
    wait_for_worker(widget.run())
    before, after = rise_px(near.data), rise_px(viewer.layers["edge SOD 500 mm deconvolved"].data)
    assert before > 10.0 and after < 0.5 * before


def test_psf_file_kernel_is_made_off_the_gui_thread(docked, tmp_path, wait_for_worker, monkeypatch, qtbot):
    """A psf.json's kernel (up to a second for a fitted model) is computed in the job's worker,
    for the whole-image run and for the live preview, whose margin follows the kernel's size."""
    import threading

    from napari_dslrxr._widgets import deconvolution as deconvolution_module
    from napari_dslrxr.core.psf import PSFModel, save_psf

    viewer, widget, _sharp, _blurred = docked
    made_on: list[bool] = []
    real_load = deconvolution_module.load_psf

    def recording_load(path):
        made_on.append(threading.current_thread() is threading.main_thread())
        return real_load(path)

    monkeypatch.setattr(deconvolution_module, "load_psf", recording_load)
    model = PSFModel(pixel_pitch_mm=0.1, source_fwhm_x_mm=0.0, source_fwhm_y_mm=0.0,
                     detector_fwhm_core_mm=0.1 * 1.5 * 2.3548, detector_fwhm_tail_mm=0.0, detector_weight_core=1.0,
                     shape_power=2.0)
    save_psf(model, tmp_path / "psf.json")
    widget._kernel_layer.value = None
    widget._psf_file.value = tmp_path / "psf.json"
    widget._method.value = "wiener"
    wait_for_worker(widget.run())
    assert made_on == [False] and "bars deconvolved" in viewer.layers
    widget._sod.value = float(widget._sod.value) + 10.0  # another geometry: another kernel
    widget._live.value = True
    qtbot.waitUntil(lambda: widget.last_preview is not None, timeout=20_000)
    assert made_on == [False, False]
    radius = deconvolution_module.resolve_kernel(widget.kernel_source()).shape[0] // 2
    rows, cols = widget.last_preview["rows"], widget.last_preview["cols"]
    visible_rows, visible_cols = deconvolution_module.visible_region(viewer, widget._image.value)
    assert rows.start == max(visible_rows.start - radius, 0) and cols.stop == min(visible_cols.stop + radius, 224)
