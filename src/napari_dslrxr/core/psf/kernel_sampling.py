"""Sampling a blur component on the detector pixel grid, and the kernel finishing helpers.

Kernels are **pixel-area integrated** (each kernel value is the mean of the continuous PSF over
the detector pixel), computed by supersampling every pixel with an odd factor that grows as the
component narrows (``ceil(12 / FWHM_px)``, capped at 41). Point sampling at pixel centres, as
pysaber does, misrepresents components narrower than about 2 px (a 0.5 px FWHM exponential
point-sampled puts almost all mass in one pixel); area integration also matches the way a
detector pixel records the edge radiographs the model is fitted on.

The support of each component reaches ``10 * FWHM / 2`` (SABER's cutoff multiplier 10) and is
**never cropped to an image size**: a long detector tail keeps its full extent, limited only by
the ``max_radius_px`` argument (default :data:`DEFAULT_MAX_RADIUS_PX`).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ParameterError
from .mtf_shapes import fwhm_to_scale

#: Largest kernel half-width (pixels) when the caller gives none: a 4097 x 4097 kernel.
DEFAULT_MAX_RADIUS_PX = 2048
#: Support half-width of a component in units of its FWHM (SABER: 10 x FWHM / 2).
SUPPORT_FWHM_MULTIPLE = 5.0
#: Components narrower than this (pixels) are a delta function.
DELTA_FWHM_PX = 1e-3
_MAX_SUPERSAMPLING = 41


def _supersampling(fwhm_px: float) -> int:
    """Odd sub-samples per pixel and axis so that a component of this FWHM is well integrated."""
    n = int(math.ceil(12.0 / max(fwhm_px, 1e-6)))
    n = min(max(n, 1), _MAX_SUPERSAMPLING)
    return n if n % 2 == 1 else n + 1


def _radius_px(fwhm_px: float, max_radius_px: int) -> int:
    return int(min(math.ceil(SUPPORT_FWHM_MULTIPLE * fwhm_px), max_radius_px))


def _delta() -> np.ndarray:
    return np.ones((1, 1), dtype=np.float64)


def sample_exponential_power(fwhm_x_px: float, fwhm_y_px: float, shape_power: float, *,
                             radius_x_px: int, radius_y_px: int) -> np.ndarray:
    """Pixel-area-integrated ``exp(-((s_x x)^2 + (s_y y)^2)^(p/2))`` normalised to unit sum.

    Parameters
    ----------
    fwhm_x_px, fwhm_y_px : float
        FWHM along columns and rows, detector pixels (> 0).
    shape_power : float
        Exponential-power ``p``.
    radius_x_px, radius_y_px : int
        Half-width of the returned array (columns, rows); its shape is
        ``(2 radius_y_px + 1, 2 radius_x_px + 1)``.

    Returns
    -------
    ndarray of float64
        Centred kernel, sums to 1.
    """
    n = _supersampling(min(fwhm_x_px, fwhm_y_px))
    scale_x = fwhm_to_scale(fwhm_x_px, shape_power)
    scale_y = fwhm_to_scale(fwhm_y_px, shape_power)
    offsets = (np.arange(n) + 0.5) / n - 0.5
    x = (np.arange(-radius_x_px, radius_x_px + 1)[:, None] + offsets[None, :]).ravel()
    y = (np.arange(-radius_y_px, radius_y_px + 1)[:, None] + offsets[None, :]).ravel()
    r2 = (scale_y * y[:, None]) ** 2 + (scale_x * x[None, :]) ** 2
    values = np.exp(-(r2 ** (shape_power / 2.0)))
    ny, nx = 2 * radius_y_px + 1, 2 * radius_x_px + 1
    kernel = values.reshape(ny, n, nx, n).sum(axis=(1, 3))
    return kernel / kernel.sum()


def _centre_pad(kernel: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    out = np.zeros(shape, dtype=kernel.dtype)
    r0 = (shape[0] - kernel.shape[0]) // 2
    c0 = (shape[1] - kernel.shape[1]) // 2
    out[r0:r0 + kernel.shape[0], c0:c0 + kernel.shape[1]] = kernel
    return out


def _centre_crop(kernel: np.ndarray, radius_px: int) -> np.ndarray:
    ry = min(radius_px, kernel.shape[0] // 2)
    rx = min(radius_px, kernel.shape[1] // 2)
    cy, cx = kernel.shape[0] // 2, kernel.shape[1] // 2
    return kernel[cy - ry:cy + ry + 1, cx - rx:cx + rx + 1]


def _finish(kernel: np.ndarray) -> np.ndarray:
    """Clip FFT round-off below zero, renormalise to unit sum, float32."""
    kernel = np.clip(kernel, 0.0, None)
    kernel = kernel / kernel.sum()
    return kernel.astype(np.float32)


def _check_cap(max_radius_px) -> int:
    if max_radius_px is None:
        return DEFAULT_MAX_RADIUS_PX
    if isinstance(max_radius_px, bool) or not float(max_radius_px).is_integer() or max_radius_px < 0:
        raise ParameterError(f"max_radius_px must be a non-negative integer, got {max_radius_px!r}")
    return int(max_radius_px)
