"""A generator of camera frames the stages were NOT developed on (the scenario corpus).

The project's own phantom (:mod:`napari_dslrxr.core.phantom`) draws geometric shapes on a
keystoned screen in a dark frame; every stage was tuned on it. This generator instead takes
the anatomy of two real clinical CR radiographs (a chest and a collimated leg, shared data) as
a transmission map, and photographs it in many ways:

* layouts: the camera sees only part of the screen (anatomy fills the whole frame), the whole
  screen in a room (rotated, keystoned), or a screen cut by one or two frame borders;
* collimated fields (the leg's own collimator bands; dark blades added on the chest);
* scintillator tints (Gd2O2S:Tb green, CsI:Tl yellow-green, CaWO4 blue) or a grey frame;
* exposures from photon-starved (a few hundred DN in the open beam) to near saturation;
* flat-field patterns from lens vignetting and the anode heel effect (a matching noisy flat
  frame is generated);
* room light around the screen from none to a few per cent of the screen's brightness.

Each :class:`Scenario` carries the truth the invariants need: the attenuation (natural log
units) of every frame pixel that shows anatomy, the anatomy mask (inside the exposed screen,
outside direct exposure and collimation), the flat-field pattern and the screen mask.

A CR pixel value is roughly proportional to the log of the exposure, so the display value
``v`` (bone bright, MONOCHROME1 inverted) scaled to [0, 1] inside the collimated field is
taken as attenuation ``a = alpha v`` with ``alpha`` of 2.5 to 4 (transmission from 1 down to
2-8 %), the range of a chest or a limb.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

#: Frame size of every scenario (small: the corpus must run in well under two minutes).
FRAME_SHAPE = (180, 270)

SOURCES = ("RG1_UNCR", "RG3_UNCR")  # chest, leg (shared data, cr_dicom)

#: Relative channel responses (R, G, B) of common scintillators seen by a Bayer camera.
TINTS = {"gos_green": (0.30, 1.00, 0.35), "csi_yellow": (0.65, 1.00, 0.20), "cawo4_blue": (0.35, 0.70, 1.00),
         "grey": None}

LAYOUTS = ("whole_field", "screen_in_room", "partial_border")


def data_dir() -> Path:
    env = os.environ.get("DSLRXR_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[2].parent / "shared" / "data"


@dataclass
class Source:
    """One real radiograph prepared as an anatomy map (downsampled)."""

    name: str
    value: np.ndarray  # float32, display value scaled to [0, 1] inside the field (bone = 1)
    anatomy: np.ndarray  # bool: inside the collimated field and not direct exposure


@dataclass
class Scenario:
    seed: int
    description: str
    raw: np.ndarray  # float32 counts, (H, W, 3) or (H, W)
    flat: np.ndarray  # matching open-beam frame
    black_level: float
    attenuation: np.ndarray  # float32 (H, W): true attenuation where anatomy is seen, NaN elsewhere
    anatomy: np.ndarray  # bool (H, W): anatomy pixels away from the screen's rim
    screen: np.ndarray  # bool (H, W): pixels on the exposed screen
    flat_pattern: np.ndarray  # float32 (H, W), relative illumination (vignetting x heel)
    info: dict = field(default_factory=dict)


@functools.lru_cache(maxsize=None)
def load_source(name: str, long_side_px: int = 720) -> Source:
    """Read a CR radiograph, downsample, find its field and its anatomy (truth for the corpus)."""
    from napari_dslrxr.core.io import read_image
    from napari_dslrxr.core.stages.collimation import detect_collimation

    data = read_image(data_dir() / "cr_dicom" / f"{name}.dcm").data.astype(np.float32)
    f = long_side_px / max(data.shape)
    small = cv2.resize(data, (round(data.shape[1] * f), round(data.shape[0] * f)), interpolation=cv2.INTER_AREA)
    collimation = detect_collimation(small, inset_px=4.0)
    field_mask = collimation.mask
    lo, hi = np.percentile(small[field_mask], [0.5, 99.5])
    value = np.clip((small - lo) / (hi - lo), -0.05, 1.05).astype(np.float32)
    # Direct exposure (no body in the beam): the darkest mode of the field's histogram, up to
    # the valley that follows it when the valley is deep (a hand rule, independent of the stages)
    hist, edges = np.histogram(value[field_mask], bins=44, range=(-0.05, 1.05))
    smooth = np.convolve(hist, np.ones(3) / 3, mode="same")
    peak = int(np.argmax(smooth[:8]))
    valley = peak + int(np.argmin(smooth[peak:16]))
    direct_level = float(edges[valley + 1]) if smooth[valley] < 0.35 * smooth[peak] else -1.0
    anatomy = field_mask & (value > direct_level + 0.03)
    anatomy = cv2.erode(anatomy.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    # burned-in markers (the leg's "R") are not anatomy either: very bright, small
    anatomy &= value < 1.02
    return Source(name, value, anatomy)


def _homography_to_quad(src_shape: tuple[int, int], quad_xy: np.ndarray) -> np.ndarray:
    h, w = src_shape
    src = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float32)
    return cv2.getPerspectiveTransform(src, quad_xy.astype(np.float32))


def _quad(rng: np.random.Generator, frame: tuple[int, int], layout: str, aspect: float) -> np.ndarray:
    """Screen corners (x, y), TL TR BR BL, for a layout."""
    fh, fw = frame
    if layout == "screen_in_room":
        scale = rng.uniform(0.55, 0.82)
        cx, cy = fw / 2 + rng.uniform(-0.06, 0.06) * fw, fh / 2 + rng.uniform(-0.06, 0.06) * fh
    else:  # partial_border: larger, pushed against one or two borders
        scale = rng.uniform(0.85, 1.05)
        cx = fw / 2 + rng.choice([-1, 0, 1]) * rng.uniform(0.15, 0.25) * fw
        cy = fh / 2 + rng.choice([-1, 1]) * rng.uniform(0.1, 0.22) * fh
    height = scale * fh
    width = min(height * aspect, 1.1 * fw * scale)
    height = width / aspect
    angle = np.deg2rad(rng.uniform(-12, 12))
    base = np.array([[-width / 2, -height / 2], [width / 2, -height / 2], [width / 2, height / 2],
                     [-width / 2, height / 2]])
    keystone = rng.uniform(-0.12, 0.12)  # one side shorter than the other (camera tilt)
    base[:2, 0] *= 1 - keystone
    base[2:, 0] *= 1 + keystone
    base += rng.normal(0, 0.015 * height, base.shape)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    return base @ rot.T + np.array([cx, cy])


def _flat_pattern(rng: np.random.Generator, frame: tuple[int, int]) -> np.ndarray:
    fh, fw = frame
    yy, xx = np.mgrid[0:fh, 0:fw].astype(np.float32)
    cx, cy = fw / 2 + rng.uniform(-0.1, 0.1) * fw, fh / 2 + rng.uniform(-0.1, 0.1) * fh
    r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / (0.5 * np.hypot(fw, fh)) ** 2
    strength = rng.uniform(0.15, 0.6)  # cos^4-like fall-off of the lens
    vignetting = 1.0 / (1.0 + strength * r2) ** 2
    direction = rng.uniform(0, 2 * np.pi)
    heel = 1.0 + rng.uniform(0.05, 0.2) * ((xx / fw - 0.5) * np.cos(direction) + (yy / fh - 0.5) * np.sin(direction)) * 2
    pattern = vignetting * heel
    return (pattern / pattern.max()).astype(np.float32)


def _dense_shield(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """A dense, uniform, irregular area (lead shielding, a thick cast, blades left undetected)
    on one or two sides of the field, 25-45 % of it: a polygon with an uneven inner outline."""
    sh, sw = shape
    target = rng.uniform(0.25, 0.45)
    sides = rng.choice(4, size=int(rng.integers(1, 3)), replace=False)
    mask = np.zeros(shape, np.uint8)
    depth = target / len(sides)
    for side in sides:
        n = int(rng.integers(4, 8))
        t = np.linspace(0, 1, n)
        # the inner outline: depth varies along the side (never a straight blade edge)
        d = np.clip(depth * (1 + rng.uniform(-0.6, 0.6, n)), 0.05, 0.8)
        if side in (0, 1):  # top, bottom
            inner = np.column_stack([t * (sw - 1), (d * sh if side == 0 else (1 - d) * sh)])
            edge = [[sw - 1, 0 if side == 0 else sh - 1], [0, 0 if side == 0 else sh - 1]]
        else:  # left, right
            inner = np.column_stack([(d * sw if side == 2 else (1 - d) * sw), t * (sh - 1)])
            edge = [[0 if side == 2 else sw - 1, sh - 1], [0 if side == 2 else sw - 1, 0]]
        poly = np.vstack([inner, edge]).round().astype(np.int32)
        cv2.fillPoly(mask, [poly], 1)
    return mask.astype(bool)


def make_scenario(seed: int, frame: tuple[int, int] = FRAME_SHAPE, *, family: str = "corpus",
                  illumination_pattern: bool = True) -> Scenario:
    """One randomised camera frame of real anatomy (deterministic per seed).

    ``illumination_pattern=False``: the same frame (same anatomy, layout, noise draws) lit
    evenly; the pattern is still drawn, so every other random choice stays the same.

    ``family="dense_area"``: the same frame with a large dense uniform area added over the
    anatomy (:func:`_dense_shield`: shielding, a cast or undetected blades, 25-45 % of the
    field, attenuating more than any anatomy). Its histogram then has two modes, the whole
    anatomy and the dense area, that a direct-exposure rule may take for "direct exposure
    and object".
    """
    rng = np.random.default_rng([20261124, seed])
    source = load_source(SOURCES[seed % 2] if rng.random() < 0.8 else SOURCES[int(rng.integers(2))])
    layout = LAYOUTS[int(rng.integers(len(LAYOUTS)))]
    tint_name = list(TINTS)[int(rng.integers(len(TINTS)))]
    fh, fw = frame
    alpha = rng.uniform(2.5, 4.0)
    value = source.value.copy()
    anatomy_src = source.anatomy.copy()
    sh, sw = value.shape
    collimated = False
    if source.name == "RG1_UNCR" and rng.random() < 0.35:
        # collimator blades on the chest: the band beyond them gets scatter and leakage only
        collimated = True
        band = np.zeros_like(anatomy_src)
        left, right = int(rng.uniform(0.04, 0.15) * sw), int(rng.uniform(0.04, 0.15) * sw)
        top = int(rng.uniform(0.0, 0.12) * sh)
        band[:, :left] = band[:, sw - right:] = True
        band[:top] = True
        value[band] = rng.uniform(1.4, 1.8)
        anatomy_src &= ~cv2.dilate(band.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    if family == "dense_area":
        shield_rng = np.random.default_rng([20261124, seed, 7])
        shield = _dense_shield(shield_rng, value.shape)
        value[shield] = shield_rng.uniform(1.3, 1.9)
        anatomy_src &= ~cv2.dilate(shield.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    elif family != "corpus":
        raise ValueError(f"unknown scenario family {family!r}")
    attenuation_src = (alpha * value).astype(np.float32)

    if layout == "whole_field":
        # the camera frames part of the screen: a crop of the anatomy fills the frame
        zoom = rng.uniform(1.0, 1.6)
        crop_w = min(sw, sh * fw / fh) / zoom
        crop_h = crop_w * fh / fw
        x0 = rng.uniform(0, sw - crop_w)
        y0 = rng.uniform(0, sh - crop_h)
        quad = np.array([[0, 0], [fw - 1, 0], [fw - 1, fh - 1], [0, fh - 1]], np.float64)
        src_quad = np.array([[x0, y0], [x0 + crop_w, y0], [x0 + crop_w, y0 + crop_h], [x0, y0 + crop_h]], np.float32)
        matrix = cv2.getPerspectiveTransform(src_quad, quad.astype(np.float32))
        # the frame's corners are screen pixels: extend the quad so it covers the frame
        quad = quad + np.array([[-20, -20], [20, -20], [20, 20], [-20, 20]])
    else:
        quad = _quad(rng, frame, layout, sw / sh)
        matrix = _homography_to_quad((sh, sw), quad)
    warp = functools.partial(cv2.warpPerspective, M=matrix, dsize=(fw, fh))
    attenuation = warp(attenuation_src, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    screen = np.isfinite(attenuation)
    anatomy = warp(anatomy_src.astype(np.uint8), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                   borderValue=0).astype(bool) & screen
    # pixels the screen blur mixes with direct exposure or a collimator's shadow are not anatomy
    anatomy = cv2.erode(anatomy.astype(np.uint8), np.ones((5, 5), np.uint8),
                        borderType=cv2.BORDER_CONSTANT, borderValue=1).astype(bool)
    if layout != "whole_field":
        # the screen's rim (a few per cent of its size) may be dropped by the region stage
        rim = max(3, int(round(0.03 * min(fh, fw))))
        inner = cv2.erode(screen.astype(np.uint8), np.ones((2 * rim + 1, 2 * rim + 1), np.uint8),
                          borderType=cv2.BORDER_CONSTANT, borderValue=1)
        anatomy &= inner.astype(bool)
    pattern = _flat_pattern(rng, frame)
    if not illumination_pattern:
        pattern = np.ones_like(pattern)
    transmission = np.where(screen, np.exp(-np.nan_to_num(attenuation, nan=0.0)), 0.0)
    # screen blur (the scintillator's light spread), a px or so
    transmission = cv2.GaussianBlur(transmission.astype(np.float32), (0, 0), rng.uniform(0.6, 1.5))
    exposure = rng.choice(["starved", "low", "normal", "high"], p=[0.2, 0.25, 0.35, 0.2])
    full_scale = 16383.0  # a 14-bit raw
    white_dn = {"starved": rng.uniform(120, 400), "low": rng.uniform(400, 2000),
                "normal": rng.uniform(2000, 9000), "high": rng.uniform(9000, 15500)}[str(exposure)]
    black = float(rng.choice([0.0, 512.0, 2048.0]))
    room = float(rng.choice([0.0, rng.uniform(0.002, 0.01), rng.uniform(0.01, 0.04)]))
    tint = TINTS[tint_name]
    gains = np.array(tint if tint is not None else (1.0,), np.float32)

    def expose(signal: np.ndarray, rng_noise: np.random.Generator) -> np.ndarray:
        # DN = black + white * pattern * (screen light + room light) per channel, Poisson (gain 1 DN
        # per electron) + read noise 3 DN, clipped at full scale
        room_light = room * (0.6 + 0.4 * (np.mgrid[0:fh, 0:fw][1] / fw)).astype(np.float32)
        light = pattern * signal + room_light * (~screen)
        mean = white_dn * light[..., None] * gains
        counts = rng_noise.poisson(np.maximum(mean, 0)).astype(np.float32) + rng_noise.normal(0, 3.0, mean.shape)
        out = np.clip(black + counts, 0, full_scale).astype(np.float32)
        return out if tint is not None else out[..., 0]

    raw = expose(transmission, rng)
    flat = expose(cv2.GaussianBlur(screen.astype(np.float32), (0, 0), 1.0), rng)
    info = {"source": source.name, "layout": layout, "tint": tint_name, "exposure": str(exposure),
            "white_dn": round(float(white_dn)), "black": black, "room": round(room, 4),
            "collimated": collimated or source.name == "RG3_UNCR", "alpha": round(float(alpha), 2)}
    info["family"] = family
    kind = "" if family == "corpus" else f" {family}"
    description = (f"seed {seed}{kind}: {source.name} {layout} {tint_name} {exposure} ({info['white_dn']} DN) "
                   f"room {info['room']}{' collimated' if collimated else ''}")
    return Scenario(seed, description, raw, flat, black, np.where(anatomy, attenuation, np.nan).astype(np.float32),
                    anatomy, screen, pattern, info)


def clipped_fraction(display: np.ndarray, mask: np.ndarray) -> float:
    """Share of ``mask`` pixels at the display's ends (the 8-bit preview's 0 or 255)."""
    values = display[mask]
    if values.size == 0:
        return 0.0
    return float(np.mean((values <= 0.5 / 255) | (values >= 254.5 / 255)))


def evaluate(scenario: Scenario, result) -> dict:
    """Per-invariant figures of a pipeline result (``keep_intermediates=True``) on a scenario.

    * ``blanked``: share of anatomy pixels outside the found region (filled, not shown);
    * ``clipped``: share of anatomy pixels inside the region at the display's ends;
    * ``polarity_r``: Pearson correlation of the display with the true attenuation over the
      anatomy (bone white: positive);
    * ``flat_left``: the share of the flat-field pattern left in the attenuation image: the
      coefficient of ``-log(pattern)`` in a joint fit ``s a_true + b (-log pattern) + c``,
      over ``s`` (1 = uncorrected, 0 = gone), and ``flat_left_se``, how finely the metric can
      read the scenario (:func:`flat_pattern_resolution`).
    """
    anatomy = scenario.anatomy
    shown = anatomy & result.region.mask
    truth = scenario.attenuation[anatomy]
    display = result.display[anatomy]
    figures = {"blanked": float(1.0 - shown.sum() / max(anatomy.sum(), 1)),
               "clipped": clipped_fraction(result.display, shown),
               "polarity_r": float(np.corrcoef(display, truth)[0, 1]) if truth.std() > 0 else 0.0}
    att = result.intermediates.get("attenuation")
    if att is not None and att.shape == anatomy.shape:
        figures["flat_left"] = flat_pattern_left(att, scenario)
        figures["flat_left_se"] = flat_pattern_resolution(scenario)
    return figures


def _masked_blur(values: np.ndarray, mask: np.ndarray, sigma_px: float) -> np.ndarray:
    weight = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), sigma_px)
    blurred = cv2.GaussianBlur(np.where(mask, values, 0).astype(np.float32), (0, 0), sigma_px)
    return blurred / np.maximum(weight, 1e-6)


def _pattern_fit(attenuation: np.ndarray, scenario: Scenario, sigma_px: float) -> tuple[float, float]:
    """``b / s`` of the joint fit (see :func:`flat_pattern_left`) and its standard error (from
    the fit's residual, on one independent sample per blur area ``2 pi sigma_px^2``)."""
    anatomy = scenario.anatomy
    core = cv2.erode(anatomy.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    truth = np.nan_to_num(scenario.attenuation, nan=0.0)
    columns = [_masked_blur(image, anatomy, sigma_px)[core].astype(np.float64)
               for image in (attenuation, truth, -np.log(scenario.flat_pattern))]
    y, truth_low, pattern_low = columns
    if pattern_low.std() < 1e-6:
        return 0.0, 0.0
    design = np.column_stack([truth_low, pattern_low, np.ones_like(y)])
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    scale, pattern_coef = coef[0], coef[1]
    if abs(scale) < 1e-9:
        return float("inf"), float("inf")
    independent = max(core.sum() / (2 * np.pi * sigma_px**2), 4.0)
    residual_var = float(np.mean((y - design @ coef) ** 2)) * core.sum() / independent
    se = np.sqrt(residual_var * np.linalg.pinv(design.T @ design)[1, 1]) / abs(scale)
    return float(abs(pattern_coef / scale)), float(se)


def flat_pattern_left(attenuation: np.ndarray, scenario: Scenario, sigma_px: float = 6.0) -> float:
    """Share of the flat-field pattern left in an attenuation image (1 = uncorrected, 0 = gone).

    An uncorrected illumination pattern ``P`` adds ``-log P`` to the attenuation, so the image
    is modelled as ``y = s a_true + b (-log P) + c`` and fitted jointly, by least squares, over
    the anatomy; ``b / s`` is returned. The image, the truth and the pattern are first
    low-passed inside the anatomy (Gaussian, ``sigma_px``: pixel noise and the zero-mean
    residuals at the anatomy's edges average out, a smooth pattern stays) and the comparison
    is made away from the anatomy's outline. The fit is joint because a chest centred on the
    screen correlates with the pattern (r up to 0.7): fitting the truth first lets it absorb
    part of a real pattern, and leaves in its residual whatever the image's response to the
    anatomy does not share with a straight line, both wrongly charged to the pattern
    (docs/safety.md).
    """
    return _pattern_fit(attenuation, scenario, sigma_px)[0]


def flat_pattern_resolution(scenario: Scenario, sigma_px: float = 6.0) -> float:
    """How finely :func:`flat_pattern_left` can read this scenario: its standard error on the
    frame's own plain flat-field division (camera frame minus black over flat minus black, per
    channel, summed; no pipeline), where it should read 0.

    A small anatomy on a small screen (1000-2000 px) sees little of the pattern that the
    anatomy itself does not follow (0.01-0.02 natural-log units), and the misfit of the
    linear model (log of the blurred transmission, noise) then moves ``b / s`` by 0.2-0.4:
    the plain division read 0.54 and 0.80 on held-out seeds 2009 and 2015 (uncorrected 1.6
    and 1.9), where the pipeline's own reading is no evidence of a pattern left.
    """
    return _pattern_fit(plain_flat_division(scenario), scenario, sigma_px)[1]


def plain_flat_division(scenario: Scenario) -> np.ndarray:
    """The frame's attenuation by a plain flat-field division (camera frame minus black over
    flat minus black, per channel, summed; natural log, bone white), no pipeline."""
    raw = np.atleast_3d(scenario.raw).astype(np.float64) - scenario.black_level
    flat = np.atleast_3d(scenario.flat).astype(np.float64) - scenario.black_level
    divided = (raw / np.maximum(flat, 1.0)).sum(axis=2)
    return -np.log(np.maximum(divided, 1e-3)).astype(np.float32)
