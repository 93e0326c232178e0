"""The whole chain on synthetic DSLR frames: stages, progress, region, outputs, determinism."""

import json

import cv2
import numpy as np
import pytest

from napari_dslrxr.core.errors import InputError
from napari_dslrxr.core.io import read_image, write_tiff
from napari_dslrxr.core.params import PipelineParams
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph
from napari_dslrxr.core.pipeline import PIPELINE_STAGES, drive, process_frame, run_file, run_pipeline


@pytest.fixture(scope="module")
def frames():
    return make_dslr_radiograph((320, 480), seed=5)


def test_generator_yields_every_stage_and_returns_result(frames):
    gen = run_pipeline(frames.raw_rgb, flats=[frames.flat], darks=[frames.dark], keep_intermediates=True)
    steps = []
    result = drive(gen, lambda *step: steps.append(step))
    n = len(PIPELINE_STAGES)
    assert steps == [(i, n) for i in range(1, n + 1)]
    assert set(result.timings_s) == set(PIPELINE_STAGES)
    assert result.display.shape == frames.raw_rgb.shape[:2] and result.display.dtype == np.float32
    assert 0 <= result.display.min() and result.display.max() <= 1
    assert {"impulse", "flatfield", "attenuation", "dynamic_range", "contrast"} <= set(result.intermediates)
    iou = (result.region.mask & frames.truth.screen_mask).sum() / (result.region.mask | frames.truth.screen_mask).sum()
    assert iou > 0.95


def test_output_shows_object_truth_and_is_bone_white(frames):
    result = process_frame(frames.raw_rgb, flats=[frames.flat], darks=[frames.dark])
    # warp the true attenuation into the frame and compare ranks inside the region
    import cv2

    h, w = frames.raw_rgb.shape[:2]
    mu = cv2.warpPerspective(frames.truth.attenuation, frames.truth.homography, (w, h))
    inside = result.region.mask & (mu > 0.5)  # object (not direct exposure)
    corr = np.corrcoef(mu[inside], result.display[inside])[0, 1]
    assert corr > 0.7  # measured 0.75; more attenuation -> brighter, after all the non-linear stages
    # pulses are gone: no isolated bright outliers at true pulse positions inside the object
    pulses = frames.truth.pulse_mask.any(axis=2) & inside
    smooth = cv2.medianBlur(np.round(result.display * 255).astype(np.uint8), 5).astype(np.float32) / 255
    assert np.median(np.abs(result.display[pulses] - smooth[pulses])) < 0.03


def test_flat_field_stage_matters(frames):
    # without the flat, vignetting + heel leave a large-area trend in the direct-exposure rim
    params = PipelineParams()
    with_flat = process_frame(frames.raw_rgb, flats=[frames.flat], darks=[frames.dark], params=params,
                              keep_intermediates=True).intermediates["attenuation"]
    no_flat = process_frame(frames.raw_rgb, darks=[frames.dark], params=params,
                            keep_intermediates=True).intermediates["attenuation"]
    # spread of the attenuation over the screen rim (uniform direct exposure in truth)
    import cv2

    h, w = frames.raw_rgb.shape[:2]
    mu = cv2.warpPerspective(frames.truth.attenuation, frames.truth.homography, (w, h))
    rim = (mu > 0) & (mu < 0.15) & frames.truth.screen_mask
    rim &= cv2.erode(frames.truth.screen_mask.astype(np.uint8), np.ones((25, 25), np.uint8)).astype(bool)
    assert np.std(with_flat[rim]) < 0.5 * np.std(no_flat[rim])


def test_run_file_writes_outputs_sidecars_and_is_deterministic(tmp_path, frames):
    inputs = tmp_path / "in"
    inputs.mkdir()
    raw = write_tiff(inputs / "shot.tif", frames.raw_rgb)
    flat = write_tiff(inputs / "flat.tif", frames.flat)
    dark = write_tiff(inputs / "dark.tif", frames.dark)
    params = PipelineParams()
    params.output.dicom = True
    outs = []
    for name in ("a", "b"):
        out = tmp_path / name
        out.mkdir()
        written = run_file(raw, out, params=params, flat_paths=[flat], dark_paths=[dark])
        assert sorted(p.name for p in written) == ["shot_dslrxr.dcm", "shot_dslrxr.png", "shot_dslrxr.tif"]
        outs.append(written)
    for a, b in zip(*outs, strict=True):
        assert a.read_bytes() == b.read_bytes()
        side = json.loads(a.with_name(a.name + ".json").read_text())
        assert side["stage"] == "run" and len(side["inputs"]) == 3
        assert set(side["timings_s"]) == set(PIPELINE_STAGES)
        assert side["parameters"]["contrast"]["detail_contrast"] == params.contrast.detail_contrast
    tif = read_image(outs[0][2]).data
    assert tif.dtype == np.uint16 and tif.shape == frames.raw_rgb.shape[:2] and tif.max() > 60000


def test_bad_reference_shape_is_one_line_error(tmp_path, frames):
    raw = write_tiff(tmp_path / "shot.tif", frames.raw_rgb)
    flat = write_tiff(tmp_path / "flat.tif", frames.flat[:100])
    with pytest.raises(InputError, match=r"flat\.tif.*flat frame shape"):  # names the file
        run_file(raw, tmp_path, flat_paths=[flat])


