"""Repeated frames of a plate edge (no thickness map): cleaning, the noise from the even/odd
difference, the ideal edge object, and :func:`diagnose_edge_repeats`."""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..errors import InputError
from ..robust import MAD_TO_SIGMA, robust_sigma
from ..simulation.physics_terms import ChainGrid
from ..simulation.simulator import block_mean
from .mismatch import diagnose
from .result import DiagnosisOptions, DiagnosisResult


def clean_repeats(frames: np.ndarray, z_threshold: float = 6.0) -> np.ndarray:
    """Repeated frames with impulsive spots replaced by the temporal median.

    Parameters
    ----------
    frames : ndarray, (N, H, W)
        Repeated exposures (DN), N >= 3.
    z_threshold : float
        A pixel of a frame is a spot when it exceeds the temporal median by more than this many
        robust (MAD) standard deviations of the frame-minus-median difference.

    Returns
    -------
    ndarray, float64, (N, H, W)
        The frames, spots replaced.
    """
    frames = np.asarray(frames, dtype=np.float64)
    if frames.ndim != 3 or frames.shape[0] < 3:
        raise InputError(None, f"need at least 3 repeated 2-D frames, got shape {frames.shape}")
    median = np.median(frames, axis=0)
    diff = frames - median
    sigma = MAD_TO_SIGMA * np.median(np.abs(diff), axis=(1, 2), keepdims=True)
    return np.where(diff > z_threshold * sigma, median, frames)


