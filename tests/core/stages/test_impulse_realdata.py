"""Impulse removal on real scintillator data: the NIQA edge repeats (shared/data/niqa_edge).

Protocol (issue 2): eight repeats of one exposure. Subtract the dark level, scale every
frame to the open-beam level, leave out a band of ``EDGE_BAND_PX`` around the plate edge
(the plate shifts by a few pixels between repeats), and take the per-pixel median of the
scaled repeats as the reference. Spot pixels of a frame are more than 6 sigma above the
reference, sigma being the repeats' noise at that intensity (from differences of pairs of
repeats, at the repeat's own local level). Fixed-pattern outliers (hot
pixels, screen defects: more than 6 sigma from the reference's own 5x5 median) are in every
repeat, so they count neither as spots nor in the percentage error.

Each frame is denoised on its own (raw uint16, as a user would). A spot pixel counts as
removed when the cleaned frame is no longer more than 6 sigma above the reference. PE is
measured on the remaining pixels between the frame and its cleaned version (both dark
subtracted and scaled): a switching filter should not touch them (PE near 0), a plain
median changes every pixel by about the noise level.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

SPOT_SIGMA = 6.0
EDGE_BAND_PX = 10
MAX_SHIFT_PX = 3
OFFSET_WINDOW_PX = 15
N_FRAMES = 8


@dataclass
class NiqaSet:
    frames: np.ndarray          # (8, H, W) uint16, as stored
    dark_level: float           # counts
    scales: np.ndarray          # (8,) frame i scaled = (frame - dark) * scales[i]
    reference: np.ndarray       # (H, W) float64, median of scaled repeats
    offsets: np.ndarray         # (8, H, W) slow difference of each scaled repeat to the reference
    sigma: np.ndarray           # (H, W) float64, single-frame noise at the reference's level
    noise_levels: np.ndarray    # level -> single-frame noise curve (counts, scaled units)
    noise_sigmas: np.ndarray
    evaluated: np.ndarray       # (H, W) bool: outside the edge band and not fixed pattern


def load_niqa(folder: Path) -> NiqaSet:
    """Build the reference, the noise map and the evaluation region from the 8 repeats."""
    import cv2
    import tifffile
    from scipy import ndimage as ndi

    folder = Path(folder)
    frames = np.stack([tifffile.imread(folder / f"edge20mm_{i:04d}.tif") for i in range(N_FRAMES)])
    open_beam = tifffile.imread(folder / "ob.tif").astype(np.float64)
    dark_level = float(np.median(tifffile.imread(folder / "dc.tif")))
    ob_level = float(np.median(open_beam)) - dark_level
    lin = frames.astype(np.float64) - dark_level
    # Open-beam part of each frame: above half the open-beam level after a median (spot-free).
    plate = np.stack([cv2.medianBlur(f.astype(np.float32), 5) < 0.5 * ob_level for f in lin])
    scales = np.array([ob_level / np.median(f[~p]) for f, p in zip(lin, plate, strict=True)])
    scaled = lin * scales[:, None, None]
    reference = np.median(scaled, axis=0)
    # Band around the edges: where a shift of an edge by MAX_SHIFT_PX would change a pixel by
    # more than the spot threshold (the blurred edge ramp) in the reference or in any repeat
    # (the plate moves between repeats), widened by EDGE_BAND_PX. Slopes are taken after a
    # despeckling so that spot tracks do not count as edges; a first noise estimate away from
    # steep slopes sets the threshold.
    slopes = [_edge_slope(image) for image in (reference, *scaled)]
    flat = slopes[0] < np.percentile(slopes[0], 50)
    sigma0 = _noise_versus_level(scaled, reference, flat)
    steep = np.any([slope * MAX_SHIFT_PX > SPOT_SIGMA * sigma0 for slope in slopes], axis=0)
    band = ndi.binary_dilation(steep, iterations=EDGE_BAND_PX)
    # Slow differences between a repeat and the reference (source decay not proportional in
    # the plate's shadow, plate shift in the PSF tails).
    offsets = np.stack([_slow_part(f - reference) for f in scaled])
    aligned = scaled - offsets
    noise_levels, noise_sigmas = _noise_curve(aligned, reference, ~band)
    sigma = np.interp(reference, noise_levels, noise_sigmas)
    # The reference is a median of 8 repeats: its own noise is sqrt(pi/2)/sqrt(8) of one
    # repeat's. Pixels that deviate from their 5x5 neighbourhood by more than 6 of those
    # sigmas are a fixed pattern of the screen or sensor (present in every repeat).
    sigma_reference = sigma * np.sqrt(np.pi / 2.0 / N_FRAMES)
    local = ndi.median_filter(reference, size=5, mode="reflect")
    fixed_pattern = np.abs(reference - local) > SPOT_SIGMA * sigma_reference
    return NiqaSet(frames, dark_level, scales, reference, offsets, sigma, noise_levels, noise_sigmas,
                   ~band & ~fixed_pattern)


def _despeckle(image: np.ndarray) -> np.ndarray:
    """Two 5x5 medians: removes spots and tracks, keeps edges (float32)."""
    import cv2

    once = cv2.medianBlur(np.ascontiguousarray(image, dtype=np.float32), 5)
    return cv2.medianBlur(once, 5)


def _slow_part(difference: np.ndarray) -> np.ndarray:
    """Slowly varying part of a difference image: despeckled, then a box mean."""
    import cv2

    return cv2.blur(_despeckle(difference), (OFFSET_WINDOW_PX, OFFSET_WINDOW_PX)).astype(np.float64)


def _edge_slope(image: np.ndarray) -> np.ndarray:
    """Gradient magnitude (counts per px) of an image after despeckling and a light blur."""
    from scipy import ndimage as ndi

    smooth = ndi.gaussian_filter(_despeckle(image).astype(np.float64), 1.5)
    return np.hypot(ndi.sobel(smooth, 0), ndi.sobel(smooth, 1)) / 8.0


def _noise_versus_level(scaled: np.ndarray, reference: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Single-frame noise at the reference's level, per pixel (see :func:`_noise_curve`)."""
    return np.interp(reference, *_noise_curve(scaled, reference, region))


