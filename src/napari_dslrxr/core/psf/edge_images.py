"""Edge radiographs for the fit: the input record, normalisation by flat and dark frames, the
impulse mask, and the first estimate of each edge's line and levels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..errors import InputError, ParameterError
from ..robust import robust_line_fit, robust_sigma
from .model import magnification_factor


@dataclass
class EdgeImage:
    """One radiograph of a straight, opaque edge.

    Parameters
    ----------
    image : ndarray, (H, W)
        Raw counts or already normalised transmission (any real dtype).
    source_to_object_mm, source_to_detector_mm : float
        SOD and SDD of this radiograph, mm.
    bright, dark : ndarray, (H, W), optional
        Open-beam (flat) and dark frames in the same units as ``image``; with both, the image is
        normalised to ``(image - dark) / (bright - dark)``; with ``bright`` only, ``image / bright``.
        Otherwise the transmission levels ``a, b`` absorb the scale.
    roi : (r0, c0, r1, c1), optional
        Pixel rectangle (end exclusive) holding one straight edge; default the whole image.
    name : str
        Label used in messages and in the fit report (for example the file name).
    """

    image: np.ndarray
    source_to_object_mm: float
    source_to_detector_mm: float
    bright: np.ndarray | None = None
    dark: np.ndarray | None = None
    roi: tuple[int, int, int, int] | None = None
    name: str = ""



@dataclass
class _Prepared:
    """One edge ready for fitting: masked pixels, their coordinates, initial edge parameters."""

    name: str
    values: np.ndarray          # normalised data of the used pixels, float64 (N,)
    x_px: np.ndarray            # column of each pixel relative to the ROI centre
    y_px: np.ndarray            # row of each pixel relative to the ROI centre
    magnification_m1: float     # ODD / SOD
    sod_mm: float
    sdd_mm: float
    angle_scale_px: float       # distance from ROI centre to its corner: angle is fitted as phi * this
    offset_px: float = 0.0
    angle_rad: float = 0.0
    low: float = 0.0
    high: float = 1.0
    shape: tuple[int, int] = (0, 0)
    keep: np.ndarray | None = None  # boolean (N,) after outlier rejection
    weight: np.ndarray | None = None  # inverse noise variance (N,), mean 1; ones until a noise model is fitted
    n_impulses_masked: int = 0



#: Smallest ROI side (and image side) the edge fit takes, in pixels. On the plugin's sample
#: edges, 8-12 px ROIs still gave the focal spot within 10 % but left the detector's tail
#: undetermined (0.4 to 6.4 mm for a true 1.0 mm); 32 px and more recover it.
MIN_ROI_PX = 16


def _as_float_image(arr, what: str, name: str) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.ndim == 3 and arr.shape[-1] in (3, 4):
        arr = arr[..., :3].mean(axis=-1)   # colour radiograph: mean of the channels
    if arr.ndim != 2 or min(arr.shape) < MIN_ROI_PX:
        raise InputError(name or what, f"{what} must be a 2-D image of at least {MIN_ROI_PX}x{MIN_ROI_PX} pixels, "
                                       f"got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise InputError(name or what, f"{what} must be real numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).any():
        raise InputError(name or what, f"{what} has no finite pixel")
    return arr


def normalise_edge_image(edge: EdgeImage) -> np.ndarray:
    """Flat/dark-normalised transmission of ``edge`` over its ROI (float64, NaN where undefined).

    Raises
    ------
    InputError
        Wrong shapes, non-numeric data, an empty ROI, or no positive open-beam signal.
    """
    name = edge.name or "edge image"
    image = _as_float_image(edge.image, "image", name)
    bright = None if edge.bright is None else _as_float_image(edge.bright, "bright frame", name)
    dark = None if edge.dark is None else _as_float_image(edge.dark, "dark frame", name)
    for label, frame in (("bright frame", bright), ("dark frame", dark)):
        if frame is not None and frame.shape != image.shape:
            raise InputError(name, f"{label} shape {frame.shape} differs from the image shape {image.shape}")
    if edge.roi is not None:
        roi = tuple(int(v) for v in edge.roi)
        if len(roi) != 4:
            raise ParameterError(f"{name}: roi must be [r0, c0, r1, c1]")
        r0, c0, r1, c1 = roi
        if not (0 <= r0 < r1 <= image.shape[0] and 0 <= c0 < c1 <= image.shape[1]):
            raise ParameterError(f"{name}: roi {list(roi)} is outside the {image.shape[0]}x{image.shape[1]} image")
        if r1 - r0 < MIN_ROI_PX or c1 - c0 < MIN_ROI_PX:
            raise ParameterError(f"{name}: roi {list(roi)} is smaller than {MIN_ROI_PX}x{MIN_ROI_PX} pixels")
        sl = (slice(r0, r1), slice(c0, c1))
        image = image[sl]
        bright = None if bright is None else bright[sl]
        dark = None if dark is None else dark[sl]
    if dark is not None:
        image = image - dark
        if bright is not None:
            bright = bright - dark
    if bright is not None:
        if not np.nanmedian(bright) > 0:
            raise InputError(name, "bright frame has no signal above the dark frame")
        with np.errstate(divide="ignore", invalid="ignore"):
            image = np.where(bright > 0, image / bright, np.nan)
    return image


#: Residual samples (evenly spaced over the region) the impulse noise model is fitted on.
_NOISE_MODEL_SAMPLES = 20000
#: Expectation-maximisation iterations of that fit (as the impulse stage's default).
_NOISE_MODEL_ITERATIONS = 30


def _impulse_mask(y: np.ndarray) -> np.ndarray:
    """Bright impulses: > 8 sigmas above the 5x5 median, dilated by one pixel.

    The sigma is per pixel: the variance ``a * level + b`` (photon noise plus a read-noise
    floor) of the impulse stage's noise model, fitted by expectation-maximisation on the
    residuals to the 5x5 median (a Gaussian + uniform-pulse mixture, so the hits do not inflate
    it) and evaluated at each pixel's median. One sigma for the whole region would mask the
    ordinary photon noise of the bright side when the dark side is much quieter.
    """
    from ..stages.impulse.noise_model import _fit_mixture

    finite = np.isfinite(y)
    filled = np.where(finite, y, np.nanmedian(y))
    median = ndimage.median_filter(filled, size=5, mode="reflect")
    excess = filled - median
    index = np.flatnonzero(finite)
    index = index[np.linspace(0, index.size - 1, min(index.size, _NOISE_MODEL_SAMPLES)).astype(int)]
    lo, hi = np.percentile(filled[finite], [0.1, 99.9])
    if not hi > lo or robust_sigma(excess.ravel()[index]) <= 0:
        return np.zeros(y.shape, bool)
    model = _fit_mixture(excess.ravel()[index], median.ravel()[index], photon_counting=True, polarity=1,
                         value_range=float(hi - lo), iterations=_NOISE_MODEL_ITERATIONS)
    sigma = np.sqrt(model.variance(median))
    return ndimage.binary_dilation(excess > 8.0 * sigma, iterations=1)


#: Smallest bright-dark step (in pixel-noise sigmas) accepted as an edge.
EDGE_MIN_STEP_SIGMA = 5.0


def _detect_edge(y: np.ndarray, valid: np.ndarray, name: str):
    """Initial straight-edge line: ``(x0, y0, nx, ny)`` through a point with the normal to the bright side."""
    filled = np.where(valid, y, np.nanmedian(y[valid]))
    smooth = ndimage.gaussian_filter(ndimage.median_filter(filled, size=3), 1.5)
    lo, hi = np.percentile(smooth[valid], [2, 98])
    if not hi - lo > 0:
        raise InputError(name, "no edge found: the region is flat")
    # Pixel noise (robust, from the residual of a 3x3 median): a region of noise alone spans
    # about one noise sigma after the smoothing above; an edge worth fitting spans many.
    noise = robust_sigma((filled - ndimage.median_filter(filled, size=3))[valid], center=0.0)
    if hi - lo < EDGE_MIN_STEP_SIGMA * noise:
        raise InputError(name, f"no edge found: the brightness step ({(hi - lo) / noise:.1f} noise sigma) is too "
                               f"small; draw the ROI across a sharp edge")
    mid = 0.5 * (lo + hi)
    gy = ndimage.sobel(smooth, axis=0)
    gx = ndimage.sobel(smooth, axis=1)
    across_columns = float((gx ** 2).sum()) >= float((gy ** 2).sum())
    data = smooth if across_columns else smooth.T
    grad = np.abs(gx) if across_columns else np.abs(gy).T
    rows, cols = [], []
    for r in range(data.shape[0]):
        prof = data[r] - mid
        crossings = np.nonzero(np.signbit(prof[:-1]) != np.signbit(prof[1:]))[0]
        if crossings.size == 0:
            continue
        k = crossings[np.argmax(grad[r, crossings])]
        denom = prof[k] - prof[k + 1]
        frac = prof[k] / denom if denom != 0 else 0.5
        rows.append(r)
        cols.append(k + frac)
    rows, cols = np.asarray(rows, float), np.asarray(cols, float)
    if rows.size < 8:
        raise InputError(name, "no straight edge found in the region (give an roi holding one edge)")
    line = robust_line_fit(rows, cols, rounds=3, clip_sigma=3.0, min_spread=0.5, min_points=8)
    if line is None:
        raise InputError(name, "no straight edge found in the region (give an roi holding one edge)")
    slope, intercept = line
    # Line col = slope * row + intercept (in transposed coordinates when the edge is horizontal).
    r_mid = 0.5 * (data.shape[0] - 1)
    point = (slope * r_mid + intercept, r_mid)             # (col, row) in the scanned frame
    normal = np.array([1.0, -slope]) / math.hypot(1.0, slope)  # (d col, d row)
    if across_columns:
        x0, y0, nx, ny = point[0], point[1], normal[0], normal[1]
    else:
        x0, y0, nx, ny = point[1], point[0], normal[1], normal[0]
    rr, cc = np.nonzero(valid)
    side = (cc - x0) * nx + (rr - y0) * ny
    if np.median(filled[rr[side > 0], cc[side > 0]]) < np.median(filled[rr[side < 0], cc[side < 0]]):
        nx, ny = -nx, -ny
    return float(x0), float(y0), float(nx), float(ny), float(lo), float(hi)


def _prepare(edge: EdgeImage, index: int, mask_impulses: bool) -> _Prepared:
    name = edge.name or f"edge {index}"
    m1 = magnification_factor(edge.source_to_object_mm, edge.source_to_detector_mm)
    y = normalise_edge_image(edge)
    valid = np.isfinite(y)
    n_impulses = 0
    if mask_impulses:
        impulses = _impulse_mask(y) & valid
        n_impulses = int(impulses.sum())
        valid &= ~impulses
    if valid.sum() < MIN_ROI_PX * MIN_ROI_PX:
        raise InputError(name, f"fewer than {MIN_ROI_PX * MIN_ROI_PX} usable pixels in the region")
    x0, y0, nx, ny, lo, hi = _detect_edge(y, valid, name)
    h, w = y.shape
    yc, xc = 0.5 * (h - 1), 0.5 * (w - 1)
    rr, cc = np.nonzero(valid)
    prep = _Prepared(name=name, values=y[rr, cc], x_px=cc - xc, y_px=rr - yc, magnification_m1=m1,
                     sod_mm=float(edge.source_to_object_mm), sdd_mm=float(edge.source_to_detector_mm),
                     angle_scale_px=max(math.hypot(xc, yc), 1.0), shape=(h, w), n_impulses_masked=n_impulses)
    prep.angle_rad = math.atan2(ny, nx)
    prep.offset_px = (x0 - xc) * nx + (y0 - yc) * ny
    d = prep.x_px * nx + prep.y_px * ny - prep.offset_px
    far_dark, far_bright = prep.values[d < -8], prep.values[d > 8]
    prep.low = float(np.median(far_dark)) if far_dark.size > 16 else lo
    prep.high = float(np.median(far_bright)) if far_bright.size > 16 else hi
    prep.keep = np.ones(prep.values.size, bool)
    prep.weight = np.ones(prep.values.size)
    return prep
