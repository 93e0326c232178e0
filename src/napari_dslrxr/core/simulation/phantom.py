"""Synthetic DSLR-like frames of an X-ray scintillator, with the truth that made them.

The model follows the acquisition chain of a consumer camera photographing a scintillator
screen through a mirror:

1. a radiograph-like object in attenuation units (soft-tissue body with a smooth thickness
   variation, two "lung" fields, bone-like bars, discs of decreasing contrast and a line-pair
   group), transmitted as ``exp(-mu)``;
2. the screen (a rectangle in its own coordinates) seen by the camera as a keystoned
   quadrilateral inside a dark frame (perspective warp);
3. an uneven gain: cos^4-like vignetting times a heel-effect ramp;
4. Gaussian blur (screen light spread + defocus);
5. the scintillator colour (Gd2O2S:Tb, green) as per-channel weights;
6. Poisson photon noise with a camera gain, Gaussian read noise and a black level, clipped
   at a 14-bit white level;
7. multi-pixel impulsive pulses (direct X-ray hits on the sensor), different in each colour
   channel.

Matching flat (screen exposed without object) and dark (no X-rays) frames are made with the
same gain map and noise model. Everything is seeded: the same arguments give the same
arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: Relative response of the R, G, B camera channels to the scintillator light (green phosphor).
SCINTILLATOR_RGB_WEIGHTS = (0.28, 1.0, 0.36)


@dataclass
class PhantomTruth:
    """What the synthetic frames were made from.

    Attributes
    ----------
    attenuation : ndarray, float32, (h_obj, w_obj)
        Object attenuation ``mu`` (dimensionless line integral) in screen coordinates.
    transmission : ndarray, float32, (h_obj, w_obj)
        ``exp(-mu)``, noise-free, in screen coordinates.
    screen_corners_xy : ndarray, float64, (4, 2)
        Corners of the screen in the frame, (x, y) pixels, order top-left, top-right,
        bottom-right, bottom-left.
    screen_mask : ndarray, bool, (H, W)
        Pixels inside the screen quadrilateral.
    gain_map : ndarray, float32, (H, W)
        Relative illumination (vignetting x heel), 1 at the brightest point.
    clean_rgb : ndarray, float32, (H, W, 3)
        Expected signal (counts above black) before noise and pulses.
    pulse_mask : ndarray, bool, (H, W, 3)
        Where pulses were added to the radiograph, per colour channel.
    flat_patch_rc : tuple of int
        ``(r0, c0, r1, c1)`` of a patch in the frame where the object is uniform soft tissue
        (for noise measurements).
    homography : ndarray, float64, (3, 3)
        Maps screen (object) pixel coordinates to frame coordinates.
    blur_sigma_px : float
        Gaussian blur applied in the frame, pixels.
    camera_gain_counts_per_photon : float
        Counts per detected photon (the Poisson gain).
    flat_pulse_mask : ndarray, bool, (H, W, 3) or None
        Where pulses were added to the flat frame, per colour channel.
    """

    attenuation: np.ndarray
    transmission: np.ndarray
    screen_corners_xy: np.ndarray
    screen_mask: np.ndarray
    gain_map: np.ndarray
    clean_rgb: np.ndarray
    pulse_mask: np.ndarray
    flat_patch_rc: tuple[int, int, int, int]
    homography: np.ndarray
    blur_sigma_px: float
    camera_gain_counts_per_photon: float
    flat_pulse_mask: np.ndarray | None = None


@dataclass
class PhantomFrames:
    """A synthetic radiograph photographed by a DSLR, with flat, dark and truth.

    Attributes
    ----------
    raw_rgb : ndarray, uint16, (H, W, 3)
        The radiograph frame: linear counts including the black level (as from camera raw).
    flat : ndarray, uint16, (H, W, 3)
        Open-beam frame (screen exposed without the object), same settings.
    dark : ndarray, uint16, (H, W, 3)
        X-ray-off frame (black level + read noise).
    black_level : float
        Black level of every channel, counts.
    white_level : int
        Saturation level, counts.
    truth : PhantomTruth
    """

    raw_rgb: np.ndarray
    flat: np.ndarray
    dark: np.ndarray
    black_level: float
    white_level: int
    truth: PhantomTruth


def make_object(shape: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """Attenuation map of a radiograph-like object in screen coordinates.

    Parameters
    ----------
    shape : (int, int)
        ``(h, w)`` of the screen in its own pixels.

    Returns
    -------
    attenuation : ndarray, float32, (h, w)
        Dimensionless ``mu`` (transmission ``exp(-mu)``), 0.1 in the direct-exposure
        background, about 1.2 in soft tissue, up to about 2.6 in bone.
    flat_patch_rc : (r0, c0, r1, c1)
        A patch (screen pixels) of uniform soft tissue.
    """
    h, w = int(shape[0]), int(shape[1])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    u, v = xx / w, yy / h  # normalised coordinates
    mu = np.full((h, w), 0.1, np.float32)  # direct exposure: thin screen cover only

    def smooth_step(d: np.ndarray, width: float) -> np.ndarray:
        # 0 outside, 1 inside, a soft edge about `width` pixels wide (d: signed distance, px)
        return np.clip(0.5 + d / max(width, 1e-6), 0.0, 1.0)

    scale = min(h, w)
    # body: ellipse with a gentle thickness variation
    body_r = np.sqrt(((u - 0.5) / 0.40) ** 2 + ((v - 0.5) / 0.44) ** 2)
    body = smooth_step((1.0 - body_r) * 0.4 * scale, 2.0)
    thickness = 1.1 + 0.25 * np.exp(-(((u - 0.5) / 0.3) ** 2 + ((v - 0.55) / 0.35) ** 2))
    mu += body * thickness
    # two lung-like fields (less attenuation) in the upper half
    for cx in (0.33, 0.67):
        lung_r = np.sqrt(((u - cx) / 0.11) ** 2 + ((v - 0.36) / 0.17) ** 2)
        mu -= 0.45 * smooth_step((1.0 - lung_r) * 0.1 * scale, 3.0)
    # bone-like bars (spine and a rib-like diagonal bar)
    spine = smooth_step(0.035 * w - np.abs(xx - 0.5 * w), 1.5) * smooth_step(0.36 * h - np.abs(yy - 0.52 * h), 1.5)
    mu += 1.1 * spine
    diag = np.abs((xx - 0.25 * w) * 0.34 - (yy - 0.70 * h) * 0.94)  # distance to a tilted line, px
    mu += 0.9 * smooth_step(0.018 * scale - diag, 1.5) * smooth_step(0.12 * w - np.abs(xx - 0.25 * w), 1.5)
    # discs of decreasing contrast (detectability) along the lower right
    for k, contrast in enumerate((0.30, 0.15, 0.08, 0.04, 0.02)):
        cx, cy = (0.60 + 0.055 * k) * w, 0.78 * h
        r = np.hypot(xx - cx, yy - cy)
        mu += contrast * smooth_step(0.018 * scale - r, 1.0)
    # line pairs: groups of bars with periods 12, 8, 6 and 4 px, upper middle
    x0 = int(0.40 * w)
    for period in (12, 8, 6, 4):
        n_bars = 5
        width_px = n_bars * period
        y0, y1 = int(0.08 * h), int(0.08 * h + max(20, 0.06 * h))
        cols = np.arange(x0, min(w, x0 + width_px))
        on = ((cols - x0) % period) < (period // 2)
        mu[y0:y1, cols[on]] += 0.5
        x0 += width_px + max(6, period * 2)
    # uniform soft-tissue patch for noise measurements: lower left inside the body
    side = max(8, int(0.06 * scale))
    cy, cx = int(0.60 * h), int(0.30 * w)
    patch = (cy - side // 2, cx - side // 2, cy + side // 2, cx + side // 2)
    return mu.astype(np.float32), patch


def _keystone_corners(frame_shape: tuple[int, int], rng: np.random.Generator,
                      keystone: float, rotation_deg: float, fill: float) -> np.ndarray:
    """Corners (x, y) of a rotated, keystoned quadrilateral centred in the frame."""
    h, w = frame_shape
    half_w, half_h = 0.5 * fill * w, 0.5 * fill * h
    # trapezoid: the top edge shorter than the bottom one (camera looking up at the mirror)
    corners = np.array([[-half_w * (1 - keystone), -half_h], [half_w * (1 - keystone), -half_h],
                        [half_w, half_h], [-half_w, half_h]], np.float64)
    corners += rng.uniform(-0.01, 0.01, corners.shape) * np.array([w, h])
    angle = np.deg2rad(rotation_deg)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    return corners @ rot.T + np.array([0.5 * w, 0.5 * h])


def _gain_map(shape: tuple[int, int]) -> np.ndarray:
    """Vignetting (cos^4 of the field angle) times a heel-effect ramp, max 1, float32."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    diag = np.hypot(h, w) / 2
    r = np.hypot(xx - 0.52 * w, yy - 0.48 * h) / diag
    cos_theta = 1.0 / np.sqrt(1.0 + (0.9 * r) ** 2)  # field angle for a moderate wide-angle lens
    heel = 1.0 - 0.25 * (xx / w)  # anode heel: intensity falls across the field
    gain = cos_theta**4 * heel
    return (gain / gain.max()).astype(np.float32)


