"""Impulse removal on synthetic data with known pulses (ground truth), against median filters."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage as ndi

from napari_dslrxr.core.errors import InputError, ParameterError
from napari_dslrxr.core.stages.impulse import (
    ImpulseParams,
    hsv_counts_to_rgb,
    remove_impulses,
    remove_impulses_cfa,
    rgb_to_hsv_counts,
)


def smooth_scene(shape=(256, 256), low=300.0, high=3000.0, blur_px=2.0) -> np.ndarray:
    """Radiograph-like smooth content in expected counts: a blob, a step, a gradient."""
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    scene = (low + (high - low) * 0.6 * np.exp(-((yy - 0.4 * h) ** 2 + (xx - 0.6 * w) ** 2) / (2 * (0.15 * h) ** 2))
             + 0.25 * (high - low) * (xx > 0.5 * w) + 0.15 * (high - low) * yy / h)
    return ndi.gaussian_filter(scene, blur_px)


def add_patches(image: np.ndarray, rng, count: int, amp_range, sizes=(1, 2, 3, 4)):
    """Add bright square patches (side from ``sizes``) at random places; return image, truth."""
    out = image.astype(np.float64).copy()
    truth = np.zeros(image.shape[:2], bool)
    h, w = truth.shape
    for _ in range(count):
        side = int(rng.choice(sizes))
        r, c = rng.integers(4, h - 4 - side), rng.integers(4, w - 4 - side)
        out[r:r + side, c:c + side] += rng.uniform(*amp_range)
        truth[r:r + side, c:c + side] = True
    return out, truth


def poisson_image(expected_counts: np.ndarray, gain: float, rng) -> np.ndarray:
    return gain * rng.poisson(expected_counts / gain).astype(np.float64)


def recall_precision(mask: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    hit = np.count_nonzero(mask & truth)
    return hit / max(np.count_nonzero(truth), 1), hit / max(np.count_nonzero(mask), 1)


def pe(reference, estimate):
    reference = np.asarray(reference, np.float64)
    return 100 * np.linalg.norm(reference - estimate) / np.linalg.norm(reference)


# --------------------------------------------------------------------------- grey


def test_grey_patches_found_replaced_and_better_than_medians(rng):
    import cv2

    clean = smooth_scene()
    noisy = poisson_image(clean, 2.0, rng)
    # Visible pulses: at least 8 sigma of the brightest area's noise.
    dirty, truth = add_patches(noisy, rng, 120, (8 * np.sqrt(2 * 3000), 6000))
    image = np.clip(np.rint(dirty), 0, 65535).astype(np.uint16)
    result = remove_impulses(image)
    mask = result.masks["grey"]
    recall, precision = recall_precision(mask, truth)
    assert recall >= 0.97 and precision >= 0.95, (recall, precision)
    assert result.image.dtype == np.uint16 and result.image.shape == image.shape
    # Switching: every pixel outside the mask is bit-identical.
    assert np.array_equal(result.image[~mask], image[~mask])
    assert np.array_equal(result.any_mask(), mask)
    # Closer to the clean scene than the input and than 3x3 / 5x5 medians.
    ours = pe(clean, result.image)
    assert ours < 0.5 * pe(clean, image)
    for size in (3, 5):
        assert ours < pe(clean, cv2.medianBlur(image, size))
    # Pulses are gone: no truth pixel stays more than 5 sigma above the clean scene.
    residual = (result.image.astype(np.float64) - clean) / np.sqrt(2.0 * clean)
    assert np.count_nonzero(residual[truth] > 5) <= 0.01 * truth.sum()


def _faint_pulses(light: np.ndarray, rng, count: int, sigmas: float):
    """Flat 3x3 blobs and 2 px wide, 9 px long horizontal tracks, ``sigmas`` noise sigmas
    above the local light in every pixel, on a spaced grid; returns (dirty counts, truth)."""
    noisy = rng.poisson(light).astype(np.float64)
    truth = np.zeros(light.shape, bool)
    h, w = light.shape
    centres = [(r, c) for r in range(12, h - 12, 24) for c in range(12, w - 12, 24)]
    for k, idx in enumerate(rng.permutation(len(centres))[:count]):
        r, c = centres[idx]
        patch = (slice(r - 1, r + 2), slice(c - 1, c + 2)) if k % 2 else (slice(r, r + 2), slice(c - 4, c + 5))
        noisy[patch] += sigmas * np.sqrt(light[patch])
        truth[patch] = True
    return noisy, truth


def test_faint_blobs_and_tracks_are_found_by_their_footprint(rng):
    """Blobs and wide tracks 3.5 noise sigmas high in each pixel: no pixel stands out alone
    (the stage before its footprint test found 0.16 of such pixels), the mean over the
    footprint does (3x3: 10 sigmas; 0.71 found). A pulse-free frame of the same light stays
    untouched."""
    light = smooth_scene((256, 256), low=300, high=1500)
    dirty, truth = _faint_pulses(light, rng, 60, 3.5)
    result = remove_impulses(dirty.astype(np.float32))
    recall, precision = recall_precision(result.masks["grey"], truth)
    assert recall > 0.5, recall
    assert precision > 0.9, precision
    clean = remove_impulses(rng.poisson(light).astype(np.float32))
    assert clean.masks["grey"].mean() < 2e-4


def test_rims_of_strong_blobs_on_ramps_are_found(rng):
    """Gaussian blobs (sigma 0.9 px) 8-16 noise sigmas high on steep ramps: their 3-5 sigma
    rims are found (the growth's old structure guard took the ramp for structure: 0.71-0.76
    found), the noise pixels around them are hardly touched, and nothing far from them."""
    h, w = 256, 256
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    light = 400.0 + 2400.0 * xx / w + 300.0 * np.sin(yy / 23.0)
    excess = np.zeros((h, w))
    for k in range(60):
        r, c = 8 + 20 * (k // 12) + rng.uniform(0, 6), 8 + 20 * (k % 12) + rng.uniform(0, 6)
        excess += rng.uniform(8, 16) * np.exp(-((yy - r) ** 2 + (xx - c) ** 2) / (2 * 0.9 ** 2))
    dirty = rng.poisson(light) + excess * np.sqrt(light)
    mask = remove_impulses(dirty.astype(np.float32)).masks["grey"]
    rim = (excess >= 3) & (excess < 5)
    assert mask[rim].mean() > 0.82, mask[rim].mean()
    assert mask[excess >= 5].mean() > 0.98
    near = ndi.binary_dilation(excess >= 0.05, iterations=1)
    assert np.count_nonzero(mask & near & (excess < 1)) < 20
    assert np.count_nonzero(mask & ~near) <= 3


def test_spread_about_a_plane_ignores_a_ramp(rng):
    """The rim guard's spread about the window's plane is the noise on a ramp, where the
    spread about the median is the ramp's; curvature (a bump) still spreads about a plane."""
    from napari_dslrxr.core.stages.impulse.neighbourhoods import _masked_median_at

    yy, xx = np.mgrid[:64, :64].astype(np.float64)
    excluded = np.zeros((64, 64), np.uint8)
    excluded[31:34, 30:35] = 1  # a patch and its ring, as in the growth
    rows, cols = np.array([32]), np.array([31])
    for name, surface, lo, hi in (("ramp", 1000 + 40 * xx + 25 * yy, 0.7, 1.4),
                                   ("bump", 1000 + 400 * np.exp(-((yy - 32) ** 2 + (xx - 32) ** 2) / 8.0), 3, None)):
        spreads = []
        for _ in range(40):
            image = (surface + rng.normal(0, 10, surface.shape)).astype(np.float32)
            _, plane = _masked_median_at(image, excluded, rows, cols, smallest_px=7, symmetric=True,
                                         with_spread=True, spread_about="plane")
            _, median = _masked_median_at(image, excluded, rows, cols, smallest_px=7, symmetric=True,
                                          with_spread=True)
            spreads.append((plane[0] / 10, median[0] / 10))
        plane_sigmas, median_sigmas = np.median(spreads, axis=0)
        assert plane_sigmas > lo, (name, plane_sigmas)
        if hi is not None:
            assert plane_sigmas < hi < median_sigmas, (name, plane_sigmas, median_sigmas)


