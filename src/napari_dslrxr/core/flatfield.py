"""Flat-field correction (stage ii): ``C = (R - D) / (F - D) * mean(F - D)``, per colour channel.

``R`` is the radiograph, ``F`` the open-beam (flat) frame taken with the same camera settings
and ``D`` the dark offset: a dark frame (X-rays off) or, without one, the raw black level.
Several flats are combined by a pixel-wise median (which also removes pulses that hit only
one of them); a single flat is pulse-cleaned with a switching median. The flat is then
smoothed with a small Gaussian so that its own photon noise is not stamped onto every
corrected radiograph (set ``flat_smoothing_px = 0`` when the flat carries fine fixed-pattern
structure, such as scintillator or readout banding, that must be divided out). The result
stays in counts: the normalisation by the mean of ``F - D`` over the exposed area keeps the
photon statistics of the radiograph, which the later stages (grey conversion, log domain)
rely on.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from .errors import InputError, ParameterError


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
    """

    offset: np.ndarray
    denominator: np.ndarray | None
    scale: np.ndarray
    n_flats: int = 0
    cleaned_pulses: int = 0


def remove_bright_pulses(frame: np.ndarray, threshold_sigma: float = 6.0) -> tuple[np.ndarray, int]:
    """Replace bright impulsive pixels of a reference frame by their 5x5 median.

    A switching median for flat and dark frames: the noise scale is the median absolute
    residual scaled by ``sqrt(median level)`` (photon noise), so the test is valid over the
    whole frame; flagged pixels are dilated by one pixel (pulses spread over neighbours).

    Parameters
    ----------
    frame : ndarray, float32, (H, W) or (H, W, C)
        Linear counts.
    threshold_sigma : float
        Detection threshold in noise standard deviations.

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
    # whole-array operations (all channels at once): per-channel strided slices are slow
    if arr.ndim == 3 and arr.shape[2] not in (1, 3, 4):
        raise InputError("reference frame", f"unsupported channel count {arr.shape[2]}")
    med = cv2.medianBlur(arr, 5)  # native dtype: uint16 is about twice as fast as float32
    if med.ndim < arr.ndim:
        med = med[..., None]
    if arr.dtype == np.uint16:
        return _remove_bright_pulses_u16(arr, med, threshold_sigma)
    values = arr.astype(np.float32)
    med = med.astype(np.float32)
    residual = values - med
    # photon noise grows with the level (the offset only adds a constant): scale by sqrt(level)
    noise_scale = np.maximum(med, 1.0)
    np.sqrt(noise_scale, out=noise_scale)
    step = max(1, int(np.sqrt(residual.shape[0] * residual.shape[1] / 250_000)))
    scaled = residual[::step, ::step] / noise_scale[::step, ::step]
    if scaled.ndim == 3:
        centre = np.median(scaled, axis=(0, 1))
        sigma = 1.4826 * np.median(np.abs(scaled - centre), axis=(0, 1)) + 1e-12
    else:
        sigma = 1.4826 * float(np.median(np.abs(scaled - np.median(scaled)))) + 1e-12
    noise_scale *= np.asarray(threshold_sigma * sigma, np.float32)
    pulses = residual > noise_scale
    del noise_scale
    pulses = cv2.dilate(pulses.view(np.uint8), np.ones((3, 3), np.uint8)).view(bool).reshape(residual.shape)
    pulses &= residual > 0
    np.copyto(values, med, where=pulses)
    return values, int(np.count_nonzero(pulses))


def _remove_bright_pulses_u16(arr: np.ndarray, med: np.ndarray, threshold_sigma: float) -> tuple[np.ndarray, int]:
    """uint16 path of :func:`remove_bright_pulses`: thresholds from a look-up table of the median.

    The test ``x > m + k sigma sqrt(m)`` is evaluated as ``x > T[m]`` with ``T`` tabulated over
    all 65536 levels (per channel), so the full-size work stays in uint16.
    """
    step = max(1, int(np.sqrt(arr.shape[0] * arr.shape[1] / 250_000)))
    a_sub = arr[::step, ::step].astype(np.float32)
    m_sub = med[::step, ::step].astype(np.float32)
    scaled = (a_sub - m_sub) / np.sqrt(np.maximum(m_sub, 1.0))
    levels = np.arange(65536, dtype=np.float64)
    values = arr.copy()
    n_channels = arr.shape[2] if arr.ndim == 3 else 1
    pulses = np.empty(arr.shape, bool)
    for c in range(n_channels):
        sc = scaled[..., c] if arr.ndim == 3 else scaled
        sigma = 1.4826 * float(np.median(np.abs(sc - np.median(sc)))) + 1e-12
        table = np.minimum(levels + threshold_sigma * sigma * np.sqrt(np.maximum(levels, 1.0)), 65535)
        table = np.floor(table).astype(np.uint16)
        if arr.ndim == 3:
            pulses[..., c] = arr[..., c] > table[med[..., c]]
        else:
            pulses[...] = arr > table[med]
    pulses = cv2.dilate(pulses.view(np.uint8), np.ones((3, 3), np.uint8)).view(bool).reshape(arr.shape)
    pulses &= arr > med
    np.copyto(values, med, where=pulses)
    return values.astype(np.float32), int(np.count_nonzero(pulses))


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


def _check_finite(arr: np.ndarray, what: str) -> None:
    if not np.isfinite(arr[::7, ::7]).all() or not np.isfinite(arr).all():
        raise InputError(what, "contains NaN or infinite values")


def combine_frames(frames: Sequence[np.ndarray]) -> np.ndarray:
    """Pixel-wise median of three or more frames, mean of two, copy of one (float32)."""
    if len(frames) == 1:
        return np.array(frames[0], np.float32)
    stack = np.stack(frames)
    return (np.median(stack, axis=0) if len(frames) >= 3 else stack.mean(axis=0)).astype(np.float32)


def prepare_flat_reference(shape: tuple[int, ...], *, flats: Sequence[np.ndarray] = (),
                           darks: Sequence[np.ndarray] = (), black_level=None,
                           params: FlatFieldParams | None = None) -> FlatReference:
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
    if darks:
        if np.asarray(darks[0]).shape != tuple(shape):
            raise InputError("dark frame", f"shape {np.asarray(darks[0]).shape} differs from the radiograph's {tuple(shape)}")
        if len(darks) == 1 and params.clean_flat_pulses:
            _as_float_frames([darks[0][:1]], "dark frame")  # dtype check only
            offset, n = remove_bright_pulses(darks[0], params.pulse_threshold_sigma)
            _check_finite(offset, "dark frame")
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
    if not flats or not params.enabled:
        return FlatReference(offset=offset, denominator=None, scale=np.ones(n_channels, np.float32),
                             n_flats=0, cleaned_pulses=cleaned)
    shapes = {np.asarray(f).shape for f in flats}
    if len(shapes) > 1:
        raise InputError("flat frame", f"frames differ in shape: {sorted(shapes)}")
    if np.asarray(flats[0]).shape != tuple(shape):
        raise InputError("flat frame", f"shape {np.asarray(flats[0]).shape} differs from the radiograph's {tuple(shape)}")
    n_flats = len(flats)
    if n_flats == 1 and params.clean_flat_pulses:
        _as_float_frames([flats[0][:1]], "flat frame")  # dtype check only
        flat, n = remove_bright_pulses(flats[0], params.pulse_threshold_sigma)
        _check_finite(flat, "flat frame")
        cleaned += n
    else:
        flat = combine_frames(_as_float_frames(flats, "flat frame"))
        if n_flats == 2 and params.clean_flat_pulses:
            flat, n = remove_bright_pulses(flat, params.pulse_threshold_sigma)
            cleaned += n
    denominator = flat - offset
    del flat
    if params.flat_smoothing_px > 0:
        denominator = cv2.GaussianBlur(denominator, (0, 0), float(params.flat_smoothing_px),
                                       borderType=cv2.BORDER_REFLECT)
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
    return FlatReference(offset=offset, denominator=denominator, scale=scale,
                         n_flats=n_flats, cleaned_pulses=cleaned)


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


def flat_field_correct(image: np.ndarray, flats: Sequence[np.ndarray] = (), darks: Sequence[np.ndarray] = (),
                       *, black_level=None, params: FlatFieldParams | None = None) -> np.ndarray:
    """Flat-field correct one radiograph (convenience: prepare the reference, then apply it).

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, C)
        Linear counts.
    flats, darks : sequence of ndarray
        Open-beam and dark frames of the same shape (counts).
    black_level : float or sequence, optional
        Used as the offset when no dark frame is given.
    params : FlatFieldParams, optional

    Returns
    -------
    ndarray, float32
        Corrected counts.
    """
    image = np.asarray(image)
    reference = prepare_flat_reference(image.shape, flats=flats, darks=darks,
                                       black_level=black_level, params=params)
    return apply_flat_field(image, reference)