def _add_pulses(frame: np.ndarray, rng: np.random.Generator, rate: float, white_level: int) -> np.ndarray:
    """Add bright multi-pixel pulses (1x1 to 3x3 px) independently per channel; return the mask."""
    h, w, n_ch = frame.shape
    mask = np.zeros(frame.shape, bool)
    n = int(rate * h * w)
    shapes = [np.ones((1, 1)), np.ones((1, 2)), np.ones((2, 1)), np.ones((2, 2)),
              np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]])]
    for c in range(n_ch):
        rows = rng.integers(1, h - 3, n)
        cols = rng.integers(1, w - 3, n)
        kinds = rng.integers(0, len(shapes), n)
        amps = rng.uniform(0.05, 0.6, n) * white_level
        for r, col, k, a in zip(rows, cols, kinds, amps, strict=True):
            sh = shapes[k]
            sel = sh > 0
            block = frame[r:r + sh.shape[0], col:col + sh.shape[1], c]
            block[sel] += a
            mask[r:r + sh.shape[0], col:col + sh.shape[1], c] |= sel
    return mask


def make_dslr_radiograph(shape: tuple[int, int] = (600, 900), *, seed: int = 0,
                         peak_counts: float = 6000.0, camera_gain: float = 2.0,
                         read_noise_counts: float = 3.0, black_level: float = 512.0,
                         blur_sigma_px: float = 1.8, pulse_rate: float = 5e-4,
                         keystone: float = 0.12, rotation_deg: float = 2.0,
                         screen_fill: float = 0.8, white_level: int = 16383) -> PhantomFrames:
    """Make a synthetic DSLR photograph of a scintillator, with flat and dark frames.

    Parameters
    ----------
    shape : (int, int)
        Frame size ``(H, W)`` in pixels (at least 64 x 64).
    seed : int
        Seed of every random choice (noise, pulses, small corner jitter).
    peak_counts : float
        Expected green-channel signal at the brightest unattenuated point, counts above black.
    camera_gain : float
        Counts per detected photon (Poisson gain); noise variance = gain x signal.
    read_noise_counts : float
        Standard deviation of the Gaussian read noise, counts.
    black_level : float
        Offset added to every channel, counts.
    blur_sigma_px : float
        Standard deviation of the Gaussian blur in the frame, pixels.
    pulse_rate : float
        Pulses per pixel per channel (each pulse covers 1 to 5 pixels).
    keystone : float
        Relative shortening of the top edge of the screen (0 = rectangle).
    rotation_deg : float
        Rotation of the screen in the frame, degrees.
    screen_fill : float
        Fraction of the frame width/height the screen spans (0.3 to 0.95).
    white_level : int
        Saturation, counts (14-bit by default).

    Returns
    -------
    PhantomFrames
        uint16 radiograph, flat and dark frames and the truth.
    """
    h, w = int(shape[0]), int(shape[1])
    if h < 64 or w < 64:
        raise ValueError(f"phantom frame must be at least 64x64, got {h}x{w}")
    rng = np.random.default_rng(seed)
    corners = _keystone_corners((h, w), rng, keystone, rotation_deg, screen_fill)
    obj_h, obj_w = int(round(screen_fill * h)), int(round(screen_fill * w))
    mu, patch_obj = make_object((obj_h, obj_w))
    transmission = np.exp(-mu).astype(np.float32)
    src = np.array([[-0.5, -0.5], [obj_w - 0.5, -0.5], [obj_w - 0.5, obj_h - 0.5], [-0.5, obj_h - 0.5]], np.float32)
    homography = cv2.getPerspectiveTransform(src, corners.astype(np.float32))

    def to_frame(img: np.ndarray, interp: int = cv2.INTER_LINEAR) -> np.ndarray:
        return cv2.warpPerspective(img, homography, (w, h), flags=interp,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    screen_light = to_frame(transmission)
    screen_cover = to_frame(np.ones((obj_h, obj_w), np.float32))  # fractional screen coverage
    gain = _gain_map((h, w))
    stray = 0.004  # stray light in the camera box, relative to the peak
    weights = np.asarray(SCINTILLATOR_RGB_WEIGHTS, np.float32)

    def expose(light: np.ndarray) -> np.ndarray:
        signal = cv2.GaussianBlur(light * gain, (0, 0), blur_sigma_px) + stray * gain
        return signal[..., None] * (peak_counts * weights)  # counts above black

    clean = expose(screen_light)
    clean_flat = expose(screen_cover)

    def sample(expected: np.ndarray) -> np.ndarray:
        # channel by channel and in float32, so a 24 Mpx frame stays within a few hundred MB
        counts = np.empty(expected.shape, np.float32)
        for c in range(expected.shape[2]):
            counts[..., c] = rng.poisson(np.maximum(expected[..., c], 0) / camera_gain)
            counts[..., c] *= camera_gain
            counts[..., c] += rng.standard_normal(expected.shape[:2], dtype=np.float32) * np.float32(read_noise_counts)
        return counts

    radiograph = sample(clean)
    pulse_mask = _add_pulses(radiograph, rng, pulse_rate, white_level)
    flat = sample(clean_flat)
    flat_pulse_mask = _add_pulses(flat, rng, pulse_rate, white_level)
    dark = rng.standard_normal((h, w, 3), dtype=np.float32) * np.float32(read_noise_counts)

    def to_u16(counts: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(counts + black_level), 0, white_level).astype(np.uint16)

    # the uniform patch, mapped into the frame (bounding box of its warped centre region)
    r0, c0, r1, c1 = patch_obj
    pts = np.array([[[c0, r0], [c1, r0], [c1, r1], [c0, r1]]], np.float32)
    warped = cv2.perspectiveTransform(pts, homography)[0]
    fr0, fr1 = int(np.ceil(warped[:, 1].min())), int(np.floor(warped[:, 1].max()))
    fc0, fc1 = int(np.ceil(warped[:, 0].min())), int(np.floor(warped[:, 0].max()))
    shrink_r, shrink_c = (fr1 - fr0) // 6, (fc1 - fc0) // 6  # stay inside the warped patch
    flat_patch = (fr0 + shrink_r, fc0 + shrink_c, fr1 - shrink_r, fc1 - shrink_c)

    truth = PhantomTruth(
        attenuation=mu, transmission=transmission, screen_corners_xy=corners,
        screen_mask=screen_cover > 0.5, gain_map=gain, clean_rgb=clean.astype(np.float32),
        pulse_mask=pulse_mask, flat_patch_rc=flat_patch, homography=homography,
        blur_sigma_px=float(blur_sigma_px), camera_gain_counts_per_photon=float(camera_gain),
        flat_pulse_mask=flat_pulse_mask)
    return PhantomFrames(raw_rgb=to_u16(radiograph), flat=to_u16(flat), dark=to_u16(dark),
                         black_level=float(black_level), white_level=int(white_level), truth=truth)