def test_gain_and_pulse_rate_estimated_within_ten_percent(rng):
    clean = smooth_scene((384, 384), low=200, high=4000)
    for gain in (0.5, 4.0):
        noisy = poisson_image(clean, gain, rng)
        dirty = noisy.copy()
        n = int(0.002 * noisy.size)
        flat = rng.choice(noisy.size, n, replace=False)
        dirty.flat[flat] += rng.uniform(0, 20000, n)  # uniform, bright-only pulses (the model)
        result = remove_impulses(dirty.astype(np.float32))
        assert abs(result.gain["grey"] / gain - 1) < 0.10, result.gain
        assert abs(result.pulse_rate["grey"] / 0.002 - 1) < 0.25, result.pulse_rate


def _pulse_free_camera_frame(rng, tint, black_dn, gain, light):
    """Poisson electrons times ``gain`` DN plus 3 DN read noise over a black level, clipped to
    14 bits. ``light``: "uniform", "vignetted" (1 at the centre, 0.4 in the corners) or
    "ramp" (0.1 to 1 across the frame)."""
    h, w = (256, 320) if light == "ramp" else (160, 192)
    yy, xx = np.mgrid[0:h, 0:w]
    pattern = {"uniform": np.ones((h, w)),
               "vignetted": 1.0 - 0.6 * ((yy - h / 2) ** 2 + (xx - w / 2) ** 2) / ((h / 2) ** 2 + (w / 2) ** 2),
               "ramp": 0.1 + 0.9 * xx / (w - 1)}[light]
    electrons = (3000.0 / gain) * pattern[..., None] * np.asarray(tint)
    dn = black_dn + gain * rng.poisson(electrons) + rng.normal(0.0, 3.0, electrons.shape)
    frame = np.clip(dn, 0, 16383).astype(np.float32)
    return frame[..., 0] if len(tint) == 1 else frame


@pytest.mark.parametrize("tint", [(1.0,), (1.0, 1.0, 1.0), (0.30, 1.0, 0.35)], ids=["grey", "grey_rgb", "green"])
def test_pulse_free_frames_over_a_black_level_are_not_flagged_and_gain_is_right(rng, tint):
    """A black level (offset) must not bias the noise law, and V = max(R, G, B) of a grey
    frame (a residual about half as wide in variance as one channel's, with one channel's
    tail three times over) must neither flag its own noise nor report that narrower noise
    as the gain (0.54 of the truth before). The gain is checked where it is identifiable: a
    uniform frame has one level, and a vignetted one (0.4-1) too narrow a range of levels
    for the slope of the variance law (estimates 0.7-1.15 of the truth)."""
    key = "grey" if len(tint) == 1 else "V"
    for black_dn in (0.0, 512.0, 1024.0):
        for gain in (0.5, 1.0, 4.0):
            for light in ("uniform", "vignetted", "ramp"):
                result = remove_impulses(_pulse_free_camera_frame(rng, tint, black_dn, gain, light))
                case = (tint, black_dn, gain, light, result.gain[key])
                if light == "ramp":
                    # The hue of a grey frame's dim end (75-300 electrons at gain 4) is
                    # noise that the H pass flags at 0.05-0.13 %: open, V is checked here.
                    assert result.masks[key].mean() < 5e-4, case
                    assert abs(result.gain[key] / gain - 1) < 0.10, case
                else:
                    assert result.any_mask().mean() < 5e-4, case


def test_clean_image_is_left_almost_untouched(rng):
    image = poisson_image(smooth_scene(), 2.0, rng).astype(np.float32)
    result = remove_impulses(image)
    assert result.masks["grey"].mean() < 2e-3
    assert pe(image, result.image) < 0.05


