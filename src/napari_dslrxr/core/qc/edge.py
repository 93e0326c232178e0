"""Presampled MTF from a slanted edge (IEC 62220-1-1): edge line, oversampled ESF, LSF, FFT."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ..errors import InputError, ParameterError
from ..robust import robust_line_fit, robust_sigma
from .params import EDGE_ANGLE_RANGE_DEG

#: Rows whose edge position lies within ``_ON_LINE_PX`` of the fitted line (the half width of
#: the window each row's edge centroid is taken over): at least this fraction, or the region
#: holds no single straight edge.
_ON_LINE_PX = 8.0
_MIN_ON_LINE_FRACTION = 0.8

#: Rows of the edge image per segment for the MTF uncertainty (the edge must move through
#: at least two whole pixels across a segment at 1.5 degrees).
_MIN_SEGMENT_ROWS = 80


@dataclass
class EdgeMTF:
    """The presampled MTF of one edge image.

    Attributes
    ----------
    direction : str
        ``"horizontal"`` (frequency along the rows: a near-vertical edge) or ``"vertical"``.
    frequency_cy_per_mm : ndarray
        Fine frequency grid from 0 to the Nyquist frequency 1/(2p).
    mtf, mtf_uncertainty : ndarray
        MTF normalised to 1 at zero frequency and its standard uncertainty (spread of the MTFs
        of independent segments along the edge over the square root of their number).
    angle_deg : float
        Edge angle to the pixel column (row) axis.
    edge_line : tuple
        ``(row0, col0, row1, col1)`` end points of the fitted edge line in image pixels.
    esf_distance_mm, esf, lsf : ndarray
        The oversampled edge-spread function (distance perpendicular to the edge) and its
        derivative.
    n_segments : int
    n_outliers : int
        Pixels left out as spots.
    lsf_half_width_px : int
        Half width of the Hann window actually applied to the LSF (the frame may shorten it).
    warnings : list of str
    """

    direction: str
    frequency_cy_per_mm: np.ndarray
    mtf: np.ndarray
    mtf_uncertainty: np.ndarray
    angle_deg: float
    edge_line: tuple
    esf_distance_mm: np.ndarray
    esf: np.ndarray
    lsf: np.ndarray
    n_segments: int
    n_outliers: int
    lsf_half_width_px: int = 0
    warnings: list = field(default_factory=list)


def spot_mask(image: np.ndarray, outlier_sigma: float) -> np.ndarray:
    """Pixels more than ``outlier_sigma`` robust sigmas from the mean of their 5x5 neighbourhood
    (spots from direct hits on the sensor, dead or hot pixels)."""
    if outlier_sigma <= 0:
        return np.zeros(image.shape, bool)
    resid = image - ndimage.uniform_filter(image, size=5, mode="reflect")
    sigma = robust_sigma(resid, center=0.0)
    if not sigma > 0:
        return np.zeros(image.shape, bool)
    return np.abs(resid) > outlier_sigma * sigma


def fill_masked(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` with the masked pixels replaced by the mean of their unmasked 5x5 neighbours."""
    keep = (~mask).astype(np.float64)
    num = ndimage.uniform_filter(np.where(mask, 0.0, image), size=5, mode="reflect")
    den = ndimage.uniform_filter(keep, size=5, mode="reflect")
    fill = np.where(den > 0, num / np.maximum(den, 1e-12), np.median(image[~mask]) if (~mask).any() else 0.0)
    return np.where(mask, fill, image)


def _edge_positions(image: np.ndarray, valid: np.ndarray):
    """Per row, the sub-pixel column of the edge (centroid of the squared row derivative)."""
    filled = image if valid.all() else fill_masked(image, ~valid)
    smooth = ndimage.gaussian_filter1d(filled, 1.0, axis=1)
    grad = np.diff(smooth, axis=1)
    rows, cols = [], []
    x = np.arange(grad.shape[1]) + 0.5
    for r in range(grad.shape[0]):
        g = np.abs(grad[r])
        k = int(np.argmax(g))
        lo, hi = max(0, k - 8), min(g.size, k + 9)
        w = g[lo:hi] ** 2
        if w.sum() > 0:
            rows.append(r)
            cols.append(float((w * x[lo:hi]).sum() / w.sum()))
    return np.asarray(rows, float), np.asarray(cols, float)


