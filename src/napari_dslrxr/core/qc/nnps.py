"""Normalised noise power spectrum from flat (open-beam) frames (IEC 62220-1-1)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from ..errors import InputError
from .edge import fill_masked, spot_mask


@dataclass
class NNPSResult:
    """NNPS of a set of flats.

    Attributes
    ----------
    frequency_cy_per_mm : ndarray
        Output frequencies ``k * frequency_bin / (roi_size * p)``, k = 1 ... up to Nyquist.
    nnps_horizontal_mm2, nnps_vertical_mm2 : ndarray
        1-D cuts along the horizontal (u) and vertical (v) frequency axes: the mean of the
        ``cut_half_width`` rows (columns) on each side of the axis, axis excluded, then the mean
        over each frequency bin.
    uncertainty_horizontal_mm2, uncertainty_vertical_mm2 : ndarray
        Standard uncertainty: spread of the single-ROI cuts over the square root of the number
        of independent ROIs (covered area / ROI area, since the ROIs overlap by half).
    nnps_2d_mm2 : ndarray (N, N)
        Mean 2-D NNPS, zero frequency at the centre (``np.fft.fftshift`` order).
    roi_origins : list of (row, col)
        Top-left corners of the ROIs (the same in every flat).
    analysis_area : tuple
        ``(r0, c0, r1, c1)`` of the central area (end exclusive).
    mean_signal : list of float
        Mean dark-subtracted signal of each flat's analysis area.
    n_rois, n_independent : int, float
    n_outliers : int
    warnings : list of str
    """

    frequency_cy_per_mm: np.ndarray
    nnps_horizontal_mm2: np.ndarray
    nnps_vertical_mm2: np.ndarray
    uncertainty_horizontal_mm2: np.ndarray
    uncertainty_vertical_mm2: np.ndarray
    nnps_2d_mm2: np.ndarray
    roi_origins: list
    analysis_area: tuple
    mean_signal: list
    n_rois: int
    n_independent: float
    n_outliers: int
    warnings: list = field(default_factory=list)


def analysis_layout(shape: tuple[int, int], roi_size_px: int, area_fraction: float):
    """The central analysis area and the half-overlapping ROI origins inside it."""
    n = roi_size_px
    side = int(area_fraction * min(shape))
    per_side = (side - n) // (n // 2) + 1
    if side < n or per_side < 1:
        return None, []
    used = (per_side - 1) * (n // 2) + n
    r0, c0 = (shape[0] - used) // 2, (shape[1] - used) // 2
    origins = [(r0 + i * (n // 2), c0 + j * (n // 2)) for i in range(per_side) for j in range(per_side)]
    return (r0, c0, r0 + used, c0 + used), origins


def detrend_quadratic(area: np.ndarray) -> np.ndarray:
    """The least-squares 2-D second-order polynomial surface of ``area`` (the slow trend: heel
    effect, vignetting). Fitted on every 4th pixel in each direction: the surface has six
    coefficients, and the subsample keeps the fit fast on large frames."""
    h, w = area.shape

    def basis(y, x):
        y = (y - h / 2) / h
        x = (x - w / 2) / w
        return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1)

    ys, xs = np.mgrid[0:h:4, 0:w:4].astype(np.float64)
    coef, *_ = np.linalg.lstsq(basis(ys, xs).reshape(-1, 6), area[::4, ::4].reshape(-1), rcond=None)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return basis(y, x) @ coef


def bin_frequencies(values: np.ndarray, frequency_bin: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of native frequency samples ``j`` with ``|j - k * bin| <= bin / 2``, k = 1, 2 ...

    ``values`` holds samples j = 0 ... N/2 on its last axis; returns (centre indices, binned).
    """
    n_half = values.shape[-1] - 1
    centres = np.arange(frequency_bin, n_half + 1, frequency_bin)
    out = np.empty(values.shape[:-1] + (centres.size,))
    j = np.arange(n_half + 1)
    for i, k in enumerate(centres):
        sel = np.abs(j - k) <= frequency_bin / 2
        out[..., i] = values[..., sel].mean(axis=-1)
    return centres, out