def test_float64_and_uint8_keep_dtype_and_untouched_bits(rng):
    clean = smooth_scene(low=20, high=200)
    dirty, truth = add_patches(poisson_image(clean, 0.5, rng), rng, 40, (60, 120), sizes=(1, 2))
    for image in (dirty.astype(np.float64), np.clip(np.rint(dirty), 0, 255).astype(np.uint8)):
        result = remove_impulses(image)
        assert result.image.dtype == image.dtype
        mask = result.masks["grey"]
        assert np.array_equal(result.image[~mask], image[~mask])
        assert recall_precision(mask, truth)[0] > 0.9


def test_bad_input_and_parameters():
    with pytest.raises(InputError):
        remove_impulses(np.full((32, 32), np.nan, np.float32))
    with pytest.raises(InputError):
        remove_impulses(np.zeros((4, 4), np.uint16))
    with pytest.raises(ParameterError):
        remove_impulses(np.zeros((32, 32), np.uint16), space="hsv")
    with pytest.raises(ParameterError):
        remove_impulses(np.zeros((32, 32), np.uint16), space="lab")
    for bad in ({"passes_h": -1}, {"passes_v": 11}, {"window_px": 4}, {"posterior_threshold": 1.0},
                {"min_saturation": 2.0}, {"passes_grey": 1.5}, {"em_samples": 10}):
        with pytest.raises(ParameterError):
            ImpulseParams(**bad)
    with pytest.raises(ParameterError, match="spots"):
        ImpulseParams(spots="grey")
    # The TOML section: unknown keys and bad polarities are one-line errors naming the key.
    from napari_dslrxr.core.params import params_from_dict

    with pytest.raises(ParameterError, match="passes_x"):
        params_from_dict({"impulse": {"passes_x": 1}})
    with pytest.raises(ParameterError, match="impulse.spots"):
        params_from_dict({"impulse": {"spots": "both_ways"}})
    assert params_from_dict({"impulse": {"passes_h": 2, "spots": "dark"}}).impulse.spots == "dark"


def grating(shape, period_px, angle_deg, phase=0.0, modulation=0.6):
    """1 + m cos(2 pi (x cos a + y sin a) / P + phase): a line pattern."""
    yy, xx = np.mgrid[:shape[0], :shape[1]].astype(np.float64)
    a = np.radians(angle_deg)
    return 1.0 + modulation * np.cos(2 * np.pi * (xx * np.cos(a) + yy * np.sin(a)) / period_px + phase)


@pytest.mark.parametrize("kind, period_px, angle_deg", [
    ("lines", 2.2, 0.0), ("lines", 3.3, 37.0), ("lines", 5.3, 90.0), ("lines", 4.4, 121.0),
    ("mesh", 3.0, 20.0), ("mesh", 4.6, 45.0),
])
def test_fine_texture_without_pulses_is_not_touched(rng, kind, period_px, angle_deg):
    """A line-pair target or grid (60 % modulation) inside a smooth radiograph: pulse-free, so
    at most 0.05 % of its pixels may be flagged (the first version flagged 2-40 % of such
    patterns)."""
    light = smooth_scene((256, 256), low=400, high=2500)
    pattern = grating((128, 128), period_px, angle_deg, phase=rng.uniform(0, 6.3))
    if kind == "mesh":
        pattern = pattern * grating((128, 128), period_px * 1.1, angle_deg + 90, phase=rng.uniform(0, 6.3))
    patch = (slice(64, 192), slice(64, 192))
    light[patch] *= pattern / pattern.mean()
    image = np.clip(np.rint(poisson_image(light, 1.0, rng)), 0, 65535).astype(np.uint16)
    result = remove_impulses(image)
    # Inside the pattern (its abrupt border, where lines end like tracks, is not counted).
    inside = (slice(70, 186), slice(70, 186))
    assert result.masks["grey"][inside].mean() <= 0.0005, result.masks["grey"][inside].mean()
    assert result.masks["grey"][patch].mean() <= 0.002
    # The same texture with strong pulses on it: most are still found (the guard gives up
    # some recall on texture; see docs/impulse.md).
    dirty, truth = add_patches(image, rng, 40, (6000, 12000), sizes=(1, 2, 3))
    found = remove_impulses(np.clip(dirty, 0, 65535).astype(np.uint16)).masks["grey"]
    assert np.count_nonzero(found & truth) >= 0.6 * truth.sum()


def _line_patch_flagged(period_px, angle_deg, low, high) -> list[float]:
    """Share of a 128 px line-pattern patch flagged (grey) inside a smooth radiograph, for
    three seeds (camera gain 1.5, read noise 2.5 counts)."""
    flagged = []
    for seed in (1, 2, 3):
        rng = np.random.default_rng([seed, 31])
        light = smooth_scene((256, 256), low=low, high=high)
        patch = (slice(64, 192), slice(64, 192))
        pattern = grating((128, 128), period_px, angle_deg, phase=rng.uniform(0, 6.3))
        light[patch] *= pattern / pattern.mean()
        counts = 1.5 * rng.poisson(light / 1.5) + rng.normal(0.0, 2.5, light.shape)
        image = np.clip(np.rint(counts), 0, 65535).astype(np.uint16)
        flagged.append(float(remove_impulses(image).masks["grey"][patch].mean()))
    return flagged


@pytest.mark.parametrize("period_px, angle_deg, low, high", [(2.6, 178.0, 800.0, 4000.0), (2.7, 3.0, 500.0, 2500.0),
                                                             (5.0, 1.0, 400.0, 2500.0)])