def _fit_line(rows: np.ndarray, cols: np.ndarray, name: str):
    if rows.size < 16:
        raise InputError(name, "no straight edge found (too few rows cross an edge)")
    line = robust_line_fit(rows, cols, rounds=4, clip_sigma=4.0, min_spread=0.1, min_points=16)
    if line is None:
        raise InputError(name, "no straight edge found (the edge positions do not fall on a line)")
    return line


def _perpendicular_distance_px(shape, slope, intercept):
    """Signed distance (px) of every pixel centre to the line col = slope * row + intercept."""
    rr, cc = np.mgrid[0:shape[0], 0:shape[1]]
    # Pixel centres sit at integer indices; the edge column was measured on the same grid.
    return (cc - (slope * rr + intercept)) / math.hypot(1.0, slope), rr


def _esf(values, dist_px, sel, oversampling, half_width_px):
    """Oversampled ESF: the mean of the selected pixels in bins of 1/oversampling px of distance."""
    reach = half_width_px + 2
    step = 1.0 / oversampling
    nbins = int(round(2 * reach / step))
    idx = np.floor((dist_px[sel] + reach) / step).astype(int)
    ok = (idx >= 0) & (idx < nbins)
    counts = np.bincount(idx[ok], minlength=nbins)
    sums = np.bincount(idx[ok], weights=values[sel][ok], minlength=nbins)
    centres = (np.arange(nbins) + 0.5) * step - reach
    filled = counts > 0
    if filled.sum() < 0.9 * nbins:
        return centres, None
    return centres, np.interp(centres, centres[filled], sums[filled] / counts[filled])


def _esf_outliers(values, dist_px, sel, centres, esf, outlier_sigma):
    """Pixels whose residual from the ESF exceeds ``outlier_sigma`` robust sigmas of the
    residuals at their distance (1-px bands: the noise differs between the dark and bright side)
    plus the ESF's change over one bin (the binned ESF cannot follow a sharp edge within a bin,
    and that deterministic misfit must not count as a spot)."""
    resid = values - np.interp(dist_px, centres, esf)
    step = float(centres[1] - centres[0])
    slack = np.abs(np.interp(dist_px, centres, np.gradient(esf, step))) * step
    # The selected pixels grouped by band once (a mask per band would pass the frame per band).
    index = np.flatnonzero(sel)
    band = np.floor(dist_px.ravel()[index]).astype(int)
    order = np.argsort(band, kind="stable")
    index, band = index[order], band[order]
    starts = np.flatnonzero(np.diff(band, prepend=band[:1] - 1))
    out = np.zeros(values.size, bool)
    resid, slack = resid.ravel(), slack.ravel()
    for here in np.split(index, starts[1:]):
        r = resid[here]
        if r.size < 8:
            continue
        centre = float(np.median(r))
        sigma = robust_sigma(r, center=centre)
        if sigma > 0:
            out[here] = np.abs(r - centre) > outlier_sigma * sigma + slack[here]
    return out.reshape(values.shape)


def _mtf_from_esf(esf, step_mm, oversampling, half_width_px, n_fft):
    """LSF (central difference), Hann window, FFT, with the binning and difference corrected."""
    lsf = np.gradient(esf)
    centre = float(np.sum(np.arange(lsf.size) * np.abs(lsf)) / max(np.sum(np.abs(lsf)), 1e-30))
    freq, mtf = _mtf_from_lsf(lsf, centre, step_mm, oversampling, half_width_px, n_fft)
    return freq, mtf, lsf


def _mtf_from_lsf(lsf, centre, step_mm, oversampling, half_width_px, n_fft):
    """Hann window of ``half_width_px`` about ``centre`` (in samples), FFT, normalisation at
    f = 0, and the bin and central-difference corrections (None when there is no contrast)."""
    k = np.arange(lsf.size) - centre
    half = half_width_px * oversampling
    window = np.where(np.abs(k) <= half, 0.5 * (1 + np.cos(np.pi * k / half)), 0.0)
    windowed = lsf * window
    spectrum = np.abs(np.fft.rfft(windowed, n_fft))
    freq = np.fft.rfftfreq(n_fft, d=step_mm)
    if not spectrum[0] > 0:
        return freq, None
    mtf = spectrum / spectrum[0]
    # The bin average is a box of one bin width, the central difference a transfer of
    # sinc(2 f step): divide both out (IEC/ISO practice) below the Nyquist frequency.
    correction = np.sinc(freq * step_mm) * np.sinc(2 * freq * step_mm)
    mtf = mtf / np.maximum(correction, 0.2)
    return freq, mtf