def _noise_curve(scaled: np.ndarray, reference: np.ndarray, region: np.ndarray):
    """Single-frame noise as a function of the reference level.

    From differences of pairs of repeats, (a - b)/sqrt(2), which have exactly one frame's
    noise (a spread around the median of the repeats would not: each repeat is part of the
    median), robustly: 1.4826 x the median absolute difference at each level.
    """
    residual = np.abs(scaled[0::2] - scaled[1::2]) / np.sqrt(2.0)
    levels = reference[region]
    edges = np.unique(np.percentile(levels, np.linspace(0, 100, 41)))
    centres, values = [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = region & (reference >= lo) & (reference < hi)
        if sel.sum() > 100:
            centres.append(np.median(reference[sel]))
            values.append(1.4826 * np.median(residual[:, sel]))
    return np.asarray(centres), np.asarray(values)


@dataclass
class FrameScore:
    spots: int
    spot_removed_pct: float
    pe_pct: float


def score_frame(data: NiqaSet, index: int, cleaned: np.ndarray) -> FrameScore:
    """Spot removal (%) and PE (%) on the remaining pixels for one cleaned frame."""
    before = (data.frames[index].astype(np.float64) - data.dark_level) * data.scales[index]
    after = (cleaned.astype(np.float64) - data.dark_level) * data.scales[index]
    # The repeat's own level (the source decays over the series): its noise is that level's.
    level = data.reference + data.offsets[index]
    limit = level + SPOT_SIGMA * np.interp(level, data.noise_levels, data.noise_sigmas)
    spots = (before > limit) & data.evaluated
    removed = spots & (after <= limit)
    rest = data.evaluated & ~spots
    pe = 100.0 * np.linalg.norm((before - after)[rest]) / np.linalg.norm(before[rest])
    return FrameScore(int(spots.sum()), 100.0 * removed.sum() / max(spots.sum(), 1), float(pe))


@pytest.fixture(scope="module")
def niqa(shared_data) -> NiqaSet:
    folder = shared_data / "niqa_edge"
    if not folder.is_dir():
        pytest.skip(f"{folder} is absent")
    return load_niqa(folder)


def test_reference_and_spots_are_sane(niqa):
    # The data README: roughly 15 000 pixels per frame more than 2000 ADU above the median.
    score = score_frame(niqa, 0, niqa.frames[0])
    assert 1_000 < score.spots < 40_000
    assert score.spot_removed_pct == 0.0 and score.pe_pct == 0.0
    assert niqa.evaluated.mean() > 0.6
    assert np.all(np.abs(niqa.scales - 1.0) < 0.4)


@pytest.mark.slow
def test_single_frame_denoising_beats_median_filters(niqa):
    import cv2

    from napari_dslrxr.core.stages.impulse import remove_impulses

    for i in range(N_FRAMES):
        frame = niqa.frames[i]
        ours = score_frame(niqa, i, remove_impulses(frame).image)
        med3 = score_frame(niqa, i, cv2.medianBlur(frame, 3))
        med5 = score_frame(niqa, i, cv2.medianBlur(frame, 5))
        assert ours.spot_removed_pct >= 95.0, (i, ours)
        assert ours.pe_pct <= 0.2, (i, ours)
        # The baselines the issue names: about 1.2-1.3 % PE and 5-40 % of spots missed.
        assert med3.pe_pct > 5 * ours.pe_pct and med5.pe_pct > 5 * ours.pe_pct
        assert ours.spot_removed_pct > med3.spot_removed_pct


# --------------------------------------------------------------------------- synthetic colour


def scintillator_photo(radiograph: np.ndarray, rng, *, blur_px: float = 1.5):
    """A camera photo of a Gd2O2S:Tb screen showing ``radiograph``: green light, Poisson noise.

    The radiograph (display convention, bright = attenuating) is turned into screen light
    (bright where X-rays pass): 150 to 3650 photo-electrons in green, blurred by the screen,
    tinted with the emission's camera RGB ratio (0.35, 1, 0.15), Poisson per channel.
    Returns the noisy RGB (float64 counts).
    """
    from scipy import ndimage as ndi

    p = (radiograph - radiograph.min()) / np.ptp(radiograph)
    light = ndi.gaussian_filter(150.0 + 3500.0 * (1.0 - p), blur_px)
    tint = np.array([0.35, 1.0, 0.15])
    return rng.poisson(light[..., None] * tint).astype(np.float64)


def inject_hsv_pulses(rgb: np.ndarray, rng, count: int = 450):
    """Multi-pixel pulses (2x2 to 4x4) injected separately into H, S or V (cycled).

    H: hue moved by +-0.1 to 0.3 (circular); S: saturation lowered by 0.35 to 0.6; V: value
    multiplied by 1.5 to 3 (bright zinger). Patches do not touch each other. Returns the
    uint16 RGB and the truth mask of each channel.
    """
    from napari_dslrxr.core.stages.impulse import hsv_counts_to_rgb, rgb_to_hsv_counts

    hue, sat, val = (c.astype(np.float64) for c in rgb_to_hsv_counts(rgb))
    truth = {c: np.zeros(hue.shape, bool) for c in "HSV"}
    occupied = np.zeros(hue.shape, bool)
    h, w = hue.shape
    for k in range(count):
        side = int(rng.integers(2, 5))
        r, c = rng.integers(4, h - 4 - side), rng.integers(4, w - 4 - side)
        if occupied[r - 2:r + side + 2, c - 2:c + side + 2].any():
            continue
        patch = (slice(r, r + side), slice(c, c + side))
        channel = "HSV"[k % 3]
        if channel == "H":
            hue[patch] = (hue[patch] + rng.choice([-1, 1]) * rng.uniform(0.1, 0.3)) % 1.0
        elif channel == "S":
            sat[patch] = np.clip(sat[patch] - rng.uniform(0.35, 0.6), 0, 1)
        else:
            val[patch] *= rng.uniform(1.5, 3.0)
        truth[channel][patch] = True
        occupied[patch] = True
    dirty = np.clip(np.rint(hsv_counts_to_rgb(hue, sat, val)), 0, 65535).astype(np.uint16)
    return dirty, truth


def test_colour_radiograph_pulses_in_h_s_v(shared_data, rng):
    from napari_dslrxr.core.io import read_image
    from napari_dslrxr.core.stages.impulse import remove_impulses

    path = shared_data / "cr_dicom" / "RG1_UNCR.dcm"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    radiograph = read_image(path).data[700:1212, 600:1112].astype(np.float64)  # chest, 512x512
    clean = np.clip(np.rint(scintillator_photo(radiograph, rng)), 0, 65535).astype(np.uint16)
    dirty, truth = inject_hsv_pulses(clean, rng)
    result = remove_impulses(dirty)  # auto: HSV, passes H 3, S 1, V 1
    for channel in "HSV":
        mask, true = result.masks[channel], truth[channel]
        hit = np.count_nonzero(mask & true)
        recall, precision = hit / true.sum(), hit / max(mask.sum(), 1)
        assert recall >= 0.95 and precision >= 0.95, (channel, recall, precision)
    unchanged = ~result.any_mask()
    assert np.array_equal(result.image[unchanged], dirty[unchanged])
    assert 0.8 < result.gain["V"] < 1.3  # green photo-electrons: gain 1 (texture inflates it)

    # Per-channel HSV passes against one pass on the grey (R+G+B) image: PE to the pulse-free
    # photo. Hue and saturation pulses barely change R+G+B, so the grey pass misses them.
    def pe(image):
        ref = clean.astype(np.float64)
        return 100 * np.linalg.norm(image.astype(np.float64) - ref) / np.linalg.norm(ref)

    grey = remove_impulses(dirty, space="grey")
    assert pe(result.image) < 0.5 * pe(grey.image) < 0.5 * pe(dirty)
    assert pe(result.image) < 0.1 * pe(dirty)