def test_border_of_a_near_axis_line_pattern_is_not_taken_for_tracks(period_px, angle_deg, low, high):
    """Lines within a few degrees of the columns, inside a smooth radiograph, the whole patch
    counted, its border too (camera gain 1.5, read noise 2.5 counts): the border column is a
    bright line segment against the unpatterned side, which only one side of the texture
    guard's annulus sees. Before the grey path took the annulus's sides, 0.03-0.78 % of these
    patches were flagged along their first and last columns."""
    flagged = _line_patch_flagged(period_px, angle_deg, low, high)
    assert max(flagged) <= 0.0005, flagged


@pytest.mark.parametrize("period_px, angle_deg", [(2.46, 95.0), (2.3, 2.0), (2.2, 90.0)])
def test_border_of_a_pattern_matched_by_the_sparse_median_is_not_taken_for_tracks(period_px, angle_deg):
    """Near-axis lines of 2.2-2.5 px period: the detection median's samples, 2 px apart, nearly
    match the pattern, so its residual inside is small and only the image's own curvature shows
    the texture beside the border line (0.26-1.6 % of such patches were flagged before the
    curved-side test; now at most 0.08 %, above the 0.05 % target on some seeds)."""
    flagged = _line_patch_flagged(period_px, angle_deg, 400.0, 2500.0)
    assert max(flagged) <= 0.001, flagged


#: Flagged share allowed on a frame filled with a mesh, per path. The target is 0.05 %; the
#: CFA planes do not reach it everywhere yet (measured on these three meshes: 0-0.15 %; HSV
#: 0-0.002 %, 0.03-0.10 % before its S and H weights took the lower of V's median and own
#: value); before the noise fit was checked against a predictor's residual, up to 42 %
#: (grey, HSV) and 56 % (CFA) of such frames were flagged.
_FULL_MESH_LIMIT = {"grey": 0.0005, "hsv": 0.0005, "cfa": 0.002}


@pytest.mark.parametrize("period_px, period2_px, angle_deg", [(5.25, 4.09, 78.0), (2.72, 4.52, 74.0),
                                                             (3.49, 3.26, 97.0)])
def test_frame_filled_with_a_mesh_is_not_touched(period_px, period2_px, angle_deg):
    """No flat area to fit the noise on: a mesh (60 % modulation) over the whole frame, grey,
    tinted RGB (HSV path) and the CFA planes of its Bayer mosaic; then strong pulses on the
    grey frame are still found."""
    rng = np.random.default_rng(20261122)
    pattern = (grating((256, 256), period_px, angle_deg, rng.uniform(0, 6.3))
               * grating((256, 256), period2_px, angle_deg + 90, rng.uniform(0, 6.3)))
    light = 1500.0 * pattern / pattern.max()
    tint = np.array([0.35, 1.0, 0.15])
    grey = np.clip(np.rint(poisson_image(light, 1.0, rng)), 0, 65535).astype(np.uint16)
    rgb = np.clip(np.rint(poisson_image(light[..., None] * tint, 1.0, rng)), 0, 65535).astype(np.uint16)
    scene = poisson_image(light[..., None] * tint, 1.0, rng)
    planes = np.stack([scene[0::2, 0::2, 0], scene[0::2, 1::2, 1], scene[1::2, 0::2, 1],
                       scene[1::2, 1::2, 2]]).astype(np.float32)
    flagged = {"grey": remove_impulses(grey).any_mask().mean(), "hsv": remove_impulses(rgb).any_mask().mean(),
               "cfa": remove_impulses_cfa(planes).any_mask().mean()}
    for path, limit in _FULL_MESH_LIMIT.items():
        assert flagged[path] <= limit, (path, flagged)
    dirty, truth = add_patches(grey, rng, 40, (6000, 12000), sizes=(1, 2, 3))
    found = remove_impulses(np.clip(dirty, 0, 65535).astype(np.uint16)).masks["grey"]
    recall, precision = recall_precision(found, truth)
    assert recall >= 0.95 and precision >= 0.95, (recall, precision)


@pytest.mark.parametrize("periods_px, angle_deg, level, tint, gain, read_noise", [
    ((3.1, 4.3), 108.0, 700.0, (0.35, 1.0, 0.15), 1.0, 3.0),
    ((3.0, 3.3), 30.0, 900.0, (1.0, 0.7, 0.2), 2.0, 2.5),
    ((3.4, 2.7), 10.0, 600.0, (0.5, 1.0, 0.1), 1.5, 2.0),
])
def test_dim_tinted_frame_filled_with_a_mesh_is_not_touched_in_hsv(periods_px, angle_deg, level, tint, gain,
                                                                    read_noise):
    """Other tints, gains and read noise than the pulse evaluation's: at a mesh's dark nodes
    the dim channels hold a few counts, and S and H weights taken from V's 3x3 median (set by
    the brighter neighbours) flagged 0.2-0.8 % of these frames, all of it texture."""
    rng = np.random.default_rng([20261203, int(level)])
    pattern = (grating((256, 256), periods_px[0], angle_deg, rng.uniform(0, 6.3))
               * grating((256, 256), periods_px[1], angle_deg + 90, rng.uniform(0, 6.3)))
    light = level * pattern[..., None] / pattern.max() * np.asarray(tint)
    counts = gain * rng.poisson(light / gain) + rng.normal(0.0, read_noise, light.shape)
    rgb = np.clip(np.rint(counts), 0, 65535).astype(np.uint16)
    result = remove_impulses(rgb)
    flagged = {name: float(mask.mean()) for name, mask in result.masks.items()}
    assert result.any_mask().mean() <= 0.0005, flagged