def noise_model_from_repeats(frames: np.ndarray, binning: int, n_bins: int = 24) -> tuple[float, float]:
    """``(K, c)``, ``var = K · level + c`` (DN², absolute level), of the mean of ``frames``
    block-averaged ``binning``×, from the repeats themselves.

    The difference of the means of the even and odd frames, halved, has the noise variance of
    the mean of all frames — including its spatially correlated part, which a high-pass
    estimate on one image misses (scintillator light spread makes the noise correlated). Each
    half's global gain/offset difference (source output drift) and a very smooth drift map are
    removed first; then a robust (MAD) variance per bin of block level and a straight line.
    Spots must already be replaced (:func:`clean_repeats`).
    """
    from scipy import ndimage

    frames = np.asarray(frames, dtype=np.float64)
    n = frames.shape[0]
    if frames.ndim != 3 or n < 4:
        raise InputError(None, f"need at least 4 repeated 2-D frames for the noise model, got {frames.shape}")
    mean = frames.mean(axis=0)
    diff = 0.5 * (frames[0::2].mean(axis=0) - frames[1::2].mean(axis=0))
    # equal weights: var(diff) = var(mean) exactly only for equal halves
    diff *= np.sqrt((n // 2 + (n - n // 2)) ** 2 / (4 * (n // 2) * (n - n // 2))) if n % 2 else 1.0
    h, w = mean.shape
    hb, wb = (h // binning) * binning, (w // binning) * binning
    level = block_mean(mean[:hb, :wb], binning)
    d = block_mean(diff[:hb, :wb], binning)
    design = np.stack([np.ones(level.size), level.ravel()], 1)
    coef, *_ = np.linalg.lstsq(design, d.ravel(), rcond=None)
    d = d - (design @ coef).reshape(d.shape)
    d = d - ndimage.gaussian_filter(d, max(2.0, 32.0 / binning), mode="reflect")
    edges = np.unique(np.quantile(level, np.linspace(0, 1, n_bins + 1)))
    which = np.clip(np.searchsorted(edges, level.ravel(), side="right") - 1, 0, len(edges) - 2)
    xs, vs = [], []
    for b in range(len(edges) - 1):
        sel = which == b
        if sel.sum() >= 20:
            dd = d.ravel()[sel]
            xs.append(level.ravel()[sel].mean())
            vs.append(robust_sigma(dd) ** 2)
    if len(xs) < 2:
        raise InputError(None, "too few pixels to estimate the noise model from the repeats")
    slope, intercept = np.polyfit(np.array(xs), np.array(vs), 1)
    return float(slope), float(intercept)


def edge_object_from_image(image: np.ndarray, supersample: int = 2, smooth_px: float = 1.0) -> np.ndarray:
    """Ideal (unblurred) opaque-object map from a recording of a plate edge, sub-pixel.

    The image is smoothed (Gaussian ``smooth_px``), upsampled ``supersample``× (bilinear) and
    thresholded half-way between the open level (95th percentile) and the plate level (5th
    percentile). For a symmetric PSF the 50 % contour of a blurred straight edge lies on the
    edge itself, so the map is the plate as it would be imaged without blur (corners are
    slightly rounded).

    Returns
    -------
    ndarray, float64, (H*s, W*s)
        1.0 where the plate is, 0.0 in the open field (a "thickness" in mm of a unit material
        whose attenuation the base fit estimates).
    """
    from scipy import ndimage

    img = ndimage.gaussian_filter(np.asarray(image, dtype=np.float64), smooth_px)
    lo, hi = np.percentile(img, 5), np.percentile(img, 95)
    fine = ndimage.zoom(img, supersample, order=1, mode="nearest", grid_mode=True)
    return (fine < 0.5 * (lo + hi)).astype(np.float64)


def diagnose_edge_repeats(frames: np.ndarray, *, dark_frame: np.ndarray | None = None,
                          flat_frame: np.ndarray | None = None, pixel_pitch_mm: float = 0.1,
                          binning: int = 2, supersample: int = 2,
                          options: DiagnosisOptions | None = None,
                          progress: Callable[[str], None] | None = None) -> DiagnosisResult:
    """Diagnose repeated recordings of an opaque plate edge (no thickness map available).

    Steps: flat-field correction with the smoothed open-beam frame (if given; median 5×5 then
    Gaussian sigma 3 px, normalised to median 1); spots replaced by the temporal median and the
    frames averaged (:func:`clean_repeats`); the ideal edge map derived from the mean image
    (:func:`edge_object_from_image`, a unit-thickness "material" whose attenuation is fitted);
    the noise model of the binned mean from the even/odd half difference
    (:func:`noise_model_from_repeats`); the offset held at the dark frame's median (it separates
    a uniform glare floor from the black level). Geometry: the object lies against the screen
    (``M - 1 ≈ 0``), so only the detector blur is fitted.

    Parameters
    ----------
    frames : ndarray, (N, H, W)
        Repeated exposures (DN), N >= 4.
    dark_frame, flat_frame : ndarray, (H, W), optional
    pixel_pitch_mm : float
        Pixel pitch on the screen (ranges are reported in mm with it).
    binning : int
        Block-averaging factor of the fit (the noise is spatially correlated).
    """
    from scipy import ndimage

    frames = np.asarray(frames, dtype=np.float64)
    if frames.ndim != 3 or frames.shape[0] < 4:
        raise InputError(None, f"need at least 4 repeated 2-D frames, got shape {frames.shape}")
    dark = float(np.median(dark_frame)) if dark_frame is not None else float(np.percentile(frames, 0.1))
    if flat_frame is not None:
        flat = ndimage.gaussian_filter(ndimage.median_filter(np.asarray(flat_frame, float), 5), 3) - dark
        if np.any(flat <= 0):
            raise InputError(None, "flat frame is not brighter than the dark level everywhere")
        flat /= np.median(flat)
        frames = (frames - dark) / flat + dark
    cleaned = clean_repeats(frames)
    recording = cleaned.mean(axis=0)
    h, w = recording.shape
    h, w = (h // binning) * binning, (w // binning) * binning
    recording, cleaned = recording[:h, :w], cleaned[:, :h, :w]
    obj = edge_object_from_image(recording, supersample)
    slope, intercept = noise_model_from_repeats(cleaned, binning)
    grid = ChainGrid(recording.shape, supersample, pixel_pitch_mm, 0.0, 1.0e4)
    open_level = float(np.percentile(recording, 95))
    plate_level = float(np.percentile(recording, 5))
    start = {"offset_dn": dark, "gain_dn": open_level - dark,
             "mu_per_mm": float(np.log((open_level - dark) / max(plate_level - dark, 1.0))),
             "detector_sigma_mm": 2.0 * pixel_pitch_mm, "focal_spot_sigma_mm": 0.0}
    opts = options or DiagnosisOptions()
    from dataclasses import replace

    # The repeats' noise power spectrum (options.noise_sample_binned) is not used here yet: on
    # this real data the residual also holds fixed-pattern structure that the temporal noise
    # does not, and whitening with the temporal spectrum amplified it (χ²/dof 10) — open work.
    opts = replace(opts, binning=binning, fixed_offset_dn=dark, noise_model_binned=(slope, intercept))
    return diagnose(recording, obj, grid, start, opts, progress)
