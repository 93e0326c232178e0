"""Colour path of the impulse stage: hue, saturation and value of photon counts, their noise
weights, and the H, S, V passes."""

from __future__ import annotations

import math

import numpy as np

from ...progress import Steps
from .detection import _clean_channel, channel_steps
from .noise_model import _count_variance, _gain, _NoiseModel
from .params import _FLOAT, _POLARITY_SIGN, ImpulseParams, ImpulseResult, _to_dtype


def _erode(mask: np.ndarray, size_px: int) -> np.ndarray:
    """Pixels whose whole ``size_px`` square window is in ``mask`` (bool; border replicated)."""
    import cv2

    kernel = np.ones((size_px, size_px), np.uint8)
    eroded = cv2.erode(np.ascontiguousarray(mask).view(np.uint8), kernel,
                       borderType=cv2.BORDER_REPLICATE)
    return eroded.view(bool)


def _median3(x: np.ndarray) -> np.ndarray:
    """3x3 median (float32, new array, replicated border)."""
    import cv2

    return cv2.medianBlur(np.ascontiguousarray(x, dtype=_FLOAT), 3)


def _noise_level(v: np.ndarray) -> np.ndarray:
    """Level of V that sets a pixel's count noise in the S and H weights (float32, new array):
    the lower of the pixel's own value and its 3x3 median.

    The median keeps a pixel's own noise from raising its own weight (a count high by
    chance would), but on fine texture (a mesh's dark nodes, 2-5 px periods) it is set by
    brighter neighbours and overstates the pixel's precision: tinted frames filled with a
    mesh had 0.2-0.8 % of their pixels flagged in H and S there (docs/impulse.md). The
    lower of the two never promises more precision than either estimate.
    """
    level = _median3(v)
    np.minimum(level, v, out=level)
    return level