@pytest.mark.parametrize("spots", ["dark", "both"])
def test_dark_clusters_are_filled_from_outside(rng, spots):
    """Dark clusters of 2-6 px (a hit turned dark by normalisation): every pixel found and
    filled with background values, not with the cluster's own; bright pulses are left to
    the "both" mode only."""
    clean = smooth_scene((192, 192))
    noisy = poisson_image(clean, 1.0, rng)
    truth = np.zeros(noisy.shape, bool)
    for _ in range(40):
        r, c = rng.integers(8, 180, 2)
        cells = [(r, c)]
        for _ in range(int(rng.integers(1, 6))):
            dr, dc = [(0, 1), (1, 0), (1, 1), (0, -1)][int(rng.integers(0, 4))]
            cells.append((cells[-1][0] + dr, cells[-1][1] + dc))
        for cr, cc in cells:
            truth[cr, cc] = True
    dirty = noisy.copy()
    dirty[truth] *= 0.2
    bright = np.zeros(noisy.shape, bool)
    bright[rng.integers(8, 184, 30), rng.integers(8, 184, 30)] = True
    bright &= ~ndi.binary_dilation(truth, iterations=3)
    dirty[bright] += 3000
    image = np.clip(np.rint(dirty), 0, 65535).astype(np.uint16)
    result = remove_impulses(image, ImpulseParams(spots=spots))
    mask = result.masks["grey"]
    assert np.count_nonzero(mask & truth) >= 0.97 * truth.sum()
    # Filled with the background: within 4 sigma of the clean scene, not pulled down by
    # the cluster.
    z = (result.image[truth].astype(np.float64) - clean[truth]) / np.sqrt(clean[truth])
    assert np.mean(np.abs(z) < 4) >= 0.97 and abs(np.median(z)) < 1.0
    if spots == "dark":
        assert not np.any(mask & bright)
    else:
        assert np.count_nonzero(mask & bright) == bright.sum()


# --------------------------------------------------------------------------- colour


def test_hsv_roundtrip_is_exact_enough(rng):
    rgb = rng.uniform(0, 60000, (64, 64, 3))
    h, s, v = rgb_to_hsv_counts(rgb)
    back = hsv_counts_to_rgb(h, s, v)
    assert np.max(np.abs(back - rgb)) < 0.2  # counts; float32 hue/saturation round-off (measured 0.03)


def test_weight_model_drops_a_variance_line_that_is_zero_above_the_darkest_counts():
    """The S and H weights use V's count-variance line only where it is credible: a line
    reaching zero at a camera's offset (a black level of 512 under a dark surround) is kept;
    one reaching zero at 316 counts on a frame whose darkest pixels hold 95 (V's fit on a
    frame filled with a mesh) is replaced by plain Poisson."""
    from napari_dslrxr.core.stages.impulse.colour import _weight_model
    from napari_dslrxr.core.stages.impulse.noise_model import _NoiseModel

    rng = np.random.default_rng(3)
    surround = 512.0 + np.abs(rng.normal(0.0, 3.0, (200, 3))).max(axis=1)  # V = max of 3 channels
    screen = 512.0 + rng.poisson(2000.0, 2000)
    v_black = np.concatenate([surround, screen]).astype(np.float32).reshape(44, 50)
    offset_line = _NoiseModel(a=1.17, b=-1.17 * 512 + 10.5, pulse_rate=1e-3, pulse_density=1e-4,
                              polarity=1, var_floor=10.5)
    assert _weight_model(offset_line, v_black) is offset_line
    v_mesh = rng.uniform(95.0, 1524.0, (64, 64)).astype(np.float32)
    mesh_line = _NoiseModel(a=4.3, b=-1357.6, pulse_rate=1e-3, pulse_density=1e-4, polarity=1, var_floor=32.9)
    assert _weight_model(mesh_line, v_mesh) is None
    positive = _NoiseModel(a=1.0, b=20.0, pulse_rate=1e-3, pulse_density=1e-4, polarity=1, var_floor=9.0)
    assert _weight_model(positive, v_mesh) is positive
    assert _weight_model(None, v_mesh) is None


def test_hue_wraparound_is_not_smeared(rng):
    """Constant hue 0.99 with hue pulses at 0.01: pulses found, replaced by hue near 0.99."""
    shape = (128, 128)
    value = poisson_image(np.full(shape, 3000.0), 1.0, rng)
    hue = np.full(shape, 0.99) + rng.normal(0, 0.002, shape)
    truth = np.zeros(shape, bool)
    for _ in range(30):
        r, c = rng.integers(4, 120, 2)
        side = int(rng.integers(1, 3))
        hue[r:r + side, c:c + side] = 0.01
        truth[r:r + side, c:c + side] = True
    hue %= 1.0
    rgb = np.clip(np.rint(hsv_counts_to_rgb(hue, np.full(shape, 0.6), value)), 0, 65535).astype(np.uint16)
    result = remove_impulses(rgb)
    mask_h = result.masks["H"]
    recall, precision = recall_precision(mask_h, truth)
    assert recall > 0.97 and precision > 0.9, (recall, precision)
    new_hue, _, _ = rgb_to_hsv_counts(result.image)
    circular = np.abs((new_hue - 0.99 + 0.5) % 1.0 - 0.5)
    assert circular.max() < 0.03  # nothing dragged towards 0.5 (the linear mean of 0.99 and 0.01)
    unchanged = ~result.any_mask()
    assert np.array_equal(result.image[unchanged], rgb[unchanged])
    assert np.isnan(result.gain["H"]) and np.isnan(result.gain["S"]) and np.isfinite(result.gain["V"])


def _phantom_channel_truth(frames, pulse_free, visible_sigma=5.0):
    """Pulse truth per H, S, V channel of a DSLR phantom frame.

    The phantom injects pulses into R, G and B (``truth.pulse_mask``, multi-pixel patches);
    each changes H, S and V by different amounts. A pulse pixel is in channel X's truth
    where the pulse moved X by more than ``visible_sigma`` times X's local noise, the noise
    measured between the pulse-free noisy frame (same seed, no pulses) and the noise-free
    expected image (1.4826 x the 5x5 median absolute difference; hue circular).
    """
    import cv2

    def circular(a):
        return np.abs((a + 0.5) % 1.0 - 0.5)

    dirty = rgb_to_hsv_counts(frames.raw_rgb)
    free = rgb_to_hsv_counts(pulse_free.raw_rgb)
    expected = rgb_to_hsv_counts(frames.truth.clean_rgb + frames.black_level)
    injected = frames.truth.pulse_mask.any(axis=2)
    truth = {}
    for i, name in enumerate("HSV"):
        diff = circular if name == "H" else np.abs
        noise = 1.4826 * cv2.medianBlur(diff(free[i] - expected[i]).astype(np.float32), 5)
        truth[name] = injected & (diff(dirty[i] - free[i]) > visible_sigma * noise)
    return injected, truth


