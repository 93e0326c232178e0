"""An independent pulse generator for evaluating impulse removal.

It shares nothing with the project's phantom or with the detector's own tests: the scenes
are real computed radiographs (shared/data/cr_dicom) used as X-ray transmission, the
camera adds Poisson and Gaussian read noise, and the pulses come in the shapes of the
issue: single pixels, flat squares (2x2 to 5x5), Gaussian blobs (up to 5x5, sub-pixel
centres), clusters (2 to 6 connected pixels), and tracks (1 or 2 px wide, 5 to 40 px long,
any angle, anti-aliased), at a given strength in noise sigmas, in any non-empty subset of
the colour channels, bright or dark. Texture scenes (sinusoidal line patterns and meshes)
have no pulses at all.

Every function takes an ``np.random.Generator`` so that seeds can be split into a
development set and a held-out set.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

SHAPES = ("single", "flat", "gauss", "cluster", "track")
STRENGTHS_SIGMA = (4.0, 8.0, 12.0, 20.0)
READ_NOISE_COUNTS = 3.0
TINTS = {"tinted": (0.35, 1.0, 0.15), "grey_rgb": (1.0, 1.0, 1.0), "grey": (1.0,)}


def data_dir() -> Path:
    return Path(os.environ.get("DSLRXR_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def radiograph_crop(rng, size_px: int = 512) -> np.ndarray:
    """A random crop of one of the two real CR radiographs, scaled to [0, 1] (1 = most attenuating)."""
    from napari_dslrxr.core.io import read_image

    name = ("RG1_UNCR.dcm", "RG3_UNCR.dcm")[int(rng.integers(0, 2))]
    image = read_image(data_dir() / "cr_dicom" / name).data.astype(np.float64)
    h, w = image.shape
    r = int(rng.integers(h // 8, h - size_px - h // 8))
    c = int(rng.integers(w // 8, w - size_px - w // 8))
    crop = image[r:r + size_px, c:c + size_px]
    lo, hi = np.percentile(crop, [0.5, 99.5])
    return np.clip((crop - lo) / max(hi - lo, 1e-9), 0.0, 1.0)


def transmission_light(attenuation01: np.ndarray, rng, tint) -> np.ndarray:
    """Expected counts per channel: the radiograph as transmission exp(-mu) of an X-ray beam.

    ``I = I0 exp(-k p)`` with ``k`` 1.5 to 3 and ``I0`` 1500 to 5000 photo-electrons in the
    brightest channel, plus a dark pedestal of 20 counts, blurred by the screen (Gaussian,
    0.8 to 1.6 px).
    """
    from scipy import ndimage as ndi

    k = rng.uniform(1.5, 3.0)
    i0 = rng.uniform(1500.0, 5000.0)
    light = ndi.gaussian_filter(20.0 + i0 * np.exp(-k * attenuation01), rng.uniform(0.8, 1.6))
    return light[..., None] * np.asarray(tint, np.float64)[None, None, :]


def camera(light: np.ndarray, rng) -> np.ndarray:
    """Poisson photo-electrons plus Gaussian read noise (float64 counts, not yet rounded)."""
    return rng.poisson(light).astype(np.float64) + rng.normal(0.0, READ_NOISE_COUNTS, light.shape)


def noise_sigma(light: np.ndarray) -> np.ndarray:
    return np.sqrt(light + READ_NOISE_COUNTS ** 2)


def pulse_profile(shape: str, rng) -> np.ndarray:
    """A pulse footprint (float, peak 1) of the given shape."""
    if shape == "single":
        return np.ones((1, 1))
    if shape == "flat":
        side = int(rng.integers(2, 6))
        return np.ones((side, side))
    if shape == "gauss":
        sigma = rng.uniform(0.5, 1.1)
        dy, dx = rng.uniform(-0.5, 0.5, 2)
        yy, xx = np.mgrid[-2:3, -2:3].astype(np.float64)
        prof = np.exp(-((yy - dy) ** 2 + (xx - dx) ** 2) / (2 * sigma ** 2))
        prof /= prof.max()
        prof[prof < 0.05] = 0.0
        return prof
    if shape == "cluster":
        n = int(rng.integers(2, 7))
        cells = {(0, 0)}
        while len(cells) < n:
            r, c = list(cells)[int(rng.integers(0, len(cells)))]
            dr, dc = [(0, 1), (1, 0), (0, -1), (-1, 0), (1, 1), (-1, 1)][int(rng.integers(0, 6))]
            cells.add((r + dr, c + dc))
        rows = [p[0] for p in cells]
        cols = [p[1] for p in cells]
        prof = np.zeros((max(rows) - min(rows) + 1, max(cols) - min(cols) + 1))
        for r, c in cells:
            prof[r - min(rows), c - min(cols)] = rng.uniform(0.6, 1.0)
        prof /= prof.max()
        return prof
    if shape == "track":
        length = rng.uniform(5.0, 40.0)
        width = float(rng.integers(1, 3))
        angle = rng.uniform(0.0, math.pi)
        half = length / 2.0 + width + 1
        n = int(math.ceil(2 * half)) | 1
        yy, xx = np.mgrid[:n, :n].astype(np.float64) - n // 2
        ux, uy = math.cos(angle), math.sin(angle)
        along = xx * ux + yy * uy
        across = -xx * uy + yy * ux
        # distance to the segment, anti-aliased over half a pixel
        beyond = np.maximum(np.abs(along) - length / 2.0, 0.0)
        dist = np.hypot(beyond, across)
        prof = np.clip(width / 2.0 + 0.5 - dist, 0.0, 1.0)
        energy = rng.uniform(0.7, 1.0, prof.shape)  # uneven deposit along the track
        prof = prof * energy
        prof[prof < 0.1] = 0.0
        keep_r = np.nonzero(prof.any(axis=1))[0]
        keep_c = np.nonzero(prof.any(axis=0))[0]
        prof = prof[keep_r[0]:keep_r[-1] + 1, keep_c[0]:keep_c[-1] + 1]
        return prof / prof.max()
    raise ValueError(shape)


@dataclass
class PulsedFrame:
    clean: np.ndarray            # uint16 (H, W) or (H, W, C): the frame without pulses
    dirty: np.ndarray            # uint16, same shape, with pulses
    light: np.ndarray            # expected counts (H, W, C)
    labels: np.ndarray           # int32 (H, W): pulse index + 1 where the pulse adds anything
    strong: np.ndarray           # bool (H, W): pixels with an excess of at least 3 sigma in a channel
    pulse_shape: list = field(default_factory=list)
    pulse_sigma: list = field(default_factory=list)
    pulse_channels: list = field(default_factory=list)


def pulsed_frame(kind: str, rng, *, polarity: str = "bright", count: int = 600, size_px: int = 512,
                 shapes=SHAPES, strengths=STRENGTHS_SIGMA) -> PulsedFrame:
    """A radiograph frame of ``kind`` (tinted, grey_rgb, grey) with ``count`` separated pulses."""
    tint = TINTS[kind]
    light = transmission_light(radiograph_crop(rng, size_px), rng, tint)
    noisy = camera(light, rng)
    sigma = noise_sigma(light)
    h, w, nch = light.shape
    dirty = noisy.copy()
    labels = np.zeros((h, w), np.int32)
    strong = np.zeros((h, w), bool)
    occupied = np.zeros((h, w), bool)
    frame = PulsedFrame(np.zeros(0), np.zeros(0), light, labels, strong)
    sign = -1.0 if polarity == "dark" else 1.0
    for _ in range(count * 3):
        if len(frame.pulse_shape) >= count:
            break
        shape = shapes[len(frame.pulse_shape) % len(shapes)]
        strength = strengths[(len(frame.pulse_shape) // len(shapes)) % len(strengths)]
        prof = pulse_profile(shape, rng)
        ph, pw = prof.shape
        if ph + 8 >= h or pw + 8 >= w:
            continue
        r = int(rng.integers(4, h - ph - 4))
        c = int(rng.integers(4, w - pw - 4))
        if occupied[r - 3:r + ph + 3, c - 3:c + pw + 3].any():
            continue
        if nch == 1:
            chans = [0]
        else:
            subset = int(rng.integers(1, 2 ** nch))
            chans = [k for k in range(nch) if subset >> k & 1]
        on = prof > 0
        win = (slice(r, r + ph), slice(c, c + pw))
        for k in chans:
            excess = strength * prof * sigma[win + (k,)]
            if sign < 0:  # a dark spot cannot take more than the pixel has
                excess = np.minimum(excess, noisy[win + (k,)] - 0.0)
            dirty[win + (k,)] += sign * excess
            strong[win] |= (strength * prof >= 3.0) & on
        labels[win][on] = len(frame.pulse_shape) + 1
        occupied[win] |= on
        frame.pulse_shape.append(shape)
        frame.pulse_sigma.append(strength)
        frame.pulse_channels.append(tuple(chans))
    to_u16 = lambda a: np.clip(np.rint(a), 0, 65535).astype(np.uint16)  # noqa: E731
    frame.clean = to_u16(noisy)
    frame.dirty = to_u16(dirty)
    if nch == 1:
        frame.clean, frame.dirty = frame.clean[..., 0], frame.dirty[..., 0]
    return frame


# --------------------------------------------------------------------------- texture


def grating(shape, period_px: float, angle_deg: float, phase: float, modulation: float = 0.6) -> np.ndarray:
    """1 + m cos(2 pi (x cos a + y sin a) / P + phase)."""
    yy, xx = np.mgrid[:shape[0], :shape[1]].astype(np.float64)
    a = math.radians(angle_deg)
    return 1.0 + modulation * np.cos(2 * math.pi * (xx * math.cos(a) + yy * math.sin(a)) / period_px + phase)


def texture_scene(rng, kind: str, size_px: int = 256):
    """A pulse-free texture: a line pattern or a mesh (period 2.2-5.3 px, 60 % modulation).

    Returns (expected counts (H, W), description).
    """
    period = rng.uniform(2.2, 5.3)
    angle = rng.uniform(0.0, 180.0)
    level = rng.uniform(300.0, 4000.0)
    if kind == "lines":
        pattern = grating((size_px, size_px), period, angle, rng.uniform(0, 2 * math.pi))
        desc = f"lines P={period:.2f} a={angle:.0f}"
    else:
        other = angle + rng.choice([60.0, 90.0])
        p2 = rng.uniform(2.2, 5.3)
        pattern = (grating((size_px, size_px), period, angle, rng.uniform(0, 6.3))
                   * grating((size_px, size_px), p2, other, rng.uniform(0, 6.3)))
        desc = f"mesh P={period:.2f}/{p2:.2f} a={angle:.0f}"
    return level * pattern / pattern.max(), desc


def embedded_texture(rng, kind: str, size_px: int = 512, patch_px: int = 256):
    """A radiograph (transmission light, grey) with a texture patch in its middle.

    Returns (expected counts (H, W), patch mask, description). The texture multiplies the
    local light, as a line-pair target or a grid on the detector would.
    """
    light = transmission_light(radiograph_crop(rng, size_px), rng, (1.0,))[..., 0]
    pattern, desc = texture_scene(rng, kind, patch_px)
    pattern = pattern / pattern.max()
    r0 = (size_px - patch_px) // 2
    patch = np.zeros(light.shape, bool)
    patch[r0:r0 + patch_px, r0:r0 + patch_px] = True
    light[patch] *= pattern.ravel() / pattern.mean()
    return light, patch, "in radiograph: " + desc