def _weight_model(model_v: _NoiseModel | None, v: np.ndarray) -> _NoiseModel | None:
    """V's noise model for the S and H weights, or None (plain Poisson, variance proportional
    to the counts) when its line is not credible on this frame.

    The weights use only the shape of the count variance. A line ``a c + b`` with ``b < 0``
    reaches zero at ``-b/a``, the camera's offset less a little; where a frame's V lies well
    below that (its 1st percentile lower by more than 3 sigmas of the model's dark-end
residual, about the read noise), the line was set by
    something other than the offset: V's fit on a frame filled with a mesh (levels of one
    narrow range, texture in the residual) gave a zero at 316 counts on a frame whose mesh
    nodes hold 95, which made the nodes' variance the floor and their H weight too high
    (0.57 % of that frame flagged in H).
    """
    if model_v is None or model_v.a <= 0 or model_v.b >= 0:
        return model_v
    step_r, step_c = max(1, v.shape[0] // 512), max(1, v.shape[1] // 512)
    darkest = float(np.percentile(v[::step_r, ::step_c], 1))
    if -model_v.b / model_v.a > darkest + 3.0 * math.sqrt(max(model_v.var_floor, 0.0)):
        return None
    return model_v


def _saturation_weight(s: np.ndarray, v: np.ndarray, model: _NoiseModel | None) -> np.ndarray:
    """Inverse noise of the saturation, normalised to a median of 1 (float32, new array).

    ``S = 1 - min/max`` with ``max = V`` and ``min = V (1 - S)``; first-order propagation:
    ``Var[S] = (Var[min] + (1 - S)^2 Var[max]) / V^2`` with the count variances of
    :func:`_count_variance`. With Poisson counts and no offset this is
    ``G (1 - S)(2 - S) / V``; over a black level in the dark it is about
    ``2 sigma_e^2 / V^2``, far smaller than a ``1/V`` law scaled from the screen would say.
    Computed in blocks of rows (bounded temporaries on 24 Mpx frames).
    """
    height, width = s.shape
    weight = np.empty((height, width), _FLOAT)
    rows_per_block = max(1, (1 << 20) // max(width, 1))
    for r0 in range(0, height, rows_per_block):
        r1 = min(height, r0 + rows_per_block)
        v_block = v[r0:r1]
        one_minus_s = np.subtract(_FLOAT(1.0), s[r0:r1], dtype=_FLOAT)
        np.clip(one_minus_s, _FLOAT(0.0), _FLOAT(1.0), out=one_minus_s)
        var_total = _count_variance(v_block * one_minus_s, model)
        one_minus_s *= one_minus_s
        one_minus_s *= _count_variance(v_block, model)
        var_total += one_minus_s
        np.sqrt(var_total, out=var_total)
        np.divide(np.maximum(v_block, _FLOAT(0.0)), var_total, out=weight[r0:r1])
    weight /= max(float(np.median(weight[::7, ::7])), 1e-12)
    return weight


def rgb_to_hsv_counts(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split RGB (any real dtype, counts) into hue, saturation and value, float32.

    Uses OpenCV's float conversion (the standard hexcone formulas, as
    ``skimage.color.rgb2hsv``, but with V kept in the input's units).

    Returns
    -------
    hue : ndarray, float32, in [0, 1] (0 red, 1/3 green, 2/3 blue; 0 where undefined; 1 = 0)
    saturation : ndarray, float32, in [0, 1] ((max - min)/max; 0 where max is 0)
    value : ndarray, float32, max(R, G, B) in the input's units (counts)
    """
    import cv2

    height, width = rgb.shape[:2]
    hue, sat, val = (np.empty((height, width), _FLOAT) for _ in range(3))
    rows_per_block = max(1, (1 << 20) // max(width, 1))  # bounded temporaries (~12 MB)
    for r0 in range(0, height, rows_per_block):
        r1 = min(height, r0 + rows_per_block)
        block = cv2.cvtColor(np.ascontiguousarray(rgb[r0:r1], dtype=_FLOAT), cv2.COLOR_RGB2HSV)
        cv2.split(block, [hue[r0:r1], sat[r0:r1], val[r0:r1]])  # into the planes (no strided copies)
    # Hue can round up to exactly 1.0 (360 degrees); every use wraps it modulo 1.
    hue *= _FLOAT(1.0 / 360.0)
    return hue, sat, val


def hsv_counts_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rgb_to_hsv_counts`; float64 (..., 3) in the units of ``v``."""
    h = np.asarray(h, np.float64) % 1.0
    s = np.clip(np.asarray(s, np.float64), 0.0, 1.0)
    v = np.asarray(v, np.float64)
    h6 = h * 6.0
    sector = np.floor(h6).astype(np.int64) % 6
    f = h6 - np.floor(h6)
    p = v * (1 - s)
    q = v * (1 - s * f)
    t = v * (1 - s * (1 - f))
    choices_r = [v, q, p, p, t, v]
    choices_g = [t, v, v, q, p, p]
    choices_b = [p, p, t, v, v, q]
    out = np.empty(h.shape + (3,), np.float64)
    out[..., 0] = np.choose(sector, choices_r)
    out[..., 1] = np.choose(sector, choices_g)
    out[..., 2] = np.choose(sector, choices_b)
    return out


def dominant_hue(h: np.ndarray, valid: np.ndarray, bins: int = 360) -> float:
    """Most frequent hue (bin centre in [0, 1)) among ``valid`` pixels (regular subsample)."""
    step = max(1, int(math.sqrt(h.size / 1_000_000)))
    sel = h[::step, ::step][valid[::step, ::step]]
    if sel.size == 0:
        return 0.0
    counts = np.bincount(np.minimum((sel * bins).astype(np.int64), bins - 1), minlength=bins)
    return (int(np.argmax(counts)) + 0.5) / bins


def hsv_steps(params: ImpulseParams) -> int:
    """Progress steps of :func:`_remove_hsv`: the HSV conversion, V's, S's and H's passes, and
    the RGB rebuild."""
    return 2 + sum(channel_steps(p) for p in (params.passes_v, params.passes_s, params.passes_h))


def _remove_hsv(image: np.ndarray, params: ImpulseParams, steps: Steps) -> ImpulseResult:
    # Channels are cleaned in place: the cleaned H, S, V are the input's wherever their
    # mask is False, so they rebuild the RGB of every changed pixel.
    h, s, v = rgb_to_hsv_counts(image)
    steps.advance()
    v_top = float(np.percentile(v[:: max(1, v.shape[0] // 512), :: max(1, v.shape[1] // 512)], 99))
    masks: dict[str, np.ndarray] = {}
    gain: dict[str, float] = {}
    rate: dict[str, float] = {}
    noise: dict[str, tuple[float, float]] = {}

    def _store(name, mask, model, photon):
        masks[name] = mask
        gain[name] = _gain(model, params) if photon else float("nan")
        rate[name] = model.pulse_rate if model else float("nan")
        noise[name] = (model.a, model.b) if model else (float("nan"), float("nan"))

    # V first: bright zingers are clearest there, and a cleaner V defines the hue mask better.
    v_new, mask_v, model_v = _clean_channel(v, passes=params.passes_v, params=params,
                                            photon_counting=True, polarity=_POLARITY_SIGN[params.spots],
                                            in_place=True, steps=steps, channels=image,
                                            texture_sides="two_signed")
    _store("V", mask_v, model_v, True)
    # S and H are ratios of photon counts. Their noise follows from that of the counts,
    # Var[c] = G (c - o) + sigma_e^2 (V's fitted model, read-noise floor included; see
    # _count_variance and _saturation_weight). Residuals are weighted by the inverse of that noise (normalised
    # to a median of 1), so that one constant Gaussian variance fits the whole image, the
    # dark surround of the screen (read noise over a black level) included.
    # The weights use 3x3 medians of S and V: a pixel's own noise must not set its own
    # weight (a count low by chance raises S and would also raise its weight). For V the
    # lower of the median and the pixel's own value (_noise_level: fine texture).
    weight_model = _weight_model(model_v, v_new)
    v_local = _noise_level(v_new)
    s_local = _median3(s)
    weight_s = _saturation_weight(s_local, v_local, weight_model)
    del v_local  # recomputed for the hue (memory: 24 Mpx frames)
    # The first-order propagation holds where max - min is well above its noise; in the
    # unsaturated dark surround S is the range of three nearly equal noisy counts and the
    # weighted residual is narrower there. The constant variance is fitted where S is
    # defined (as for hue), so that the screen's variance is not underestimated.
    s_defined = s_local >= _FLOAT(params.min_saturation)
    del s_local
    s_new, mask_s, model_s = _clean_channel(s, passes=params.passes_s, params=params,
                                            photon_counting=False, polarity=0, value_range=1.0,
                                            residual_weight=weight_s, in_place=True,
                                            fit_region=s_defined, steps=steps)
    del s_defined
    _store("S", mask_s, model_s, False)
    del weight_s
    hue_valid = (s_new >= params.min_saturation) & (v_new >= params.min_value_fraction * v_top)
    # A hue is tested against the hues of its detection samples, so they must be defined too:
    # a pixel just above the saturation cut in the dark surround would otherwise be compared
    # with the random hues of its unsaturated neighbours.
    hue_valid = _erode(hue_valid, params.window_px)
    hue_mode = dominant_hue(h, hue_valid)
    h_rot = h
    h_rot += _FLOAT(0.5 - hue_mode)
    h_rot -= np.floor(h_rot)
    # Hue noise: sqrt(Var[V]) / (V S) (the hexcone hue is a difference of two channels over
    # max - min = V S).
    v_local = _noise_level(v_new)
    weight_h = _count_variance(v_local, weight_model)
    np.sqrt(weight_h, out=weight_h)
    np.divide(v_local, weight_h, out=weight_h)
    del v_local
    weight_h *= s_new
    typical = weight_h[::7, ::7][hue_valid[::7, ::7]]
    weight_h /= max(float(np.median(typical)) if typical.size else 1.0, 1e-12)
    h_new, mask_h, model_h = _clean_channel(h_rot, passes=params.passes_h, params=params,
                                            photon_counting=False, polarity=0,
                                            valid=hue_valid, circular=True, value_range=1.0,
                                            residual_weight=weight_h, in_place=True, steps=steps)
    del weight_h
    _store("H", mask_h, model_h, False)
    out = image.copy()
    changed = mask_h | mask_s | mask_v
    if changed.any():
        rows, cols = np.nonzero(changed)
        hh = (h_new[rows, cols] + (hue_mode - 0.5)) % 1.0
        rgb = hsv_counts_to_rgb(hh, s_new[rows, cols], v_new[rows, cols])
        out[rows, cols] = _to_dtype(rgb, image.dtype)
    steps.advance()
    return ImpulseResult(out, {"H": mask_h, "S": mask_s, "V": mask_v}, gain, rate, noise)