def test_dslr_phantom_pulses_per_channel_on_screen_and_in_the_dark():
    """The napari sample frame: per-channel precision and recall against the phantom's truth.

    Before the fixes of the read-noise floor, the count-based S/H noise weights and the
    structure guards, HSV filtering flagged about 1,300 non-pulse pixels on the screen and
    1,800 in the dark surround (precision 0.27 to 0.6 for S and V).
    """
    from scipy import ndimage as ndi

    from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph

    shape, seed = (480, 720), 0  # napari_dslrxr._sample_data: PHANTOM_SHAPE, PHANTOM_SEED
    frames = make_dslr_radiograph(shape, seed=seed)
    injected, truth = _phantom_channel_truth(frames, make_dslr_radiograph(shape, seed=seed, pulse_rate=0.0))
    screen = frames.truth.screen_mask
    # The blurred screen edge (3 blur sigmas) is neither screen nor dark surround.
    dark = ndi.distance_transform_edt(~screen) > 3 * frames.truth.blur_sigma_px
    result = remove_impulses(frames.raw_rgb, space="hsv")
    for name in "HSV":
        mask = result.masks[name]
        for region_name, region in (("screen", screen), ("outside", ~screen)):
            flagged = mask & region
            precision = np.count_nonzero(flagged & injected) / max(np.count_nonzero(flagged), 1)
            assert precision >= 0.95, (name, region_name, precision)
        # Hue is undefined in the dark surround (left out of hue filtering by design): its
        # pulses are S and V pulses there.
        for region_name, region in (("screen", screen), ("dark", dark))[: 1 if name == "H" else 2]:
            true = truth[name] & region
            recall = np.count_nonzero(mask & true) / np.count_nonzero(true)
            assert recall >= 0.95, (name, region_name, recall)
    found = result.any_mask()
    assert np.count_nonzero(found & injected) >= 0.98 * np.count_nonzero(injected)
    assert np.array_equal(result.image[~found], frames.raw_rgb[~found])


# --------------------------------------------------------------------------- CFA


def test_cfa_planes_single_pixel_zingers(rng):
    clean = smooth_scene((128, 128), low=200, high=2000)
    planes = np.stack([poisson_image(clean * f, 1.0, rng) for f in (0.5, 1.0, 1.0, 0.4)]).astype(np.float32)
    truth = np.zeros(planes.shape, bool)
    dirty = planes.copy()
    for p in range(4):
        idx = rng.choice(128 * 128, 40, replace=False)
        truth[p].flat[idx] = True
        dirty[p].flat[idx] += rng.uniform(800, 4000, 40).astype(np.float32)
    result = remove_impulses_cfa(dirty)
    assert set(result.masks) == {"R", "G1", "G2", "B"}
    for p, name in enumerate(("R", "G1", "G2", "B")):
        recall, precision = recall_precision(result.masks[name], truth[p])
        assert recall >= 0.95 and precision >= 0.95, (name, recall, precision)
        assert np.array_equal(result.image[p][~result.masks[name]], dirty[p][~result.masks[name]])
        assert 0.8 < result.gain[name] < 1.2
    assert result.image.dtype == np.float32
    with pytest.raises(InputError):
        remove_impulses_cfa(np.zeros((3, 16, 16), np.float32))


def write_bayer_dng(path, mosaic: np.ndarray, *, black: int = 64, white: int = 16383):
    """Write an RGGB mosaic (uint16 counts incl. black) as an uncompressed 16-bit DNG.

    The shared writer (``tests/robustness/synthetic_files.py``) with this file's black and
    white levels; kept under this name because tests/_cli/test_denoise.py uses it.
    """
    from robustness.synthetic_files import write_dng

    return write_dng(path, mosaic, pattern="RGGB", black_counts=black, white_counts=white, bits=16)


