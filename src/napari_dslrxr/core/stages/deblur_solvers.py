"""The deconvolution solvers and what they share with the automatic regularisation.

* the checks of the kernel and the image (the method and ``reg`` are checked by
  :mod:`.deblur_params`);
* the robust range and the white-noise estimate of an image (the units ``reg`` is expressed in);
* the closed-form Fourier solvers of one channel (Wiener, gradient-regularised least squares, and
  the Fortunato-Oliveira sparse adaptive prior with its edge-aware smoothing and shrinkage).

:mod:`.deconvolution` (the stage: parameters, :func:`~.deconvolution.deconvolve`) and
:mod:`.regularisation` (``reg = "auto"``) both build on this module, which imports neither; the
method and its constants are described in :mod:`.deconvolution`.
"""

from __future__ import annotations

import math
from collections.abc import Generator

import numpy as np

from ..errors import InputError

#: Range used for the robust normalisation (percentiles of the image).
_RANGE_PERCENTILES = (0.1, 99.9)

# Fortunato-Oliveira constants relative to the noise sigma_n of the normalised image. The paper's
# defaults for [0, 1] natural images at 1 % noise correspond to lam_d = 6.5 / 3.25 sigma_n,
# range sigma 3.3 sigma_n, w4 / w1 = 50 and one pass; these were re-chosen on synthetic
# phantoms and the NEMA leg radiograph (benchmarks/eval_deconvolution.py).
_FO_SIGMA_SPATIAL_PX = 20.0
_FO_W4_OVER_W1 = 5.0
_FO_SIGMA_R_PER_NOISE = 10.0
_FO_LAMBDA1_PER_NOISE = 1.0
_FO_LAMBDA2_PER_NOISE = 0.5
#: Smoothing + sparse-target + solve passes (the paper does one; more passes re-guide from the
#: previous result: no measurable gain on our cases, twice the time).
_FO_PASSES = 1




# --------------------------------------------------------------------------- validation


def validate_kernel(kernel: np.ndarray, source: str = "kernel") -> np.ndarray:
    """Check a blur kernel and return it as float32 normalised to unit sum.

    Parameters
    ----------
    kernel : ndarray
        2-D array with odd sides (the centre pixel is the origin), finite, non-negative, with a
        positive sum.
    source : str
        Name used in the error message (a file name, for example).

    Returns
    -------
    ndarray of float32
        The kernel divided by its sum.
    """
    k = np.asarray(kernel)
    if k.ndim != 2 or k.size == 0:
        raise InputError(source, f"blur kernel must be a 2-D array, got shape {k.shape}")
    if k.shape[0] % 2 == 0 or k.shape[1] % 2 == 0:
        raise InputError(source, f"blur kernel must have odd sides (centre = origin), got {k.shape[0]}x{k.shape[1]}")
    if k.dtype.kind not in "uif":
        raise InputError(source, f"blur kernel has unsupported dtype {k.dtype}")
    k = k.astype(np.float64)
    if not np.all(np.isfinite(k)):
        raise InputError(source, "blur kernel contains NaN or infinite values")
    if k.min() < -1e-6 * max(float(k.max()), 1e-30):
        raise InputError(source, f"blur kernel has negative values (min {k.min():.3g})")
    total = float(np.clip(k, 0, None).sum())
    if not total > 0:
        raise InputError(source, "blur kernel sums to zero")
    return (np.clip(k, 0, None) / total).astype(np.float32)


def _validate_image(image: np.ndarray) -> np.ndarray:
    arr = np.asarray(image)
    if arr.dtype.kind not in "uif":
        raise InputError("image", f"unsupported dtype {arr.dtype}")
    if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[-1] == 3)):
        raise InputError("image", f"expected (H, W) or (H, W, 3), got shape {arr.shape}")
    if min(arr.shape[:2]) < 3:
        raise InputError("image", f"image too small for deconvolution: {arr.shape[0]}x{arr.shape[1]}")
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise InputError("image", "image contains NaN or infinite values")
    return arr


# --------------------------------------------------------------------------- noise, scale


def robust_range(image: np.ndarray) -> tuple[float, float]:
    """Return ``(offset, scale)``: the 0.1 percentile and the 0.1-99.9 percentile span (> 0).

    Parameters
    ----------
    image : ndarray
        Any real image; large images are subsampled (every 4th pixel) for speed.
    """
    arr = np.asarray(image)
    sample = arr[::4, ::4] if arr.shape[0] * arr.shape[1] > 4_000_000 else arr
    lo, hi = np.percentile(sample, _RANGE_PERCENTILES)
    scale = float(hi - lo)
    if not scale > 0:
        scale = float(np.max(np.abs(sample))) or 1.0
    return float(lo), scale


