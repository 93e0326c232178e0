"""Display defaults without damage: the anatomy is kept off the display's black and white ends."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from napari_dslrxr.core.stages.dynamic_range import DynamicRangeParams, fit_to_display, lut_input_range, sigmoid_lut
from napari_dslrxr.core.metrics import global_contrast_factor, largest_box
from napari_dslrxr.core.params import PipelineParams, params_from_dict
from napari_dslrxr.core.pipeline import enhance_radiograph


def _clipped(values: np.ndarray) -> float:
    return float(np.mean((values <= 0.5 / 255) | (values >= 254.5 / 255)))


def test_lut_input_range_maps_to_the_clip_levels():
    params = DynamicRangeParams()
    u0, u1 = lut_input_range(params)
    ends = sigmoid_lut(np.array([u0, u1], np.float32), params)
    assert ends[0] == pytest.approx(0.5 / 255, abs=1e-4) and ends[1] == pytest.approx(254.5 / 255, abs=1e-4)
    assert u0 < 0 < 1 < u1


def test_fit_compresses_only_what_would_clip(rng):
    params = DynamicRangeParams()
    inside = rng.uniform(0.1, 0.9, 10000).astype(np.float32)
    untouched = inside.copy()
    assert fit_to_display(untouched, untouched, params) == {"gain": 1.0, "offset": 0.0}
    assert np.array_equal(untouched, inside)  # an image that does not clip keeps its look
    wide = rng.normal(0.5, 0.6, 10000).astype(np.float32)  # far beyond the curve's range
    before = _clipped(sigmoid_lut(wide.copy(), params))
    fit = fit_to_display(wide, wide.copy(), params)
    assert 0 < fit["gain"] < 1 and before > 0.2
    assert _clipped(sigmoid_lut(wide, params)) <= 0.006  # 0.5 % target
    shifted = rng.uniform(0.3, 1.2, 10000).astype(np.float32)  # fits, but off the top end
    fit = fit_to_display(shifted, shifted.copy(), params)
    assert fit["gain"] == 1.0 and fit["offset"] < 0 and _clipped(sigmoid_lut(shifted, params)) <= 0.006


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["RG1_UNCR", "RG3_UNCR"])
def test_real_cr_anatomy_is_not_burned_out(shared_data, name):
    """Chest and leg: anatomy (field, no direct exposure) clipped <= 1 % (was 7.8 % / 0.3 %); GCF over it up."""
    from napari_dslrxr.core.io import read_image
    from napari_dslrxr.core.stages.collimation import detect_collimation

    data = read_image(shared_data / "cr_dicom" / f"{name}.dcm").data.astype(np.float32)
    field = detect_collimation(data, inset_px=10).mask
    lo, hi = np.percentile(data[field], [0.5, 99.5])
    value = (data - lo) / (hi - lo)
    # direct exposure by hand: the darkest histogram mode of the field, up to the valley after it
    hist, edges = np.histogram(value[field], bins=44, range=(-0.05, 1.05))
    smooth = np.convolve(hist, np.ones(3) / 3, mode="same")
    peak = int(np.argmax(smooth[:8]))
    valley = peak + int(np.argmin(smooth[peak:16]))
    direct = float(edges[valley + 1]) if smooth[valley] < 0.35 * smooth[peak] else -1.0
    anatomy = field & (value > direct + 0.03) & (value < 1.02)  # markers are not anatomy
    anatomy = cv2.erode(anatomy.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    out = enhance_radiograph(data, PipelineParams())
    assert _clipped(out[anatomy]) <= 0.01
    rows = np.nonzero(field.any(axis=1))[0]
    lower = anatomy.copy()
    lower[: rows[0] + 2 * (rows[-1] - rows[0]) // 3] = False  # the lower chest burned out most (10 %)
    assert _clipped(out[lower]) <= 0.01
    # GCF over the anatomy alone (the largest box of it: no direct exposure, no markers) rises;
    # on the whole frame the leg's does not (its direct exposure is shown black, docs/safety.md)
    box = largest_box(anatomy, step=4)
    gcf_in, gcf_out = global_contrast_factor(np.clip(value[box], 0, 1)), global_contrast_factor(out[box])
    # measured chest 2.52 -> 3.01, leg 2.97 -> 3.40 (3.55 before its thinnest tissue was lifted off
    # black beside the beam: the toe gives the skin line display range); the value-of-interest
    # window alone gives the leg +13 % (it leaves out the direct exposure), the chest -3 %
    # the issue's +10 % for the leg, whose toe costs it; the chest (no direct exposure, no toe)
    # keeps the stricter +15 % it met before
    assert gcf_out > (1.15 if name == "RG1_UNCR" else 1.1) * gcf_in, (gcf_in, gcf_out)
    if name == "RG1_UNCR":
        assert global_contrast_factor(out) > global_contrast_factor(np.clip(value, 0, 1) * field)


def _chest_like(rng, shape=(240, 300), direct_border_px=30):
    """A body with two lucent lung fields in a direct-exposure surround (attenuation units)."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    image = np.full(shape, 0.05, np.float32)  # direct exposure: the unattenuated level
    body = ((xx - w / 2) / (w / 2 - direct_border_px)) ** 2 + ((yy - h / 2) / (h / 2 - direct_border_px)) ** 2 < 1
    image[body] = 1.2 + 0.3 * np.sin(yy[body] / 7.0)  # soft tissue with rib-like texture
    lungs = np.zeros(shape, bool)
    for cx in (0.35 * w, 0.65 * w):
        lungs |= ((xx - cx) / (0.1 * w)) ** 2 + ((yy - h / 2) / (0.25 * h)) ** 2 < 1
    image[lungs] = 0.25 + 0.1 * np.sin(yy[lungs] / 5.0)  # lucent, but attenuated: not direct exposure
    return image + rng.normal(0, 0.01, shape).astype(np.float32), body, lungs