def test_deblur_stage_runs_with_a_kernel(frames):
    small = make_dslr_radiograph((128, 160), seed=1)
    yy, xx = np.mgrid[-4:5, -4:5]
    kernel = np.exp(-(xx**2 + yy**2) / (2 * 1.8**2)).astype(np.float32)
    kernel /= kernel.sum()
    refs = dict(flats=[small.flat], darks=[small.dark], keep_intermediates=True)
    result = process_frame(small.raw_rgb, psf_kernel=kernel, **refs)
    assert isinstance(result.results["deblur"], dict) and result.timings_s["deblur"] > 0
    assert np.isfinite(result.display).all()
    # deblurring sharpens: more gradient energy in the attenuation image inside the region,
    # away from the screen's rim (6 px), whose step dominated an earlier, looser region
    plain = process_frame(small.raw_rgb, **refs)
    interior = cv2.erode((result.region.mask & plain.region.mask).astype(np.uint8), np.ones((13, 13), np.uint8))
    inside = interior.astype(bool)[1:, 1:]

    def gradient_energy(att):
        return float((np.square(np.diff(att, axis=0)[:, 1:]) + np.square(np.diff(att, axis=1)[1:, :]))[inside].mean())

    # 1.15x measured (with the noise-capped automatic regularisation; no deblurring gives 1.0)
    assert gradient_energy(result.intermediates["attenuation"]) > 1.1 * gradient_energy(plain.intermediates["attenuation"])
    # the recorded auto value is the one the solver used: passing it back reproduces the run
    params = PipelineParams()
    params.deblur.reg = result.results["deblur"]["reg_used"]
    again = process_frame(small.raw_rgb, psf_kernel=kernel, params=params, **refs)
    assert np.array_equal(again.display, result.display)


def test_camera_raw_input_cleans_pulses_on_the_cfa_planes(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from robustness.synthetic_files import write_dng

    small = make_dslr_radiograph((192, 256), seed=7, pulse_rate=0.0)
    green = small.raw_rgb[..., 1].astype(np.float64) - small.black_level
    mosaic = np.clip(green / 4 + 64, 0, 4095).astype(np.uint16)  # 12-bit RGGB-like mosaic
    rng = np.random.default_rng(0)
    rows, cols = rng.integers(4, 188, 60), rng.integers(4, 252, 60)
    mosaic[rows, cols] = 4000  # zingers
    path = write_dng(tmp_path / "shot.dng", mosaic, black_counts=64, white_counts=4095)
    written = run_file(path, tmp_path)
    side = json.loads(written[0].with_name(written[0].name + ".json").read_text())
    assert side["results"]["impulse"]["space"] == "cfa"
    assert sum(side["results"]["impulse"]["pulse_pixels"].values()) >= 40


def test_batch_prepares_the_flat_reference_once(tmp_path, frames):
    shot = write_tiff(tmp_path / "shot.tif", frames.raw_rgb)
    refs = dict(flat_paths=[write_tiff(tmp_path / "flat.tif", frames.flat)],
                dark_paths=[write_tiff(tmp_path / "dark.tif", frames.dark)])
    for name in ("a", "b", "plain"):
        (tmp_path / name).mkdir()
    cache: dict = {}
    run_file(shot, tmp_path / "a", reference_cache=cache, **refs)
    (prepared,) = cache.values()
    reused = run_file(shot, tmp_path / "b", reference_cache=cache, **refs)
    assert len(cache) == 1 and next(iter(cache.values())) is prepared
    plain = run_file(shot, tmp_path / "plain", **refs)
    assert reused[0].read_bytes() == plain[0].read_bytes()  # same output as preparing it afresh


def test_contrast_widget_and_core_share_the_display_stages(frames):
    """The widget's render, the pipeline's stages v-vi and enhance_radiograph give the same bytes."""
    import dataclasses

    pytest.importorskip("magicgui")
    from napari_dslrxr._widgets.contrast import DISPLAY, LINEAR, PreparedInput, render
    from napari_dslrxr.core.pipeline import apply_display_stages, enhance_radiograph

    params = PipelineParams()  # off-default sliders and a white outside, so every field is used
    params.region = dataclasses.replace(params.region, rectify=False)
    params.dynamic_range = dataclasses.replace(params.dynamic_range, latitude=0.4, detail_gain=1.8,
                                               lut_width=0.3)
    params.contrast = dataclasses.replace(params.contrast, bone_contrast=1.7, detail_contrast=0.6)
    params.output = dataclasses.replace(params.output, outside_region="white")
    result = process_frame(frames.raw_rgb, flats=[frames.flat], darks=[frames.dark], params=params,
                           keep_intermediates=True)
    attenuation, mask = result.intermediates["attenuation"], result.region.mask
    assert 0.05 < (~mask).mean() < 0.9  # the outside fill is exercised

    # linear path: widget on the pipeline's VOI-scaled attenuation == the pipeline's display
    prepared = PreparedInput(attenuation, mask, attenuation, mask, 1.0)
    _, widget_display, _ = render(prepared, frames.raw_rgb, LINEAR, params, attenuation.size, True)
    core_display = apply_display_stages(attenuation, mask, params)
    assert widget_display.dtype == np.float32 and widget_display.shape == mask.shape
    np.testing.assert_array_equal(widget_display, result.display)
    np.testing.assert_array_equal(core_display, result.display)
    assert np.all(result.display[~mask] == 1.0) and result.display[mask].std() > 0.05

    # display-radiograph path: widget (its own VOI scaling) == enhance_radiograph
    grey = frames.raw_rgb.mean(axis=2).astype(np.float32)
    _, widget_grey, _ = render(None, grey, DISPLAY, params, grey.size, True)
    np.testing.assert_array_equal(widget_grey, enhance_radiograph(grey, params))
