"""Flat-field correction (stage ii): ``C = (R - D) / (F - D) * mean(F - D)``, per colour channel.

``R`` is the radiograph, ``F`` the open-beam (flat) frame taken with the same camera settings
and ``D`` the dark offset: a dark frame (X-rays off) or, without one, the raw black level.
Several flats are combined by a pixel-wise median (which also removes pulses that hit only
one of them); a single flat is pulse-cleaned with a switching median. The flat is then
smoothed with a small Gaussian over its lit area only (so the screen border keeps its level),
so that its own photon noise is not stamped onto every corrected radiograph (set
``flat_smoothing_px = 0`` when the flat carries fine fixed-pattern structure, such as
scintillator or readout banding, that must be divided out). See docs/algorithms/flatfield.md. The result
stays in counts: the normalisation by the mean of ``F - D`` over the exposed area keeps the
photon statistics of the radiograph, which the later stages (grey conversion, log domain)
rely on.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import InputError, ParameterError
from ..param_fields import validate_fields
from ..progress import ProgressCallback, Steps
from ..robust import robust_sigma


@dataclass
class FlatFieldParams:
    """Parameters of the flat-field stage (TOML section ``[flatfield]``).

    Attributes
    ----------
    enabled : bool
        Apply the correction when a flat frame is given.
    flat_smoothing_px : float
        Standard deviation (pixels) of the Gaussian applied to the combined flat; 0 keeps
        every fine structure of the flat (0 to 200).
    min_flat_fraction : float
        The denominator ``F - D`` is clamped at this fraction of its 99.5th percentile, so
        that unexposed pixels (outside the screen) are not divided by noise (0 to 1).
    clean_flat_pulses : bool
        Remove bright pulses from a single flat or dark frame before using it.
    black_level_counts : float
        Offset (counts) subtracted when no dark frame is given and the input carries no
        black level of its own.
    pulse_threshold_sigma : float
        A pixel of a reference frame is a pulse when it exceeds its 5x5 median by this many
        noise standard deviations (3 to 50).
    """

    enabled: bool = field(default=True, metadata={"help": "apply the flat-field correction when a flat frame is given"})
    flat_smoothing_px: float = field(default=4.0, metadata={
        "help": "Gaussian sigma applied to the combined flat, so its own noise is not added; "
                "0 keeps fine fixed-pattern structure (banding)", "unit": "px", "min": 0.0, "max": 200.0})
    min_flat_fraction: float = field(default=0.05, metadata={
        "help": "clamp F - D at this fraction of its 99.5th percentile (unexposed pixels are not divided by noise)",
        "unit": "fraction", "min": 0.0, "max": 1.0})
    clean_flat_pulses: bool = field(default=True, metadata={
        "help": "remove bright pulses from a single flat or dark frame with a switching median"})
    black_level_counts: float = field(default=0.0, metadata={
        "help": "offset subtracted when no dark frame is given (camera raw files supply their own)",
        "unit": "counts", "min": 0.0, "max": 65535.0})
    pulse_threshold_sigma: float = field(default=6.0, metadata={
        "help": "a reference-frame pixel is a pulse when it exceeds its 5x5 median by this many noise sigmas",
        "unit": "sigma", "min": 3.0, "max": 50.0})

    def __post_init__(self) -> None:
        validate_fields(self, "flatfield")


@dataclass
class FlatReference:
    """A prepared flat-field reference, reusable for every radiograph of a session.

    Attributes
    ----------
    offset : ndarray, float32, (H, W[, 3]) or (C,) or scalar
        Dark offset ``D`` in counts, subtracted from the radiograph.
    denominator : ndarray or None, float32, (H, W[, 3])
        ``F - D`` combined, cleaned, smoothed and clamped (counts); None without a flat.
    scale : ndarray, float32, (C,) or scalar
        Mean of ``F - D`` over the exposed area, per channel (counts).
    n_flats : int
        How many flat frames were combined.
    cleaned_pulses : int
        Pulse pixels replaced in the reference frames.
    saturated_fraction : float
        Largest share, over the flats and their channels, of pixels sitting at the frame's
        maximum value (a clipped plateau: the flat field is wrong there); 0 when none.
    saturated_level_counts : float
        That maximum (counts); NaN when nothing is saturated.
    """

    offset: np.ndarray
    denominator: np.ndarray | None
    scale: np.ndarray
    n_flats: int = 0
    cleaned_pulses: int = 0
    saturated_fraction: float = 0.0
    saturated_level_counts: float = float("nan")


#: A flat channel counts as clipped when more than this share of its pixels sit exactly at its
#: maximum (a noisy exposure repeats its maximum on a handful of pixels at most), but not all of
#: them (a constant synthetic flat is not a clipped one).
SATURATED_FLAT_FRACTION = 0.001


def saturated_flat_message(reference: FlatReference) -> str:
    """The warning for a reference whose flat was clipped ("" when it was not); one text for
    ``dslrxr run`` and the widget."""
    if not reference.saturated_fraction > 0:
        return ""
    return (f"flat frame saturated: {100 * reference.saturated_fraction:.1f} % of its pixels sit at its maximum "
            f"({reference.saturated_level_counts:.0f} counts) in one channel, so the flat field is wrong there "
            "(give flats exposed below the camera's white level)")


def saturated_plateau(frames: Sequence[np.ndarray]) -> tuple[float, float]:
    """Share of pixels at the maximum of the most clipped channel of ``frames``, and that level.

    A camera clips at its white level, so an over-exposed flat has a plateau of identical
    values at its maximum; returns ``(0.0, nan)`` when no channel has one above
    :data:`SATURATED_FLAT_FRACTION` (or when a channel is constant).
    """
    worst, level = 0.0, float("nan")
    for frame in frames:
        arr = np.asarray(frame)
        chans = arr.reshape(arr.shape[0], arr.shape[1], -1)
        for c in range(chans.shape[2]):
            plane = chans[..., c]
            top = plane.max()
            share = float(np.count_nonzero(plane == top)) / plane.size
            if SATURATED_FLAT_FRACTION < share < 0.99 and share > worst:
                worst, level = share, float(top)
    return worst, level


def remove_bright_pulses(frame: np.ndarray, threshold_sigma: float = 6.0,
                         offset_counts=0.0, *, check: Callable[[], object] | None = None) -> tuple[np.ndarray, int]:
    """Replace bright impulsive pixels of a reference frame by their 5x5 median.

    A switching median for flat and dark frames. With ``m`` the 5x5 median and ``r = x - m``
    the residual, the noise model is photon noise on the signal above the dark offset plus a
    constant (read noise)::

        var(r) = a + b * max(m - offset, 0)

    ``b`` from the pixels above a quarter of the brightest level (robust: 1.4826 MAD of
    ``r / sqrt(m - offset)``), ``a`` from the darkest pixels (1.4826 MAD of ``r``; ``b`` x 1
    count when the frame has no dark area). A pixel is a pulse when ``r > k sqrt(var)``
    (``k = threshold_sigma``); its 8 neighbours join it when ``r > 3 sqrt(var)`` (pulses
    cover 1 to 5 pixels; a blind dilation would take the noise around them as well).

    Parameters
    ----------
    frame : ndarray, float32 or uint16, (H, W) or (H, W, C)
        Linear counts.
    threshold_sigma : float
        Detection threshold in noise standard deviations.
    offset_counts : float or sequence of float
        Dark offset (counts, per channel or one for all) under the signal: the photon noise
        grows with ``m - offset``, not with ``m``.
    check : callable, optional
        Called between channels (a progress report that may stop the stage by raising).

    Returns
    -------
    cleaned : ndarray, float32
        Same shape; unflagged pixels unchanged.
    n_replaced : int
        Number of replaced values.
    """
    arr = np.asarray(frame)
    if arr.dtype not in (np.uint16, np.float32):
        arr = arr.astype(np.float32)
    arr = np.ascontiguousarray(arr)
    if arr.ndim == 3 and arr.shape[2] not in (1, 3, 4):
        raise InputError("reference frame", f"unsupported channel count {arr.shape[2]}")
    # whole-array median (all channels at once), native dtype: uint16 is about twice as fast
    med = cv2.medianBlur(arr, 5)
    arr3 = arr if arr.ndim == 3 else arr[..., None]
    med = med.reshape(arr3.shape)
    n_channels = arr3.shape[2]
    offsets = np.broadcast_to(np.asarray(offset_counts, np.float64).reshape(-1), (n_channels,))
    step = max(1, int(np.sqrt(arr3.shape[0] * arr3.shape[1] / 250_000)))
    high = np.empty(arr3.shape, bool)
    low = np.empty(arr3.shape, bool)
    for c in range(n_channels):
        if check is not None:
            check()
        a, b = _pulse_noise_model(arr3[::step, ::step, c], med[::step, ::step, c], offsets[c])
        if arr.dtype == np.uint16:
            # thresholds tabulated over all 65536 median levels: the full-size work stays uint16
            levels = np.arange(65536, dtype=np.float64)
            sd = np.sqrt(a + b * np.maximum(levels - offsets[c], 0.0))
            for out, k in ((high, threshold_sigma), (low, 3.0)):
                table = np.floor(np.minimum(levels + k * sd, 65535)).astype(np.uint16)
                out[..., c] = arr3[..., c] > table[med[..., c]]
        else:
            m = med[..., c].astype(np.float32)
            sd = np.maximum(m - np.float32(offsets[c]), 0)
            sd *= np.float32(b)
            sd += np.float32(a)
            np.sqrt(sd, out=sd)
            residual = arr3[..., c] - m
            high[..., c] = residual > np.float32(threshold_sigma) * sd
            low[..., c] = residual > 3.0 * sd
    grown = cv2.dilate(high.view(np.uint8), np.ones((3, 3), np.uint8)).view(bool).reshape(high.shape)
    pulses = high | (grown & low)
    pulses = pulses.reshape(arr.shape)
    values = arr.astype(np.float32)
    np.copyto(values, med.reshape(arr.shape), where=pulses)
    return values, int(np.count_nonzero(pulses))


def _pulse_noise_model(values: np.ndarray, median: np.ndarray, offset: float) -> tuple[float, float]:
    """``(a, b)`` of ``var(x - m) = a + b max(m - offset, 0)`` from a subsample (robust)."""
    x = values.astype(np.float64).ravel()
    m = median.astype(np.float64).ravel()
    signal = np.maximum(m - offset, 0.0)
    residual = x - m
    top = float(np.percentile(signal, 99.5))
    bright = signal > 0.25 * top
    if top > 0 and np.count_nonzero(bright) > 100:
        scaled = residual[bright] / np.sqrt(signal[bright])
        b = robust_sigma(scaled) ** 2
    else:
        b = 0.0
    dark = signal < 0.05 * top if top > 0 else np.ones(signal.shape, bool)
    if np.count_nonzero(dark) > 100:
        r = residual[dark]
        a = robust_sigma(r) ** 2
    else:
        a = b
    return max(a, 1e-6), b


def _as_float_frames(frames: Sequence[np.ndarray], what: str) -> list[np.ndarray]:
    out = []
    for i, f in enumerate(frames):
        arr = np.asarray(f)
        if arr.dtype.kind not in "uif":
            raise InputError(f"{what} {i + 1}", f"unsupported dtype {arr.dtype}")
        arr = arr.astype(np.float32, copy=False)
        if not np.all(np.isfinite(arr)):
            raise InputError(f"{what} {i + 1}", "contains NaN or infinite values")
        out.append(arr)
    if len({a.shape for a in out}) > 1:
        raise InputError(what, f"frames differ in shape: {sorted({a.shape for a in out})}")
    return out


def _channel_levels(offset) -> np.ndarray:
    """Per-channel median of a dark frame or of per-channel offset values (counts)."""
    arr = np.asarray(offset, np.float32)
    if arr.ndim <= 1:
        return arr.reshape(-1)
    chans = arr.reshape(arr.shape[0], arr.shape[1], -1)[::4, ::4]
    return np.median(chans.reshape(-1, chans.shape[-1]), axis=0)


def _check_finite(arr: np.ndarray, what: str) -> None:
    if not np.isfinite(arr[::7, ::7]).all() or not np.isfinite(arr).all():
        raise InputError(what, "contains NaN or infinite values")


def _clean_single_frame(frame: np.ndarray, what: str, offset_levels: np.ndarray,
                        params: FlatFieldParams, check: Callable[[], object] | None = None) -> tuple[np.ndarray, int]:
    """Pulse clean-up of a lone reference frame (no median to reject them); checks dtype and NaN."""
    _as_float_frames([frame[:1]], what)  # dtype check only (no full-size copy)
    cleaned, n = remove_bright_pulses(frame, params.pulse_threshold_sigma, offset_counts=offset_levels,
                                      check=check)
    _check_finite(cleaned, what)
    return cleaned, n


def combine_frames(frames: Sequence[np.ndarray]) -> np.ndarray:
    """Pixel-wise median of three or more frames, mean of two, copy of one (float32)."""
    if len(frames) == 1:
        return np.array(frames[0], np.float32)
    stack = np.stack(frames)
    return (np.median(stack, axis=0) if len(frames) >= 3 else stack.mean(axis=0)).astype(np.float32)


def prepare_flat_reference(shape: tuple[int, ...], *, flats: Sequence[np.ndarray] = (),
                           darks: Sequence[np.ndarray] = (), black_level=None,
                           params: FlatFieldParams | None = None,
                           progress: ProgressCallback | None = None) -> FlatReference:
    """Build the dark offset and the smoothed flat denominator for radiographs of ``shape``.

    Parameters
    ----------
    shape : tuple
        Shape of the radiographs, ``(H, W)`` or ``(H, W, C)``.
    flats : sequence of ndarray
        Open-beam frames (counts, same shape as the radiograph). May be empty.
    darks : sequence of ndarray
        Dark frames (counts). When empty, ``black_level`` is the offset.
    black_level : float or sequence of float, optional
        Raw black level per channel (counts); 0 when neither darks nor a black level is given.
    params : FlatFieldParams, optional
    progress : callable, optional
        Called as ``progress(done, total)`` between the steps (dark frame, flat frame,
        smoothing, statistics) and between the channels of a pulse clean-up. To stop, raise
        from it (e.g. :class:`~napari_dslrxr.core.errors.WorkCancelled`): it propagates.

    Returns
    -------
    FlatReference

    Raises
    ------
    InputError
        A flat or dark of another shape than the radiograph, NaN values, or an all-dark flat.
    """
    params = params or FlatFieldParams()
    n_channels = shape[2] if len(shape) == 3 else 1
    cleaned = 0
    steps = Steps(progress, 4)
    if darks:
        if np.asarray(darks[0]).shape != tuple(shape):
            raise InputError("dark frame", f"shape {np.asarray(darks[0]).shape} differs from the radiograph's {tuple(shape)}")
        if len(darks) == 1 and params.clean_flat_pulses:
            offset, n = _clean_single_frame(darks[0], "dark frame", _channel_levels(darks[0]), params,
                                            check=steps.check)
            cleaned += n
        else:
            offset = combine_frames(_as_float_frames(darks, "dark frame"))
    elif black_level is not None:
        offset = np.asarray(black_level, np.float32).reshape(-1)
        if offset.size not in (1, n_channels):
            raise ParameterError(f"black level: expected 1 or {n_channels} values, got {offset.size}")
        offset = offset if n_channels > 1 else offset[:1]
    else:
        offset = np.zeros(n_channels if n_channels > 1 else 1, np.float32)
    steps.advance()
    if not flats or not params.enabled:
        return FlatReference(offset=offset, denominator=None, scale=np.ones(n_channels, np.float32),
                             n_flats=0, cleaned_pulses=cleaned)
    shapes = {np.asarray(f).shape for f in flats}
    if len(shapes) > 1:
        raise InputError("flat frame", f"frames differ in shape: {sorted(shapes)}")
    if np.asarray(flats[0]).shape != tuple(shape):
        raise InputError("flat frame", f"shape {np.asarray(flats[0]).shape} differs from the radiograph's {tuple(shape)}")
    n_flats = len(flats)
    saturated_fraction, saturated_level = saturated_plateau(flats)
    if n_flats == 1 and params.clean_flat_pulses:
        flat, n = _clean_single_frame(flats[0], "flat frame", _channel_levels(offset), params, check=steps.check)
        cleaned += n
    else:
        flat = combine_frames(_as_float_frames(flats, "flat frame"))
        if n_flats == 2 and params.clean_flat_pulses:
            flat, n = remove_bright_pulses(flat, params.pulse_threshold_sigma,
                                           offset_counts=_channel_levels(offset), check=steps.check)
            cleaned += n
    steps.advance()
    denominator = flat - offset
    del flat
    if params.flat_smoothing_px > 0:
        denominator = _smooth_within_lit_area(denominator, float(params.flat_smoothing_px))
    steps.advance()
    chans = denominator.reshape(denominator.shape[0], denominator.shape[1], -1)
    step = max(1, int(np.sqrt(chans.shape[0] * chans.shape[1] / 1_000_000)))
    sub = chans[::step, ::step]  # statistics from a regular subsample
    scale = np.empty(chans.shape[2], np.float32)
    floors = np.empty(chans.shape[2], np.float32)
    for c in range(chans.shape[2]):
        plane = sub[..., c]
        top = float(np.percentile(plane, 99.5))
        if not top > 0:
            raise InputError("flat frame", f"channel {c}: no exposed pixels (flat is not brighter than the dark offset)")
        floors[c] = max(params.min_flat_fraction * top, 1e-6)
        scale[c] = float(plane[plane > 0.5 * top].mean())  # the exposed screen area
    np.maximum(chans, floors, out=chans)
    steps.advance()
    return FlatReference(offset=offset, denominator=denominator, scale=scale,
                         n_flats=n_flats, cleaned_pulses=cleaned, saturated_fraction=saturated_fraction,
                         saturated_level_counts=saturated_level)


# A pixel belongs to the flat's lit area above this fraction of its bright level (the 99.5th
# percentile): half the level is where a blurred screen border crosses from dark to lit.
_LIT_FRACTION = 0.5


def _lit_blur(block: np.ndarray, lit: np.ndarray, blur) -> np.ndarray:
    """Blur of ``block`` (H, W, C) over its ``lit`` pixels only (normalised convolution)."""
    weight = blur(lit.astype(np.float32))[..., None]
    inside = blur(np.where(lit[..., None], block, np.float32(0))).reshape(block.shape)
    return inside / np.maximum(weight, np.float32(1e-6))


def _smooth_within_lit_area(denominator: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian smoothing of ``F - D`` that, on the lit screen, averages lit pixels only
    (normalised convolution); pixels outside it keep the plain blur.

    A plain blur mixes the dark room into the flat within a few sigma of the screen border, so
    the denominator sinks there and the corrected frame shows a bright rim inside the border
    (16 % on the sample frame at 4 px). The border is where the channel sum crosses half its
    bright level (the same border in every channel). Outside it the plain blur stays: the
    penumbra and the room beside the border hold the screen's spilled light in the radiograph
    as in the flat, and a room-only average there would divide that light by the room's level
    (a bright band round the screen). Away from the border the lit average equals the plain
    blur, so only the tiles the border crosses are smoothed again, each with a margin of the
    kernel's radius (exact, and a small cost on a whole frame).
    """
    def blur(a: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(a, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)

    h, w = denominator.shape[:2]
    out = blur(denominator).reshape(h, w, -1)
    chans = denominator.reshape(h, w, -1)
    level = chans[..., 0].copy()
    for c in range(1, chans.shape[2]):
        level += chans[..., c]
    step = max(1, int(np.sqrt(h * w / 1_000_000)))
    lit = level > _LIT_FRACTION * float(np.percentile(level[::step, ::step], 99.5))
    del level
    share = blur(lit.astype(np.float32))  # share of lit pixels under the kernel
    crossed = (share > 1e-4) & (share < 1 - 1e-4)
    del share
    margin = int(np.ceil(4 * sigma_px)) + 2  # OpenCV's kernel radius is about 4 sigma
    tile = 128
    for r0 in range(0, h, tile):
        for c0 in range(0, w, tile):
            r1, c1 = min(r0 + tile, h), min(c0 + tile, w)
            if not crossed[r0:r1, c0:c1].any():
                continue
            R0, C0 = max(0, r0 - margin), max(0, c0 - margin)
            R1, C1 = min(h, r1 + margin), min(w, c1 + margin)
            smoothed = _lit_blur(np.ascontiguousarray(chans[R0:R1, C0:C1]), lit[R0:R1, C0:C1], blur)
            keep = lit[r0:r1, c0:c1]
            out[r0:r1, c0:c1][keep] = smoothed[r0 - R0:r1 - R0, c0 - C0:c1 - C0][keep]
    return out.reshape(denominator.shape)


def apply_flat_field(image: np.ndarray, reference: FlatReference) -> np.ndarray:
    """Correct one radiograph with a prepared reference: ``(R - D) / (F - D) * mean(F - D)``.

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, C)
        Linear counts (uint16 or float).
    reference : FlatReference

    Returns
    -------
    ndarray, float32
        Flat-fielded counts, same shape; negative values (read noise below the offset) kept.
    """
    out = np.asarray(image, np.float32).copy() if np.asarray(image).dtype != np.float32 else np.array(image)
    out -= reference.offset
    if reference.denominator is not None:
        out /= reference.denominator
        if out.ndim == 3:
            out *= reference.scale
        else:
            out *= reference.scale[0]
    return out