def nnps_from_flats(flats: Sequence[np.ndarray], darks: Sequence[np.ndarray] | None, pixel_pitch_mm: float, *,
                    roi_size_px: int = 256, area_fraction: float = 0.9, cut_half_width: int = 7,
                    frequency_bin: int = 4, outlier_sigma: float = 0.0, names: Sequence[str] | None = None,
                    progress: Callable[[int, int], object] | None = None,
                    dark: np.ndarray | None = None) -> NNPSResult:
    """NNPS from flats at one air kerma: detrended, half-overlapping ROIs averaged over all flats.

    Each flat minus the mean dark is cut to a central area; a quadratic surface fitted to the
    area is subtracted; each ROI's 2-D periodogram ``|FFT(roi - mean)|^2 p^2 / N^2`` is divided
    by the squared mean signal of its flat. The 1-D cuts average the rows (columns) beside the
    frequency axes, excluding the axis itself. ``dark``: the mean dark with its spots filled, when
    the caller has it already (``darks`` is then not read).

    Raises
    ------
    InputError
        Frames of different shapes, too small for one ROI, or without signal above the dark.
    """
    flats = [np.asarray(f, dtype=np.float64) for f in flats]
    names = list(names) if names is not None else [f"flat {i + 1}" for i in range(len(flats))]
    if not flats:
        raise InputError(None, "no flat frames given")
    shape = flats[0].shape
    for f, name in zip(flats, names):
        if f.ndim != 2 or f.shape != shape:
            raise InputError(name, f"flat of shape {f.shape} differs from the first flat's {shape}")
        if not np.isfinite(f).all():
            raise InputError(name, "NaN or infinite values")
    if dark is None:
        dark = mean_dark(darks, shape)
        dark = fill_masked(dark, spot_mask(dark, outlier_sigma))
    area, origins = analysis_layout(shape, roi_size_px, area_fraction)
    if area is None:
        raise InputError(names[0], f"the frame ({shape[0]}x{shape[1]} px) is too small for a "
                                   f"{roi_size_px}x{roi_size_px} NNPS region in its central area "
                                   f"(lower qc.roi_size_px or raise qc.nnps_area_fraction)")
    r0, c0, r1, c1 = area
    n = roi_size_px
    m = cut_half_width
    sum_2d = np.zeros((n, n))
    cuts_h, cuts_v = [], []
    means, warnings = [], []
    n_outliers = 0
    window_rows = np.r_[1:m + 1, n - m:n]
    for i, (flat, name) in enumerate(zip(flats, names)):
        signal = flat[r0:r1, c0:c1] - dark[r0:r1, c0:c1]
        mean = float(signal.mean())
        if not mean > 0:
            raise InputError(name, "no signal above the dark frame in the central area")
        bad = spot_mask(signal, outlier_sigma)
        if bad.any():
            n_outliers += int(bad.sum())
            signal = fill_masked(signal, bad)
        residual = signal - detrend_quadratic(signal)
        means.append(mean)
        for (rr, cc) in origins:
            roi = residual[rr - r0:rr - r0 + n, cc - c0:cc - c0 + n]
            power = np.abs(np.fft.fft2(roi - roi.mean())) ** 2 * (pixel_pitch_mm ** 2 / (n * n)) / mean ** 2
            sum_2d += power
            cuts_h.append(power[window_rows, : n // 2 + 1].mean(axis=0))
            cuts_v.append(power[: n // 2 + 1, window_rows].mean(axis=1))
        if progress is not None:
            progress(i + 1, len(flats))
    total = len(cuts_h)
    covered = (r1 - r0) * (c1 - c0) / float(n * n)
    n_indep = covered * len(flats)
    centres, binned_h = bin_frequencies(np.asarray(cuts_h), frequency_bin)
    _, binned_v = bin_frequencies(np.asarray(cuts_v), frequency_bin)
    unc_h = binned_h.std(axis=0, ddof=1) / math.sqrt(n_indep) if total > 1 else np.full(centres.size, np.nan)
    unc_v = binned_v.std(axis=0, ddof=1) / math.sqrt(n_indep) if total > 1 else np.full(centres.size, np.nan)
    if n_outliers > 1e-3 * len(flats) * (r1 - r0) * (c1 - c0):
        warnings.append(f"{n_outliers} spot pixels ({100.0 * n_outliers / (len(flats) * (r1 - r0) * (c1 - c0)):.2g} %) "
                        "replaced by the mean of their neighbours in the flats before the NNPS")
    return NNPSResult(
        frequency_cy_per_mm=centres / (n * pixel_pitch_mm),
        nnps_horizontal_mm2=binned_h.mean(axis=0), nnps_vertical_mm2=binned_v.mean(axis=0),
        uncertainty_horizontal_mm2=unc_h, uncertainty_vertical_mm2=unc_v,
        nnps_2d_mm2=np.fft.fftshift(sum_2d / total), roi_origins=origins, analysis_area=area,
        mean_signal=means, n_rois=total, n_independent=n_indep, n_outliers=n_outliers, warnings=warnings)


def mean_dark(darks: Sequence[np.ndarray] | None, shape: tuple[int, int]) -> np.ndarray:
    """The mean of the dark frames (zeros when none); refuses a dark of another shape."""
    if not darks:
        return np.zeros(shape)
    stack = [np.asarray(d, dtype=np.float64) for d in darks]
    for i, d in enumerate(stack):
        if d.shape != shape:
            raise InputError(f"dark {i + 1}", f"dark of shape {d.shape} differs from the flats' {shape}")
    return np.mean(stack, axis=0)