def _fft_length(half_width_px: int, oversampling: int) -> int:
    """FFT length of the LSF: a power of two, at least 4096 and eight window widths."""
    return 1 << int(math.ceil(math.log2(max(4096, 8 * (2 * half_width_px + 4) * oversampling))))


def edge_method_mtf(presampled_mtf, frequency_cy_per_mm, pixel_pitch_mm: float, *, lsf_half_width_px: int,
                    oversampling: int = 4) -> np.ndarray:
    """What :func:`slanted_edge_mtf` reads, without noise, from an edge whose presampled MTF
    (blur x pixel aperture along the edge normal) is ``presampled_mtf``.

    The measurement sees the presampled MTF through its own operator: the ESF bins (a box of one
    bin width), the central difference, and the Hann window of ``lsf_half_width_px`` on the LSF,
    normalised at f = 0; the first two are divided out again, the window is not. A blur whose line
    spread reaches beyond the window (a long tail) therefore reads higher at low frequencies than
    its presampled MTF. Comparing a blur model with a measured MTF like for like means passing
    the model through this function with the measurement's window (``EdgeMTF.lsf_half_width_px``).

    Parameters
    ----------
    presampled_mtf : callable
        Frequency (cycles/mm, array) -> presampled MTF, 1 at 0.
    frequency_cy_per_mm : array
        Where to evaluate.
    pixel_pitch_mm : float
    lsf_half_width_px, oversampling : int
        The measurement's window half width and ESF bins per pixel.

    Raises
    ------
    ParameterError
        When the presampled MTF is 0 at f = 0.
    """
    step_mm = pixel_pitch_mm / oversampling
    n_fft = _fft_length(lsf_half_width_px, oversampling)
    # The central difference of the bin-averaged ESF samples the line spread convolved with a box
    # of one bin and a box of two bins (transfer sinc(f step) sinc(2 f step)), times the step.
    # Sampled at the bin pitch over one FFT length (at least eight window widths, so the periodic
    # copies of the line spread fall far outside the window).
    grid = np.fft.rfftfreq(n_fft, d=step_mm)
    transfer = np.asarray(presampled_mtf(grid), dtype=np.float64) * np.sinc(grid * step_mm) * np.sinc(2 * grid * step_mm)
    lsf = np.fft.fftshift(np.fft.irfft(transfer, n_fft))
    freq, mtf = _mtf_from_lsf(lsf, n_fft // 2, step_mm, oversampling, lsf_half_width_px, n_fft)
    if mtf is None:
        raise ParameterError("edge_method_mtf: the presampled MTF has no zero-frequency response")
    return np.interp(np.abs(np.asarray(frequency_cy_per_mm, dtype=np.float64)), freq, mtf)


def slanted_edge_mtf(edge_image: np.ndarray, pixel_pitch_mm: float, *, oversampling: int = 4,
                     lsf_half_width_px: int = 64, outlier_sigma: float = 6.0, valid: np.ndarray | None = None,
                     name: str = "edge image") -> EdgeMTF:
    """Presampled MTF of a straight edge slanted by a few degrees to the pixel grid.

    Parameters
    ----------
    edge_image : ndarray (H, W)
        Linear image (dark-subtracted, ideally gain-corrected) holding one straight edge across
        the frame; either orientation (a near-horizontal edge is measured on the transposed
        image and reported as direction ``"vertical"``).
    pixel_pitch_mm : float
    oversampling : int
        ESF bins per pixel.
    lsf_half_width_px : int
        Half width of the Hann window applied to the LSF.
    outlier_sigma : float
        Pixels further than this many robust sigmas from the ESF at their distance (spots,
        dust) are left out; 0 keeps all.
    valid : ndarray of bool, optional
        Pixels to use (False for known defects).
    name : str
        File or label for error messages.

    Returns
    -------
    EdgeMTF
        The MTF on a fine grid from 0 to Nyquist, with its uncertainty.

    Raises
    ------
    InputError
        No straight edge, or too few rows to build the ESF.
    """
    image = np.asarray(edge_image, dtype=np.float64)
    if image.ndim != 2 or min(image.shape) < 32:
        raise InputError(name, f"the edge must be a 2-D image of at least 32x32 pixels, got shape {image.shape}")
    if not np.isfinite(image).all():
        raise InputError(name, "NaN or infinite values in the edge image")
    valid = np.ones(image.shape, bool) if valid is None else np.asarray(valid, bool)
    smooth = ndimage.gaussian_filter(image, 1.5)
    gy, gx = ndimage.sobel(smooth, axis=0), ndimage.sobel(smooth, axis=1)
    near_vertical = float((gx ** 2).sum()) >= float((gy ** 2).sum())
    data, mask = (image, valid) if near_vertical else (image.T, valid.T)
    direction = "horizontal" if near_vertical else "vertical"
    rows, cols = _edge_positions(data, mask)
    slope, intercept = _fit_line(rows, cols, name)
    # A region holding a corner, two edges or none still yields a line through some of the
    # rows' strongest gradients; its "MTF" is meaningless (a whole NIQA frame gave 1.4 at 1.3
    # cycles/mm). Measured within 8 px: 0.3-7 % of the rows on whole NIQA frames (the plate's
    # corner), 85-100 % on regions around one of its edges, the blurriest frame included.
    on_line = float(np.mean(np.abs(cols - (slope * rows + intercept)) <= _ON_LINE_PX))
    if on_line < _MIN_ON_LINE_FRACTION:
        raise InputError(name, f"no single straight edge across the region: {100 * on_line:.0f} % of the rows "
                               f"have their edge within {_ON_LINE_PX:g} px of the fitted line (a corner, a "
                               "second edge or no edge?); choose a region around one edge")
    angle = math.degrees(math.atan(abs(slope)))
    warnings = []
    lo, hi = EDGE_ANGLE_RANGE_DEG
    if not lo <= angle <= hi:
        warnings.append(f"{name}: edge angle {angle:.2f} deg is outside the {lo:g}-{hi:g} deg the standard asks for")
    if angle < 0.5:
        raise InputError(name, f"the edge is only {angle:.2f} deg from the pixel axis; the ESF cannot be "
                               "oversampled (tilt it by 1.5-3 deg)")
    half = int(min(lsf_half_width_px, (data.shape[1] - 4) // 2 - 2))
    step_mm = pixel_pitch_mm / oversampling
    n_fft = _fft_length(half, oversampling)
    dist_px, rows_of = _perpendicular_distance_px(data.shape, slope, intercept)
    sel = mask & (np.abs(dist_px) <= half + 2)
    centres, esf = _esf(data, dist_px, sel, oversampling, half)
    if esf is None:
        raise InputError(name, "the edge does not cross enough rows to fill the oversampled ESF")
    n_outliers = int((~mask).sum())
    if outlier_sigma > 0:
        spots = _esf_outliers(data, dist_px, sel, centres, esf, outlier_sigma)
        if spots.any():
            n_outliers += int(spots.sum())
            sel &= ~spots
            centres, esf = _esf(data, dist_px, sel, oversampling, half)
    dist = centres * pixel_pitch_mm
    freq, mtf, lsf = _mtf_from_esf(esf, step_mm, oversampling, half, n_fft)
    if mtf is None:
        raise InputError(name, "the edge has no contrast")
    nyquist = 0.5 / pixel_pitch_mm
    keep = freq <= nyquist * (1 + 1e-9)
    # Uncertainty: MTFs of independent bands of rows along the edge.
    n_seg = max(2, min(8, data.shape[0] // _MIN_SEGMENT_ROWS))
    bounds = np.linspace(0, data.shape[0], n_seg + 1).astype(int)
    seg_mtfs = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        _, seg_esf = _esf(data, dist_px, sel & (rows_of >= a) & (rows_of < b), oversampling, half)
        if seg_esf is None:
            continue
        _, seg_mtf, _ = _mtf_from_esf(seg_esf, step_mm, oversampling, half, n_fft)
        if seg_mtf is not None:
            seg_mtfs.append(seg_mtf[keep])
    if len(seg_mtfs) >= 2:
        unc = np.std(np.asarray(seg_mtfs), axis=0, ddof=1) / math.sqrt(len(seg_mtfs))
    else:
        unc = np.full(int(keep.sum()), np.nan)
        warnings.append(f"{name}: the edge is too short to estimate the MTF uncertainty")
    length = data.shape[0]
    if direction == "horizontal":
        line = (0.0, intercept, float(length - 1), slope * (length - 1) + intercept)
    else:
        line = (intercept, 0.0, slope * (length - 1) + intercept, float(length - 1))
    return EdgeMTF(direction=direction, frequency_cy_per_mm=freq[keep], mtf=mtf[keep], mtf_uncertainty=unc,
                   angle_deg=angle, edge_line=tuple(float(v) for v in line), esf_distance_mm=dist, esf=esf,
                   lsf=lsf, n_segments=len(seg_mtfs), n_outliers=n_outliers, lsf_half_width_px=half,
                   warnings=warnings)