def estimate_noise_sigma(image: np.ndarray, block_px: int = 32) -> float:
    """Estimate the root-mean-square white-noise level, aware of signal-dependent (Poisson) noise.

    The finest diagonal Haar band ``d = (a - b - c + e) / 2`` over disjoint 2x2 pixel blocks
    carries the noise's variance and almost none of a blurred image's signal. A robust
    ``sigma_b = median(|d|) / 0.6745`` is taken per ``block_px`` square tile, and the result is
    ``sqrt(mean(sigma_b^2))``: the average noise variance over the image, which is what a
    Fourier-domain solver sees when the variance follows the signal (Poisson); a single global
    median would report the darkest, quietest regions instead.

    Parameters
    ----------
    image : ndarray (H, W)
        Grey image, any units.
    block_px : int
        Tile side in pixels (even).

    Returns
    -------
    float
        Noise standard deviation in the image's units.
    """
    return float(np.sqrt(np.mean(noise_sigma_tiles(image, block_px) ** 2)))


def noise_sigma_tiles(image: np.ndarray, block_px: int = 32) -> np.ndarray:
    """Robust noise sigma of each ``block_px`` tile (see :func:`estimate_noise_sigma`), float64, 1-D."""
    arr = np.asarray(image, dtype=np.float32)
    h, w = (arr.shape[0] // 2) * 2, (arr.shape[1] // 2) * 2
    d = (arr[0:h:2, 0:w:2] - arr[0:h:2, 1:w:2]) - (arr[1:h:2, 0:w:2] - arr[1:h:2, 1:w:2])
    np.abs(d, out=d)
    b = max(block_px // 2, 4)
    bh, bw = d.shape[0] // b, d.shape[1] // b
    if bh == 0 or bw == 0:
        return np.array([float(np.median(d)) * 0.5 / 0.6744897501960817])
    tiles = d[:bh * b, :bw * b].reshape(bh, b, bw, b)
    if bh * bw > 4096:  # large image: every other tile row and column is plenty
        tiles = tiles[::2, :, ::2, :]
    tiles = tiles.transpose(0, 2, 1, 3).reshape(-1, b * b)
    return np.median(tiles, axis=1).astype(np.float64) * (0.5 / 0.6744897501960817)


def _luminance(arr: np.ndarray) -> np.ndarray:
    return arr if arr.ndim == 2 else arr.astype(np.float32).mean(axis=2)


def _channels(arr: np.ndarray) -> list[np.ndarray]:
    return [arr] if arr.ndim == 2 else [arr[..., i] for i in range(arr.shape[-1])]


def _channel_noise(arr: np.ndarray, scale: float) -> float:
    """Relative noise sigma_n: root-mean-square over channels of their noise, over ``scale``."""
    variances = [estimate_noise_sigma(ch) ** 2 for ch in _channels(arr)]
    return _noise_floor(math.sqrt(float(np.mean(variances))) / scale)


def _noise_floor(sigma_n: float) -> float:
    """Relative noise never below 1e-4 of the range (noise-free synthetic data)."""
    return max(float(sigma_n), 1e-4)


# --------------------------------------------------------------------------- solvers


def _shrink(g: np.ndarray, lam: float, tmp: np.ndarray) -> np.ndarray:
    """In place ``g <- g^5 / (g^4 + lam^4) = g - g lam^4 / (g^4 + lam^4)`` (float32, no allocation)."""
    lam4 = np.float32(lam ** 4)
    np.multiply(g, g, out=tmp)
    np.multiply(tmp, tmp, out=tmp)  # g^4
    tmp += lam4
    np.divide(lam4, tmp, out=tmp)
    tmp *= g
    g -= tmp
    return g


def _sparse_targets(smooth: np.ndarray, lam1: float, lam2: float, strip_rows: int = 128) -> np.ndarray:
    """``b1 = sum_d f_d^T * rho(f_d * smooth; lam_d)`` with the five FO filters (float32).

    Correlations with 2-3 tap filters via ``cv2.filter2D``; the adjoint of a correlation is
    the correlation with the flipped kernel (and flipped anchor). The image is processed in
    strips of ``strip_rows`` rows (with a 2-row halo, so the result equals the whole-image
    computation) so the ~40 elementwise passes run in cache instead of main memory.
    """
    import cv2

    half = np.float32(0.5)
    r2 = np.float32(1.0 / math.sqrt(2.0))
    s2 = np.float32(math.sqrt(2.0))
    fx = np.array([[-half, 0, half]], np.float32)
    fxx = np.array([[-r2, 2 * r2, -r2]], np.float32)
    fxy = np.array([[-s2, s2], [s2, -s2]], np.float32)
    specs = (  # filter, adjoint, threshold, adjoint anchor
        (fx, -fx, lam1, (-1, -1)),
        (fx.T.copy(), -fx.T.copy(), lam1, (-1, -1)),
        (fxx, fxx, lam2, (-1, -1)),
        (fxx.T.copy(), fxx.T.copy(), lam2, (-1, -1)),
        (fxy, fxy, lam2, (0, 0)),
    )
    border = cv2.BORDER_REPLICATE
    height, width = smooth.shape
    halo = 2
    b1 = np.empty_like(smooth)
    ext_rows = strip_rows + 2 * halo
    g_buf = np.empty((ext_rows, width), np.float32)
    tmp_buf = np.empty((ext_rows, width), np.float32)
    acc_buf = np.empty((ext_rows, width), np.float32)
    for r0 in range(0, height, strip_rows):
        r1 = min(height, r0 + strip_rows)
        e0, e1 = max(0, r0 - halo), min(height, r1 + halo)
        src = smooth[e0:e1]
        n = e1 - e0
        g, tmp, acc = g_buf[:n], tmp_buf[:n], acc_buf[:n]
        for i, (filt, adjoint, lam, adj_anchor) in enumerate(specs):
            cv2.filter2D(src, cv2.CV_32F, filt, dst=g, borderType=border)
            _shrink(g, lam, tmp)
            if i == 0:
                cv2.filter2D(g, cv2.CV_32F, adjoint, dst=acc, anchor=adj_anchor, borderType=border)
            else:
                cv2.filter2D(g, cv2.CV_32F, adjoint, dst=tmp, anchor=adj_anchor, borderType=border)
                acc += tmp
        b1[r0:r1] = acc[r0 - e0:r0 - e0 + (r1 - r0)]
    return b1


def _edge_aware_smooth(x: np.ndarray, sigma_r: float) -> np.ndarray:
    """Gastal-Oliveira domain-transform recursive filter of a float32 image guided by itself."""
    import cv2

    return cv2.ximgproc.dtFilter(x, x, _FO_SIGMA_SPATIAL_PX, sigma_r,
                                 mode=cv2.ximgproc.DTF_RF, numIters=1)


def _solve_channel(y: np.ndarray, otf_conj: np.ndarray, k2: np.ndarray, reg_spectrum: np.ndarray | None,
                   method: str, lam: float, sigma_n: float, shape: tuple[int, int],
                   ) -> Generator[int, None, np.ndarray]:
    """Deconvolve one padded, tapered, normalised, zero-mean channel; yields after each step.

    ``otf_conj`` is conj(K) (complex64), ``k2`` = |K|^2 (float32), both on the rfft2 grid.
    """
    import scipy.fft as sfft

    Y = sfft.rfft2(y, workers=-1)
    del y
    Y *= otf_conj  # Y <- conj(K) Y
    yield 1
    if method in ("wiener", "rls"):
        if method == "wiener":
            denom = k2 + np.float32(lam)
        else:
            denom = reg_spectrum * np.float32(lam)
            denom += k2
        Y /= denom
        del denom
        yield 1
        return sfft.irfft2(Y, s=shape, workers=-1, overwrite_x=True)
    # adaptive: w4 = lam, w1 = lam / _FO_W4_OVER_W1
    w4 = np.float32(lam)
    w1 = np.float32(lam / _FO_W4_OVER_W1)
    denom = reg_spectrum * w1
    denom += k2
    x = sfft.irfft2(Y / denom, s=shape, workers=-1, overwrite_x=True)
    yield 1
    sigma_r = float(_FO_SIGMA_R_PER_NOISE * sigma_n)
    np.multiply(reg_spectrum, w4, out=denom)
    denom += k2
    for _ in range(_FO_PASSES):
        # Edge-aware smoothing of the current estimate guides the sparse derivative targets.
        smooth = _edge_aware_smooth(x, sigma_r)
        del x
        b1 = _sparse_targets(smooth, _FO_LAMBDA1_PER_NOISE * sigma_n, _FO_LAMBDA2_PER_NOISE * sigma_n)
        del smooth
        yield 1
        B1 = sfft.rfft2(b1, workers=-1).astype(np.complex64, copy=False)
        del b1
        B1 *= w4
        B1 += Y
        B1 /= denom
        x = sfft.irfft2(B1, s=shape, workers=-1, overwrite_x=True)
        del B1
        yield 1
    return x