def test_lungs_are_anatomy_and_the_surround_is_direct_exposure(rng):
    """Direct exposure is the beam that missed the body: outside its outline, connected to the
    frame's edge. Lucent lungs enclosed by the body are anatomy, even near that level."""
    from napari_dslrxr.core.display import anatomy_grid
    from napari_dslrxr.core.stages.region import direct_exposure_mask

    image, body, lungs = _chest_like(rng)
    direct = direct_exposure_mask(image, at_foot=True)
    assert direct is not None
    assert np.mean(direct[~body]) > 0.95  # the surround
    assert not direct[lungs].any()  # the lung fields, enclosed by the body
    step, anatomy = anatomy_grid(image, None, PipelineParams())
    assert step == 1 and anatomy[lungs].all() and anatomy[body].mean() > 0.99
    # lungs as lucent as the open beam: still anatomy while the body encloses them (the rule is
    # spatial, not a level alone), direct exposure once a channel joins one to the frame's edge
    level = image.copy()
    level[lungs] = 0.05 + rng.normal(0, 0.01, int(lungs.sum())).astype(np.float32)
    direct = direct_exposure_mask(level, at_foot=True)
    assert np.mean(direct[~body]) > 0.95 and not direct[lungs].any()
    h, w = image.shape
    level[h // 2 - 4: h // 2 + 4, : int(0.3 * w)] = 0.05  # from the left lung to the left edge
    direct = direct_exposure_mask(level, at_foot=True)
    left_lung = lungs & (np.arange(w) < w // 2)[None, :]
    right_lung = lungs & ~left_lung
    assert direct[left_lung].mean() > 0.9 and not direct[right_lung].any()


def test_a_wide_low_mode_is_not_direct_exposure(rng):
    """Anatomy below a dense uniform area (shielding, undetected blades) makes two histogram
    modes; the low one spreads over the anatomy's range and is not the unattenuated beam."""
    from napari_dslrxr.core.stages.region import direct_exposure_mask

    h, w = 200, 300
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    anatomy = 0.2 + 1.8 * (0.5 + 0.5 * np.sin(xx / 9.0) * np.cos(yy / 13.0))  # spread 0.2-2.0
    image = np.where(xx < 200, anatomy, 4.0).astype(np.float32)  # a third of the frame dense
    image += rng.normal(0, 0.02, image.shape).astype(np.float32)
    assert direct_exposure_mask(image) is None
    assert direct_exposure_mask(image, at_foot=True) is None


def test_self_check_flags_burned_out_and_inverted_anatomy(rng):
    from napari_dslrxr.core.display import display_self_check

    attenuation = rng.uniform(0, 1, 5000).astype(np.float32)
    good = display_self_check(0.1 + 0.8 * attenuation, attenuation, 0.004)
    assert "warning" not in good and good["polarity_evidence"] > 0.99
    inverted = display_self_check(0.9 - 0.8 * attenuation, attenuation, 0.004)
    assert "does not follow its attenuation" in inverted["warning"]
    burned = display_self_check(np.zeros_like(attenuation), attenuation, 1.0)
    assert "100.0 % of the anatomy" in burned["warning"] and burned["polarity_evidence"] == 0.0


def _limb(rng, shape=(200, 300), radius_px=80):
    """A cylinder of soft tissue (a limb seen from the side) in open beam; wider than the frame, it fills it."""
    h, w = shape
    xx = np.arange(w, dtype=np.float32) - w / 2
    chord = 2 * np.sqrt(np.clip(radius_px ** 2 - xx ** 2, 0, None)) / (2 * radius_px)  # 0 at the skin, 1 at the axis
    row = 0.05 + chord ** 2  # attenuation rising linearly from the skin
    image = np.repeat(row[None, :], h, axis=0)
    return image + rng.normal(0, 0.005, shape).astype(np.float32), np.repeat((chord > 0)[None, :], h, axis=0)


def test_thin_tissue_beside_direct_exposure_is_lifted_and_the_beam_stays_black(rng):
    """The skin line shows: the thinnest tissue is grey against a black beam, with no rim at the skin."""
    image, body = _limb(rng)
    out = enhance_radiograph(image, PipelineParams())
    off = enhance_radiograph(image, params_from_dict({"dynamic_range": {"anatomy_floor": 0.0}}))
    depth = cv2.distanceTransform(body.astype(np.uint8), cv2.DIST_L2, 5)
    beam_depth = cv2.distanceTransform((~body).astype(np.uint8), cv2.DIST_L2, 5)
    skin = body & (depth <= 8)
    beam = ~body & (beam_depth > 4)
    assert out[beam].max() <= 0.01  # the open beam stays black
    assert out[skin].mean() >= 0.1, out[skin].mean()  # measured 0.16; without the lift 0.07
    assert off[skin].mean() < 0.09, off[skin].mean()
    # across the skin the display only rises into the body (mean over rows; no dark or bright rim)
    profile = out.mean(axis=0)
    half = profile[: out.shape[1] // 2]
    assert np.all(np.diff(half) >= -2e-3), np.diff(half).min()
    # deep tissue is as it was
    deep = depth > 40
    assert np.abs(out[deep] - off[deep]).max() < 0.02


def test_a_frame_without_direct_exposure_is_unchanged_by_the_foot_lift(rng):
    image, body = _limb(rng, radius_px=220)
    assert body.all()
    out = enhance_radiograph(image, PipelineParams())
    off = enhance_radiograph(image, params_from_dict({"dynamic_range": {"anatomy_floor": 0.0}}))
    assert np.array_equal(out, off)


def test_foot_weight_on_a_coarse_grid_lands_on_its_pixels():
    """The grid weight (statistics grid of step 3) is read at (r / 3, c / 3): in blocks, only where it is."""
    from napari_dslrxr.core.display import apply_anatomy_foot

    grid = np.zeros((40, 50), np.float32)
    grid[10:30, 5:20] = np.linspace(0.2, 1.0, 15, dtype=np.float32)[None, :]  # a body with a ramp across it
    display = np.zeros((120, 150), np.float32)
    apply_anatomy_foot(display, 3, grid, 0.1, rows=7)
    assert np.allclose(display[::3, ::3], 0.1 * grid, atol=1e-6)
    assert display[:, 70:].max() == 0.0 and display[100:].max() == 0.0  # far from the body: untouched
