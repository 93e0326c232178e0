"""Non-blind deconvolution: Wiener, gradient-regularised least squares, and the sparse adaptive prior.

Three closed-form Fourier-domain solvers for ``y = k * x + n`` with a known, shift-invariant
blur kernel ``k`` (for example :meth:`napari_dslrxr.core.psf.PSFModel.kernel` at the object's
geometry):

``"wiener"``
    Classic Wiener filter with a constant noise-to-signal ratio,
    ``X = conj(K) Y / (|K|^2 + lam_w)``.
``"rls"``
    Regularised least squares with a gradient prior (Tikhonov on forward differences),
    ``X = conj(K) Y / (|K|^2 + lam (|Dx|^2 + |Dy|^2))``.
``"adaptive"`` (default)
    The sparse adaptive prior of Fortunato and Oliveira (The Visual Computer 30:661-671, 2014):
    a Tikhonov estimate (weight ``w1``), an edge-aware domain-transform smoothing of it
    (``cv2.ximgproc.dtFilter``, recursive filter), a sparsifying shrinkage
    ``rho(t; lam_d) = t^5 / (t^4 + lam_d^4)`` of its five derivatives, and a second closed-form
    solve (weight ``w4``) that pulls the derivatives of the result towards those targets. We
    express the paper's constants relative to the noise (radiographs are not natural photos;
    at the published absolute defaults the prior lost to Wiener): ``w4 = reg sigma_n^2``,
    ``w1 = w4 / 5``, ``lam_d = 1.0 sigma_n`` (first derivatives) and ``0.5 sigma_n`` (second),
    range sigma ``10 sigma_n``, spatial sigma 20 px.

The regularisation knob
-----------------------
All three methods take one dimensionless knob ``reg``. The image is first normalised by a
robust range (0.1 to 99.9 percentile), and the white-noise standard deviation ``sigma_n`` of
the normalised image is estimated (:func:`estimate_noise_sigma`). ``reg`` is the *prior
precision of the image gradient* in those units: every method regularises with a weight
``reg * sigma_n**2`` (a Gaussian gradient prior of variance ``1/reg`` has exactly this MAP
weight), so doubling ``reg`` doubles the smoothing in every method and on every image, and the
same value means the same trade-off whatever the exposure. Useful values span about 1 to 1e5
(show it on a log slider). ``reg="auto"`` chooses it from the data (module :mod:`.regularisation`,
:func:`~napari_dslrxr.core.stages.regularisation.estimate_regularisation`):
a Whittle maximum-likelihood fit of the observed power spectrum to ``c |K|^2 / |D|^2 + s2``
gives the gradient variance ``c`` of the sharp image and the average noise variance ``s2``;
the MSE-optimal Tikhonov weight under that model is ``s2 / c``, scaled by one fixed
per-method constant (calibrated once, never per image). The sparse prior's shrinkage
thresholds and the smoother's range sigma scale with ``sigma_n`` as well.

Borders
-------
Each channel is replicate-padded by at least twice the kernel radius per side (more, up to
the next fast FFT length), and the padding is blended with a raised cosine towards the image
mean, so the periodic model of the FFT holds without a seam: a bright object at one border
does not wrap to the opposite one. Colour images are deconvolved per channel, reusing the
kernel OTF and the regulariser spectra.

All arithmetic is float32/complex64 with ``scipy.fft`` real transforms on all cores; the
adaptive prior needs 2 + 2 x passes large FFTs per channel (``Y``, ``x0``, then ``B1`` and
``x`` per pass) plus the kernel OTF once per image; derivative spectra are closed-form cosines.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..param_fields import check_value, validate_fields
from .fourier import fo_derivative_spectrum, gradient_spectrum, kernel_otf, pad_and_taper, padded_shape

METHODS = ("adaptive", "wiener", "rls")

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

#: Bounds for reg (beyond them the solution is either the inverse filter or a flat image).
REG_MIN, REG_MAX = 1e-3, 1e9


@dataclass
class DeconvolutionParams:
    """Parameters of the deconvolution stage (TOML section ``[deblur]``), checked on construction.

    The one class of the section: ``dslrxr run`` (where deblurring runs only when a PSF model is
    given), ``dslrxr deconvolve`` and the deconvolution widget all use it.

    Attributes
    ----------
    method : str
        ``"adaptive"`` (sparse adaptive prior, default), ``"wiener"`` or ``"rls"``.
    reg : float or str
        The regularisation knob (dimensionless prior precision of the image gradient, relative
        to the noise; see the module docstring) or ``"auto"`` to estimate it from the image.
    """

    method: str = field(default="adaptive", metadata={
        "help": "deconvolution method (in a pipeline run only when a PSF model is given)", "choices": METHODS})
    reg: float | str = field(default="auto", metadata={
        "help": "regularisation knob, larger = smoother (prior precision of the image gradient relative "
                "to the noise), or \"auto\" to estimate it from the image",
        "min": REG_MIN, "max": REG_MAX, "auto": True})

    def __post_init__(self) -> None:
        validate_fields(self, "deblur")

    def validate(self) -> DeconvolutionParams:
        """The values are checked on construction; kept for callers that re-check after edits."""
        validate_fields(self, "deblur")
        return self


# --------------------------------------------------------------------------- validation


def check_method(method: str) -> str:
    """Return ``method`` if it is one of :data:`METHODS`, else raise :class:`ParameterError`."""
    return check_value(DeconvolutionParams, "deblur", "method", method)


def check_reg(reg: float | str) -> float | str:
    """Return ``reg`` as ``"auto"`` or a float in [REG_MIN, REG_MAX]; else raise ParameterError.

    Text (a command-line value) that reads as a number is taken as that number.
    """
    if isinstance(reg, str) and reg.strip().lower() != "auto":
        try:
            reg = float(reg)
        except ValueError:
            pass  # refused below with the parameter file's message
    return check_value(DeconvolutionParams, "deblur", "reg", reg)


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


_STEPS_PER_CHANNEL = {"wiener": 3, "rls": 3, "adaptive": 3 + 2 * _FO_PASSES}


def deconvolve_steps(image: np.ndarray, kernel: np.ndarray, *, method: str = "adaptive",
                     reg: float | str = "auto") -> Generator[tuple[int, int], None, np.ndarray]:
    """Generator form of :func:`deconvolve`: yields ``(done, total)`` and returns the result.

    Use ``result = yield from deconvolve_steps(...)`` or drive it with ``next()`` and read
    ``StopIteration.value``; stop iterating to cancel.
    """
    check_method(method)
    reg = check_reg(reg)
    arr = _validate_image(image)
    k = validate_kernel(kernel)
    channels = _channels(arr)
    total = 1 + len(channels) * _STEPS_PER_CHANNEL[method]
    done = 0

    h, w = arr.shape[:2]
    shape = padded_shape((h, w), k.shape)
    grey = _luminance(arr).astype(np.float32, copy=False)
    _, scale = robust_range(grey)
    if reg == "auto":
        from .regularisation import estimate_regularisation

        reg = estimate_regularisation(arr, k, method)
    sigma_n = _channel_noise(arr, scale)
    lam = float(reg) * sigma_n ** 2
    otf_conj = kernel_otf(k, shape)
    k2 = np.square(otf_conj.real)
    k2 += np.square(otf_conj.imag)
    np.conjugate(otf_conj, out=otf_conj)
    if method == "rls":
        reg_spectrum = gradient_spectrum(shape)
    elif method == "adaptive":
        reg_spectrum = fo_derivative_spectrum(shape)
    else:
        reg_spectrum = None
    done += 1
    yield done, total

    out = np.empty(arr.shape, dtype=np.float32)
    for i, ch in enumerate(channels):
        # Work on (v - mean) / scale: zero-mean, so the Wiener constant cannot dim the image
        # and the tapered padding fades to 0.
        mean = float(ch.mean(dtype=np.float64))
        padded, (r0, c0) = pad_and_taper(ch.astype(np.float32, copy=False), shape, mean)
        padded -= np.float32(mean)
        padded *= np.float32(1.0 / scale)
        solver = _solve_channel(padded, otf_conj, k2, reg_spectrum, method, lam, sigma_n, shape)
        del padded
        while True:
            try:
                next(solver)
            except StopIteration as stop:
                x = stop.value
                break
            done += 1
            yield done, total
        target = out if arr.ndim == 2 else out[..., i]
        np.multiply(x[r0:r0 + h, c0:c0 + w], np.float32(scale), out=target)
        target += np.float32(mean)
        del x
        done += 1
        yield done, total
    np.nan_to_num(out, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    return out


def deconvolve(image: np.ndarray, kernel: np.ndarray, *, method: str = "adaptive",
               reg: float | str = "auto",
               progress: Callable[[int, int], object] | None = None) -> np.ndarray:
    """Remove a known shift-invariant blur from a linear image.

    Parameters
    ----------
    image : ndarray (H, W) or (H, W, 3)
        Blurred image in linear intensity (counts or normalised), any real dtype; no NaN.
    kernel : ndarray
        Blur kernel on the image's pixel grid, odd sides, non-negative (normalised here), for
        example ``PSFModel.kernel(source_to_object_mm, source_to_detector_mm)``.
    method : str
        ``"adaptive"`` (Fortunato-Oliveira sparse adaptive prior), ``"wiener"`` or ``"rls"``.
    reg : float or "auto"
        Regularisation knob (gradient prior precision relative to the noise; larger = smoother),
        or ``"auto"`` for :func:`~napari_dslrxr.core.stages.regularisation.estimate_regularisation`.
    progress : callable, optional
        Called as ``progress(done, total)`` after each step.

    Returns
    -------
    ndarray of float32
        Same shape as ``image``, in the image's units; not clipped (may undershoot zero or
        overshoot the input range slightly), NaN-free.
    """
    gen = deconvolve_steps(image, kernel, method=method, reg=reg)
    while True:
        try:
            done, total = next(gen)
        except StopIteration as stop:
            return stop.value
        if progress is not None:
            progress(done, total)
