"""Dynamic-range and latitude reduction (stage v) and the display look-up table.

Works on the value-of-interest scaled attenuation image ``x`` (log domain, about 0..1 over
the values of interest). A large-kernel, mask-normalised low-pass separates large-area
variation from detail (Kodak US 6,069,979; Fuji DRC)::

    x_L = blur(x * m) / blur(m)                     (m: region mask; no leakage from outside)
    y   = x_mid + latitude * (x_L - x_mid) + detail_gain * (x - x_L)

with ``latitude`` < 1 (low-frequency gain) and ``detail_gain`` >= 1. A plain blur smears a
strong edge (collimator, skin line, metal) into ``x_L``, so ``x - x_L`` gets a bump on both
sides of the edge and the output a bright/dark halo of the kernel's width. The default
low-pass is therefore edge-aware (docs/algorithms/dynamic_range.md, section 'Halos at strong edges'): the
Gastal-Oliveira domain-transform recursive filter (``cv2.ximgproc.dtFilter``, spatial sigma
``sigma_s``, range sigma ``edge_step``) smooths up to, never across, steps larger than
``edge_step``; those steps stay in ``x_L`` and are compressed by ``latitude`` without a halo.
``sigma_s`` is half the box size ``kernel_fraction x short side`` (the plain blur's scale).
Its guide is the image smoothed by a Gaussian of 1 px, so that pixel noise shortens the
kernel less (in the domain transform every grey-level change lengthens the distance).
Structure well below ``edge_step`` is detail (gain ``detail_gain``); between about a third
of ``edge_step`` and ``edge_step`` it is partly kept in ``x_L`` and so partly compressed.
``edge_step = 0`` selects the plain blur (three box-filter passes, close to a Gaussian).
Measured on a unit-free step of 1.2 (latitude 0.6): overshoot + undershoot / step 0.016
edge-aware vs 0.59 with the plain blur (``tests/core/stages/test_dynamic_range.py``).
:func:`sigmoid_lut` is the final gradation curve mapping the processed values to the display
range.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..param_fields import validate_fields


@dataclass
class DynamicRangeParams:
    """Parameters of dynamic-range reduction and the display curve (TOML ``[dynamic_range]``).

    Attributes
    ----------
    enabled : bool
        Apply the low-frequency compression.
    latitude : float
        Gain of large-area (low-frequency) variation, 0.1 to 1: lower shows thick and thin
        parts (mediastinum and lung) together; 1 = no compression (the default: the contrast
        stage's coarse remapping compresses strong steps without a halo).
    detail_gain : float
        Gain of everything finer than the kernel, 1 to 3.
    kernel_fraction : float
        Size of the low-pass kernel as a fraction of the image's short side (0.01 to 0.3).
    lut_center : float
        Centre of the sigmoid display curve in value-of-interest units (0 to 1).
    lut_width : float
        Width (slope scale) of the sigmoid in value-of-interest units (0.05 to 2);
        smaller = steeper, more global contrast.
    edge_step : float
        Steps larger than this (value-of-interest units) are kept out of the low-pass so they
        cause no halo (edge-aware low-pass); 0 = plain blur (halos at strong edges).
    max_clipped_percent : float
        Largest share (%) of the anatomy (inside the region, outside direct exposure) that
        may land on the display's black or white end: when the processed values spread beyond
        the curve's range they are compressed (never expanded) onto it, see
        :func:`fit_to_display` (0 to 100; 100 = never adjust).
    anatomy_floor : float
        Display grey of the darkest anatomy in a frame with direct exposure (0 to 0.3; 0 =
        off): where the frame has direct exposure (the beam beside the body, kept black), the
        anatomy's darkest values are lifted to about this grey so the skin line and thin soft
        tissue stand out from the black background (:func:`lift_anatomy_foot`). The lift
        covers the whole body, so dark enclosed anatomy (lungs) shown below
        ``FOOT_TOE_SPAN * anatomy_floor`` is lifted too, with its contrast there reduced by up
        to half. Frames without direct exposure are unchanged.
    """

    enabled: bool = field(default=True, metadata={"help": "compress large-area (low-frequency) variation"})
    latitude: float = field(default=1.0, metadata={
        "help": "gain of large-area variation: lower shows thick and thin parts together; 1 = off",
        "unit": "gain", "min": 0.1, "max": 1.0})
    detail_gain: float = field(default=1.0, metadata={
        "help": "gain of detail finer than the kernel", "unit": "gain", "min": 1.0, "max": 3.0})
    kernel_fraction: float = field(default=0.05, metadata={
        "help": "low-pass kernel size as a fraction of the image's short side", "unit": "fraction",
        "min": 0.01, "max": 0.3})
    lut_center: float = field(default=0.5, metadata={
        "help": "centre of the sigmoid display curve", "unit": "VOI units (0..1)", "min": 0.0, "max": 1.0})
    lut_width: float = field(default=0.6, metadata={
        "help": "width of the sigmoid display curve; smaller = steeper", "unit": "VOI units", "min": 0.05, "max": 2.0})
    edge_step: float = field(default=0.2, metadata={
        "help": "steps larger than this stay out of the low-pass (no halo at strong edges); 0 = plain blur",
        "unit": "VOI units", "min": 0.0, "max": 1.0})
    max_clipped_percent: float = field(default=0.5, metadata={
        "help": "largest share of the anatomy shown as pure black or white; the processed values are "
                "compressed onto the display curve when more would clip (100 = never adjust)",
        "unit": "%", "min": 0.0, "max": 100.0})
    anatomy_floor: float = field(default=0.12, metadata={
        "help": "display grey of the darkest anatomy when the frame has direct exposure (the beam beside the "
                "body stays black), so the skin line shows; dark lungs are lifted too; 0 = off",
        "unit": "display fraction", "min": 0.0, "max": 0.3})

    def __post_init__(self) -> None:
        validate_fields(self, "dynamic_range")


def masked_lowpass(image: np.ndarray, mask: np.ndarray | None, size_px: int) -> np.ndarray:
    """Mask-normalised low-pass: ``blur(x * m) / blur(m)`` with three box-filter passes.

    Parameters
    ----------
    image : ndarray, float32, (H, W)
    mask : ndarray, bool, (H, W) or None
        Pixels that may contribute; None = all.
    size_px : int
        Box size of each pass (odd, >= 3); three passes approximate a Gaussian of
        sigma ~ size * 0.5.

    Returns
    -------
    ndarray, float32, (H, W)
        Outside the mask the value extends the nearest region values.
    """
    size_px = max(3, int(size_px) | 1)
    x = np.asarray(image, np.float32)
    # Blur a downsampled copy when the kernel is large: same result, much cheaper.
    factor = max(1, size_px // 24)
    h, w = x.shape
    if factor > 1:
        sw, sh = max(4, w // factor), max(4, h // factor)
        xs = cv2.resize(x, (sw, sh), interpolation=cv2.INTER_AREA)
        ms = None if mask is None else cv2.resize(mask.astype(np.float32), (sw, sh), interpolation=cv2.INTER_AREA)
        k = max(3, int(round(size_px / factor)) | 1)
    else:
        xs, ms, k = x, (None if mask is None else mask.astype(np.float32)), size_px
    if ms is None:
        num = xs.copy()
        for _ in range(3):
            num = cv2.blur(num, (k, k), borderType=cv2.BORDER_REFLECT)
        low = num
    else:
        num, den = xs * ms, ms.copy()
        for _ in range(3):
            num = cv2.blur(num, (k, k), borderType=cv2.BORDER_REFLECT)
            den = cv2.blur(den, (k, k), borderType=cv2.BORDER_REFLECT)
        valid = den > 1e-3
        low = np.where(valid, num / np.maximum(den, 1e-6), np.float32(np.nan))
        if not np.all(valid):
            fill = float(np.nanmedian(low)) if np.any(valid) else 0.0
            low = np.where(valid, low, np.float32(fill))
    low = low.astype(np.float32)
    if factor > 1:
        low = cv2.resize(low, (w, h), interpolation=cv2.INTER_LINEAR)
    return low


def edge_aware_lowpass(image: np.ndarray, mask: np.ndarray | None, sigma_px: float,
                       edge_step: float) -> np.ndarray:
    """Edge-aware low-pass (domain transform) that ignores pixels outside ``mask``.

    Outside the mask the image is first replaced by the mask-normalised plain low-pass of
    the region (:func:`masked_lowpass`), a smooth continuation of the inside values, so the
    outside neither leaks into the region nor forms an edge at the mask border; then one
    domain-transform recursive filter pass set (``cv2.ximgproc.dtFilter``, three iterations)
    runs, guided by the filled image smoothed by a Gaussian of 1 px.

    Parameters
    ----------
    image : ndarray, float32, (H, W)
        Value-of-interest scaled image.
    mask : ndarray, bool, (H, W) or None
        Pixels that may contribute; None = all.
    sigma_px : float
        Spatial standard deviation of the filter in pixels (in flat areas).
    edge_step : float
        Range sigma in image units: the filter does not smooth across steps much larger.

    Returns
    -------
    ndarray, float32, (H, W)
        Outside the mask the value extends the nearest region values.
    """
    x = np.ascontiguousarray(image, np.float32)
    if mask is not None and not mask.all():
        fill = masked_lowpass(x, mask, max(3, int(round(2 * sigma_px))))
        x = np.where(mask, x, fill)
    guide = cv2.GaussianBlur(x, (0, 0), 1.0)
    # three iterations: one leaves visible stripes along the filter's scan directions
    return cv2.ximgproc.dtFilter(guide, x, float(sigma_px), float(edge_step),
                                 mode=cv2.ximgproc.DTF_RF, numIters=3).astype(np.float32, copy=False)


def reduce_dynamic_range(image: np.ndarray, mask: np.ndarray | None = None,
                         params: DynamicRangeParams | None = None) -> np.ndarray:
    """Compress large-area variation of a VOI-scaled log image, keep (or boost) detail.

    Parameters
    ----------
    image : ndarray, float32, (H, W)
        Value-of-interest scaled attenuation (about 0..1).
    mask : ndarray, bool, (H, W), optional
        The region (screen / collimated field); the low-pass ignores pixels outside it.
    params : DynamicRangeParams, optional

    Returns
    -------
    ndarray, float32, (H, W)
        ``x_mid + latitude (x_L - x_mid) + detail_gain (x - x_L)``, ``x_mid`` the median of
        the low-pass inside the region.
    """
    params = params or DynamicRangeParams()
    x = np.asarray(image, np.float32)
    if not params.enabled or (params.latitude == 1.0 and params.detail_gain == 1.0):
        return x.copy()
    size = max(3, int(round(params.kernel_fraction * min(x.shape))))
    if params.edge_step > 0:
        # three box passes of size k have sigma ~ 0.5 k: the same scale for both low-passes
        low = edge_aware_lowpass(x, mask, 0.5 * size, params.edge_step)
    else:
        low = masked_lowpass(x, mask, size)
    step = max(1, int(np.sqrt(low.size / 1_000_000)))  # median of a regular subsample
    sub = low[::step, ::step]
    sub_mask = None if mask is None else mask[::step, ::step]
    mid = float(np.median(sub[sub_mask] if sub_mask is not None and sub_mask.any() else sub))
    out = (x - low) * np.float32(params.detail_gain)
    out += low * np.float32(params.latitude)
    out += np.float32(mid * (1.0 - params.latitude))
    return out


def sigmoid_lut(image: np.ndarray, params: DynamicRangeParams | None = None) -> np.ndarray:
    """Display curve: a sigmoid rescaled so that VOI 0 -> 0.02 and VOI 1 -> 0.98.

    Parameters
    ----------
    image : ndarray, float32
        Processed values in value-of-interest units.
    params : DynamicRangeParams, optional
        ``lut_center`` and ``lut_width``.

    Returns
    -------
    ndarray, float32
        Display values clipped to [0, 1].
    """
    params = params or DynamicRangeParams()
    c, w = float(params.lut_center), float(params.lut_width)
    s0 = 1.0 / (1.0 + np.exp(-(0.0 - c) / w))
    s1 = 1.0 / (1.0 + np.exp(-(1.0 - c) / w))
    # y = 0.02 + 0.96 (s(x) - s0) / (s1 - s0), computed in place to save memory
    out = np.asarray(image, np.float32) - np.float32(c)
    out *= np.float32(-1.0 / w)
    np.exp(out, out=out)
    out += 1.0
    np.reciprocal(out, out=out)
    out -= np.float32(s0)
    out *= np.float32(0.96 / (s1 - s0))
    out += 0.02
    np.clip(out, 0.0, 1.0, out=out)
    return out


#: Display values that count as clipped: the 8-bit preview's 0 and 255.
CLIPPED_LOW, CLIPPED_HIGH = 0.5 / 255.0, 254.5 / 255.0


def lut_input_range(params: DynamicRangeParams | None = None) -> tuple[float, float]:
    """Processed values that :func:`sigmoid_lut` maps to the unclipped ends (0.5/255, 254.5/255)."""
    params = params or DynamicRangeParams()
    c, w = float(params.lut_center), float(params.lut_width)
    s0 = 1.0 / (1.0 + np.exp(-(0.0 - c) / w))
    s1 = 1.0 / (1.0 + np.exp(-(1.0 - c) / w))
    ends = []
    for y in (CLIPPED_LOW, CLIPPED_HIGH):
        s = s0 + (y - 0.02) * (s1 - s0) / 0.96
        s = min(max(s, 1e-9), 1.0 - 1e-9)
        ends.append(c + w * float(np.log(s / (1.0 - s))))
    return ends[0], ends[1]


def fit_to_display(image: np.ndarray, sample: np.ndarray, params: DynamicRangeParams | None = None) -> dict:
    """Keep the anatomy off the display's ends: compress (never expand) processed values in place.

    Contrast and detail gains push values of the anatomy beyond the value-of-interest range,
    and the display curve then burns them out to pure black or white. With ``q =
    max_clipped_percent``, the ``q/2`` and ``100 - q/2`` percentiles of ``sample`` (the
    processed anatomy values) are brought inside :func:`lut_input_range`: by a shift when
    their span fits, else by an affine compression onto it. Values already inside are left
    alone (gain 1, shift 0), so images that do not clip keep their look.

    Parameters
    ----------
    image : ndarray, float32
        Processed values in value-of-interest units; modified in place.
    sample : ndarray
        Processed anatomy values (a subsample of ``image``).
    params : DynamicRangeParams, optional

    Returns
    -------
    dict
        ``gain`` and ``offset`` applied (``image <- gain * image + offset``).
    """
    params = params or DynamicRangeParams()
    q = float(params.max_clipped_percent)
    values = np.asarray(sample, np.float32).ravel()
    if q >= 100.0 or values.size < 16:
        return {"gain": 1.0, "offset": 0.0}
    u0, u1 = lut_input_range(params)
    p_lo, p_hi = (float(v) for v in np.percentile(values, [0.5 * q, 100.0 - 0.5 * q]))
    gain, offset = 1.0, 0.0
    if p_hi - p_lo > u1 - u0:
        gain = (u1 - u0) / (p_hi - p_lo)
        offset = u0 - gain * p_lo
    elif p_lo < u0:
        offset = u0 - p_lo
    elif p_hi > u1:
        offset = u1 - p_hi
    if gain != 1.0:
        image *= np.float32(gain)
    if offset != 0.0:
        image += np.float32(offset)
    return {"gain": round(gain, 4), "offset": round(offset, 4)}


#: The foot lift fades out at this multiple of ``anatomy_floor``: the display's slope at the
#: anatomy's darkest values is at least half the curve's (``1 - 2 / FOOT_TOE_SPAN``).
FOOT_TOE_SPAN = 4.0


def lift_anatomy_foot(display: np.ndarray, weight: np.ndarray, floor: float) -> None:
    """Lift the darkest anatomy off black, in place: ``y + floor * weight * (1 - y / t)^2`` below ``t``.

    ``t = FOOT_TOE_SPAN * floor``: a toe that lifts display value 0 to ``floor`` and joins the
    curve smoothly (same value and slope) at ``t``; above ``t`` nothing changes, and the
    result stays increasing in ``y`` (its slope is at least ``1 - 2 / FOOT_TOE_SPAN``).
    ``weight`` (0..1, same shape) is the anatomy as opposed to direct exposure, feathered over
    a pixel or two at the skin (:func:`napari_dslrxr.core.display.anatomy_foot_weight`), so the
    beam stays black and the step to grey lies on the skin line, where the attenuation rises
    steeply, not on an iso-value line through the beam's glow.

    Parameters
    ----------
    display : ndarray, float32
        Display values in [0, 1] (after :func:`sigmoid_lut`); modified in place.
    weight : ndarray, float32
        Where to lift (1 = anatomy, 0 = direct exposure).
    floor : float
        Display value given to the anatomy's black (0 = no change).
    """
    if floor <= 0:
        return
    top, scale = foot_toe(floor)
    add_toe(display, np.asarray(weight, np.float32) * scale, top)


def foot_toe(floor: float) -> tuple[float, np.float32]:
    """The toe's end ``t`` (display units) and the weight's scale ``floor / t^2`` for :func:`add_toe`."""
    top = FOOT_TOE_SPAN * float(floor)
    return top, np.float32(floor / top ** 2)


def add_toe(display: np.ndarray, scaled_weight: np.ndarray, top: float) -> None:
    """``display += scaled_weight * (top - min(display, top))^2`` in place (:func:`lift_anatomy_foot`'s body)."""
    toe = np.minimum(display, np.float32(top))
    np.subtract(np.float32(top), toe, out=toe)
    np.square(toe, out=toe)
    toe *= scaled_weight
    display += toe