def zinger_mosaic(rng, shape=(192, 256), count=60, black=64):
    """A green-screen Bayer mosaic (RGGB) with single-pixel zingers.

    Returns the dirty and the clean mosaic (uint16, black included) and the truth mask.
    """
    h, w = shape
    scene = smooth_scene((h // 2, w // 2), low=300, high=2500, blur_px=1.5)
    ratios = {(0, 0): 0.35, (0, 1): 1.0, (1, 0): 1.0, (1, 1): 0.15}  # R, G1, G2, B
    mosaic = np.zeros(shape)
    for (r, c), ratio in ratios.items():
        mosaic[r::2, c::2] = rng.poisson(scene * ratio)
    clean = np.clip(mosaic + black, 0, 16383).astype(np.uint16)
    truth = np.zeros(shape, bool)
    idx = rng.choice(h * w, count, replace=False)
    truth.flat[idx] = True
    mosaic.flat[idx] += rng.uniform(1500, 6000, count)
    return np.clip(np.rint(mosaic) + black, 0, 16383).astype(np.uint16), clean, truth


def test_cfa_mesh_inside_a_radiograph_is_not_touched_hits_around_it_are_found():
    """A fine mesh (60 % modulation) in the middle of a smooth radiograph, on the CFA planes
    of a tinted Bayer mosaic: at the mesh's border only one side of the texture guard's
    annulus lies on it, and the dim planes hold it aliased at a few noise sigmas (0.4-2 % of
    its pixels were flagged, mostly within 3 px of the border). Single-pixel hits on the
    radiograph around the mesh are still found."""
    rng = np.random.default_rng(20261125)
    size = 384
    light = smooth_scene((size, size), low=400, high=3000)
    patch = np.zeros((size, size), bool)
    patch[96:288, 96:288] = True
    mesh = grating((size, size), 4.82, 67.0, 1.0) * grating((size, size), 4.16, 157.0, 2.0)
    light = np.where(patch, light * mesh / mesh.max(), light)
    tint = np.array([0.35, 1.0, 0.15])
    scene = poisson_image(light[..., None] * tint, 1.0, rng)
    planes = np.stack([scene[0::2, 0::2, 0], scene[0::2, 1::2, 1], scene[1::2, 0::2, 1],
                       scene[1::2, 1::2, 2]]).astype(np.float32)
    on_patch = patch[0::2, 0::2]
    truth = np.zeros(planes.shape, bool)
    away = ~ndi.binary_dilation(on_patch, iterations=3)
    away[:4], away[-4:], away[:, :4], away[:, -4:] = False, False, False, False
    dirty = planes.copy()
    for p in range(4):
        idx = rng.choice(np.flatnonzero(away), 30, replace=False)
        truth[p].flat[idx] = True
        dirty[p].flat[idx] += 12.0 * np.sqrt(planes[p].flat[idx] + 1.0)  # 12 noise sigmas
    result = remove_impulses_cfa(dirty)
    for p, name in enumerate(("R", "G1", "G2", "B")):
        assert result.masks[name][on_patch].mean() <= 0.0005, (name, result.masks[name][on_patch].mean())
        recall, _ = recall_precision(result.masks[name], truth[p])
        assert recall >= 0.9, (name, recall)
        # a few noise pixels of the dim blue plane (60-450 counts) pass, wherever they are
        assert np.count_nonzero(result.masks[name] & ~ndi.binary_dilation(truth[p])) <= 3, name


@pytest.mark.parametrize("period_px, angle_deg, period2_px, angle2_deg, peak_counts", [
    (3.44, 134.1, 2.50, 194.1, 340.0), (3.25, 125.0, 2.88, 215.0, 530.0)])
def test_cfa_planes_of_a_dim_frame_filled_with_a_mesh_are_not_touched(period_px, angle_deg, period2_px,
                                                                      angle2_deg, peak_counts):
    """A dim tinted frame filled with a fine mesh (60 % modulation), as raw CFA planes with
    Poisson and read noise: the red and blue planes hold the mesh aliased at a few noise
    sigmas, their noise fit came out 4-10 times too wide (under the limit that shrinks it
    on demosaiced frames) with a pulse rate of 0.14-0.17, and 10-31 % (first mesh) and
    0.25-1.2 % (second) of the frame's pixels were flagged."""
    rng = np.random.default_rng(20261125)
    pattern = (grating((256, 256), period_px, angle_deg, rng.uniform(0, 6.3))
               * grating((256, 256), period2_px, angle2_deg, rng.uniform(0, 6.3)))
    expected = (peak_counts * pattern / pattern.max())[..., None] * np.array([0.35, 1.0, 0.15])
    scene = rng.poisson(expected) + rng.normal(0.0, 3.0, expected.shape)
    planes = np.stack([scene[0::2, 0::2, 0], scene[0::2, 1::2, 1], scene[1::2, 0::2, 1],
                       scene[1::2, 1::2, 2]]).astype(np.float32)
    flagged = remove_impulses_cfa(planes).any_mask().mean()
    assert flagged <= 0.002, flagged


def test_cfa_zingers_in_a_dng_found_before_demosaicing(tmp_path, rng):
    from napari_dslrxr.core.stages.impulse import cfa_mask_to_mosaic, demosaic_cleaned_raw
    from napari_dslrxr.core.io import read_image

    import cv2

    mosaic, clean_mosaic, truth = zinger_mosaic(rng)
    path = write_bayer_dng(tmp_path / "zingers.dng", mosaic)
    clean_rgb = read_image(write_bayer_dng(tmp_path / "clean.dng", clean_mosaic)).data
    loaded = read_image(path)
    frame = loaded.raw
    result = remove_impulses_cfa(frame.cfa_planes)
    found = cfa_mask_to_mosaic(result.masks, frame.plane_offsets, mosaic.shape)
    recall, precision = recall_precision(found, truth)
    assert recall >= 0.95 and precision >= 0.95, (recall, precision)
    # Unchanged planes demosaic exactly as io.read_image does.
    assert np.array_equal(demosaic_cleaned_raw(path, frame.cfa_planes, frame), loaded.data)
    cleaned_rgb = demosaic_cleaned_raw(path, result.image, frame)
    assert cleaned_rgb.dtype == np.uint16 and cleaned_rgb.shape == loaded.data.shape
    # Against the demosaiced zinger-free mosaic: far better than the dirty RGB and than a
    # 3x3 or 5x5 median of it (demosaicing spread each zinger into a coloured blob).
    ours = pe(clean_rgb, cleaned_rgb)
    assert ours < 0.2 * pe(clean_rgb, loaded.data)
    for size in (3, 5):
        assert ours < pe(clean_rgb, cv2.medianBlur(loaded.data, size))
    # Demosaicing (LibRaw AHD) reaches about 5 px: beyond 8 px of a replaced site nothing changes.
    far = ndi.distance_transform_edt(~found) > 8
    assert np.array_equal(cleaned_rgb[far], loaded.data[far])


@pytest.mark.parametrize("space", ["hsv", "grey"])
def test_progress_reaches_the_end_and_a_raising_callback_stops_the_stage(space):
    """The progress callback sees steps that only grow up to their total, the result is the
    same as without it, and raising from it stops the stage at that step (nothing returned)."""
    from napari_dslrxr.core.errors import WorkCancelled
    from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph

    rgb = make_dslr_radiograph((160, 200), seed=4).raw_rgb
    params = ImpulseParams(passes_h=2)
    reports: list[tuple[int, int]] = []
    result = remove_impulses(rgb, params, space=space, progress=lambda done, total: reports.append((done, total)))
    plain = remove_impulses(rgb, params, space=space)
    np.testing.assert_array_equal(result.image, plain.image)
    done = [d for d, _ in reports]
    assert len({t for _, t in reports}) == 1 and done == sorted(done) and done[-1] == reports[0][1]
    assert len(set(done)) >= (10 if space == "hsv" else 4)  # per pass of each channel, not only at the end
    stop_at = done[len(done) // 2]
    calls_after = []

    def cancel(step, total):
        if calls_after or step >= stop_at:
            calls_after.append(step)
            raise WorkCancelled("impulse removal: cancelled")

    with pytest.raises(WorkCancelled):
        remove_impulses(rgb, params, space=space, progress=cancel)
    assert calls_after == [stop_at]  # no step ran after the raise


def test_broad_patch_guard_keeps_pulses_in_a_subset_of_the_channels(rng):
    """A smooth blob and a pulse can have the same shape; a sensor hit lands in one colour's
    pixels, scintillator light in the screen's colour. On a yellow-green frame with a black
    level, Gaussian pulses 14 noise sigmas high in green only are found as without the guard,
    blobs of the screen's colour beside them are left more often, and the tint the guard
    compares with is the screen's."""
    from napari_dslrxr.core.stages.impulse.detection import _scintillator_tint

    h = w = 240
    yy, xx = np.mgrid[:h, :w]
    tint = np.array([0.65, 1.0, 0.2])
    light = 900.0 + 0.8 * xx + 500.0 * np.sin(xx / 19.0) * np.cos(yy / 27.0)  # anatomy-like variation
    blobs, pulses = np.zeros((h, w)), np.zeros((h, w))
    for i, r in enumerate(range(20, h - 20, 40)):
        for j, c in enumerate(range(20, w - 20, 40)):
            if (i + j) % 2 == 0:
                disc = ((yy - r) ** 2 + (xx - c) ** 2 <= 3.0 ** 2).astype(float)
                blobs += ndi.gaussian_filter(disc, 1.4) * 14 * 30.0
            else:
                pulses += 14 * 30.0 * np.exp(-((yy - r) ** 2 + (xx - c) ** 2) / (2 * 1.6 ** 2))
    scene = (light + blobs)[..., None] * tint
    scene[..., 1] += pulses
    image = rng.poisson(scene).astype(np.float32) + 256.0
    estimate = _scintillator_tint(image)
    assert np.dot(estimate, tint / np.linalg.norm(tint)) > 0.999, estimate
    mask = remove_impulses(image).any_mask()
    truth, blob = pulses > 3 * 30.0, blobs > 2 * 30.0
    # measured 235 of 252 pulse pixels, as without the guard; blob pixels 292 of 793 (437 without)
    assert np.count_nonzero(mask & truth) >= 0.9 * np.count_nonzero(truth)
    assert np.count_nonzero(mask & blob) < 0.45 * np.count_nonzero(blob)


@pytest.mark.parametrize("tint", [(1.0,), (0.65, 1.0, 0.2)], ids=["grey", "yellow_green"])
def test_small_dense_objects_blurred_by_the_screen_are_not_pulses(rng, tint):
    """A calcification or a marker bead is a Gaussian hill as wide as the screen's blur; the
    growth climbs it down to the noise, so its ring no longer stands up, and replacing it
    would erase the object. Of the pixels of hills of sigma 1.6-3 px and 10-60 noise sigmas on a
    sloping background, 1.0 % (grey) and 0.2 % (tinted) are flagged, 68 % and 56 % before the
    hill test, while flat pulses (2x2 to 4x4), single pixels and narrow Gaussian hits (sigma 0.7 px)
    of 8-20 sigmas beside them are all found, as before."""
    h, w = 260, 300
    yy, xx = np.mgrid[:h, :w].astype(float)
    light = 1200.0 + 1.2 * xx + 400.0 * np.sin(xx / 23.0) * np.cos(yy / 31.0)
    noise = np.sqrt(light)
    hills, hits = np.zeros((h, w)), np.zeros((h, w))
    for i, r in enumerate(range(20, h - 15, 30)):
        for j, c in enumerate(range(20, w - 15, 30)):
            if (i + j) % 2 == 0:
                sigma_px, height = (1.6, 2.0, 2.5, 3.0)[(i + 3 * j) % 4], (10, 20, 35, 60)[(2 * i + j) % 4]
                hills += height * noise[r, c] * np.exp(-((yy - r) ** 2 + (xx - c) ** 2) / (2 * sigma_px ** 2))
            else:
                height = (8, 12, 20)[(i + j) % 3] * noise[r, c]
                kind = (i + 2 * j) % 3
                if kind == 0:
                    side = 2 + (i % 3)
                    hits[r:r + side, c:c + side] += height
                elif kind == 1:
                    hits[r, c] += height
                else:
                    hits += height * np.exp(-((yy - r) ** 2 + (xx - c) ** 2) / (2 * 0.7 ** 2)) * (
                        (np.abs(yy - r) <= 2) & (np.abs(xx - c) <= 2))
    tint = np.asarray(tint)
    scene = (light + hills)[..., None] * tint
    scene[..., -1] += hits  # a sensor hit lands in one colour's pixels
    image = rng.poisson(scene).astype(np.float32)
    image = image[..., 0] if image.shape[-1] == 1 else image
    mask = remove_impulses(image).any_mask()
    hill_px, hit_px = hills > 2 * noise, hits > 3 * noise
    assert np.count_nonzero(mask & hill_px) < 0.05 * np.count_nonzero(hill_px)
    assert np.count_nonzero(mask & hit_px) >= 0.9 * np.count_nonzero(hit_px)
    # the knob: at its widest the test is off, and the hills are flattened as before
    off = remove_impulses(image, ImpulseParams(min_object_sigma_px=4.0)).any_mask()
    assert np.count_nonzero(off & hill_px) > 0.4 * np.count_nonzero(hill_px)
