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
    a Tikhonov estimate, an edge-aware domain-transform smoothing of it, a sparsifying
    shrinkage ``rho(t; lam_d) = t^5 / (t^4 + lam_d^4)`` of its five derivatives, and a second
    closed-form solve that pulls the derivatives of the result towards those targets.

The regularisation knob
-----------------------
All three methods take one dimensionless knob ``reg``. The image is first normalised by a
robust range (0.1 to 99.9 percentile), and the white-noise standard deviation ``sigma_n`` of
the normalised image is estimated (:func:`estimate_noise_sigma`). ``reg`` is the *prior
precision of the image gradient* in those units: every method regularises with a weight
``reg * sigma_n**2`` (a Gaussian gradient prior of variance ``1/reg`` has exactly this MAP
weight), so doubling ``reg`` doubles the smoothing in every method and on every image, and the
same value means the same trade-off whatever the exposure. Useful values span about 1 to 1e5
(show it on a log slider). ``reg="auto"`` chooses it from the data (:func:`estimate_regularisation`):
a Whittle maximum-likelihood fit of the observed power spectrum to ``c |K|^2 / |D|^2 + sigma^2``
gives the gradient variance ``c`` of the sharp image and the noise floor; ``reg = kappa / c``
with one fixed per-method constant ``kappa`` (calibrated once, never per image). The sparse
prior's shrinkage thresholds and the smoother's range sigma scale with ``sigma_n`` as well.

Borders
-------
Each channel is replicate-padded by at least twice the kernel radius per side (more, up to
the next fast FFT length), and the padding is blended with a raised cosine towards the image
mean, so the periodic model of the FFT holds without a seam: a bright object at one border
does not wrap to the opposite one. Colour images are deconvolved per channel, reusing the
kernel OTF and the regulariser spectra.

All arithmetic is float32/complex64 with ``scipy.fft`` real transforms on all cores; the
adaptive prior needs five large FFTs per channel (kernel OTF once, ``Y``, ``x0``, ``B1``, ``x``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from .errors import InputError, ParameterError

METHODS = ("adaptive", "wiener", "rls")

#: Range used for the robust normalisation (percentiles of the image).
_RANGE_PERCENTILES = (0.1, 99.9)

# Fortunato-Oliveira constants (paper defaults for [0, 1] images at 1 % noise), re-expressed
# relative to the noise: lam_d = 6.5 sigma_n (first derivatives), 3.25 sigma_n (second),
# smoother range sigma 3.3 sigma_n, spatial sigma 20 px, w4 / w1 = 50.
_FO_SIGMA_SPATIAL_PX = 20.0
_FO_W4_OVER_W1 = 50.0
_FO_SIGMA_R_PER_NOISE = 10.0
_FO_LAMBDA1_PER_NOISE = 3.0
_FO_LAMBDA2_PER_NOISE = 1.5
#: Smoothing + sparse-target + solve passes (the paper does one; later passes re-guide from
#: the previous result).
_FO_PASSES = 1

#: Per-method constants kappa of the automatic choice reg = kappa / c (see module docstring).
_AUTO_KAPPA = {"wiener": 0.3, "rls": 1.0, "adaptive": 10.0}

#: Bounds for reg (beyond them the solution is either the inverse filter or a flat image).
REG_MIN, REG_MAX = 1e-3, 1e9


@dataclass
class DeconvolutionParams:
    """Parameters of the deconvolution stage (TOML section ``[deblur]``).

    Attributes
    ----------
    method : str
        ``"adaptive"`` (sparse adaptive prior, default), ``"wiener"`` or ``"rls"``.
    reg : float or str
        The regularisation knob (dimensionless prior precision of the image gradient, relative
        to the noise; see the module docstring) or ``"auto"`` to estimate it from the image.
    """

    method: str = "adaptive"
    reg: float | str = "auto"

    def validate(self) -> DeconvolutionParams:
        """Check the values; raise :class:`ParameterError` with a one-line message."""
        check_method(self.method)
        check_reg(self.reg)
        return self


# --------------------------------------------------------------------------- validation


def check_method(method: str) -> str:
    """Return ``method`` if it is one of :data:`METHODS`, else raise :class:`ParameterError`."""
    if method not in METHODS:
        raise ParameterError(f"deblur method: expected one of {', '.join(METHODS)}, got {method!r}")
    return method


def check_reg(reg: float | str) -> float | str:
    """Return ``reg`` as ``"auto"`` or a float in [REG_MIN, REG_MAX]; else raise ParameterError."""
    if isinstance(reg, str):
        if reg.strip().lower() == "auto":
            return "auto"
        try:
            reg = float(reg)
        except ValueError:
            raise ParameterError(f"deblur reg: expected a positive number or 'auto', got {reg!r}") from None
    value = float(reg)
    if not math.isfinite(value) or not REG_MIN <= value <= REG_MAX:
        raise ParameterError(f"deblur reg: must be 'auto' or between {REG_MIN:g} and {REG_MAX:g}, got {reg!r}")
    return value


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


def estimate_noise_sigma(image: np.ndarray) -> float:
    """Estimate the standard deviation of white noise from the finest diagonal Haar band.

    ``d = (a - b - c + e) / 2`` over disjoint 2x2 blocks has the noise's variance and almost no
    signal (a blurred image has little energy at the highest diagonal frequencies);
    ``sigma = median(|d|) / 0.6745``. For Poisson noise this is the root-mean variance.

    Parameters
    ----------
    image : ndarray (H, W)
        Grey image, any units.

    Returns
    -------
    float
        Noise standard deviation in the image's units.
    """
    arr = np.asarray(image, dtype=np.float32)
    h, w = (arr.shape[0] // 2) * 2, (arr.shape[1] // 2) * 2
    a = arr[0:h:2, 0:w:2]
    b = arr[0:h:2, 1:w:2]
    c = arr[1:h:2, 0:w:2]
    e = arr[1:h:2, 1:w:2]
    d = (a - b) - (c - e)
    return float(np.median(np.abs(d))) * 0.5 / 0.6744897501960817


# --------------------------------------------------------------------------- spectra


def _padded_shape(shape: tuple[int, int], kernel_shape: tuple[int, int]) -> tuple[int, int]:
    """FFT-friendly size with >= 2 kernel radii (and >= 4 px) of padding on each side."""
    out = []
    for n, k in zip(shape, kernel_shape):
        pad = max(2 * ((k - 1) // 2), 4)
        out.append(sfft.next_fast_len(n + 2 * pad, real=True))
    return out[0], out[1]


def _frequency_cosines(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``cos(omega)`` along rows (column vector, full) and columns (row vector, half) for rfft2."""
    wy = 2 * np.pi * np.fft.fftfreq(shape[0])
    wx = 2 * np.pi * np.fft.rfftfreq(shape[1])
    return np.cos(wy).astype(np.float32)[:, None], np.cos(wx).astype(np.float32)[None, :]


def gradient_spectrum(shape: tuple[int, int]) -> np.ndarray:
    """``|Dx|^2 + |Dy|^2`` of forward differences on an rfft2 grid of ``shape`` (float32).

    Closed form ``(2 - 2 cos wx) + (2 - 2 cos wy)``.
    """
    cy, cx = _frequency_cosines(shape)
    return (2.0 - 2.0 * cy) + (2.0 - 2.0 * cx)


def fo_derivative_spectrum(shape: tuple[int, int]) -> np.ndarray:
    """``A1 = sum_d |F_d|^2`` of the five Fortunato-Oliveira filters on an rfft2 grid (float32).

    f_x = [-1/2, 0, 1/2] -> sin^2 w; f_xx = [-1, 2, -1]/sqrt 2 -> (2 - 2 cos w)^2 / 2;
    f_xy = sqrt 2 [[-1, 1], [1, -1]] -> 2 (2 - 2 cos wx)(2 - 2 cos wy).
    """
    cy, cx = _frequency_cosines(shape)
    ux, uy = 2.0 - 2.0 * cx, 2.0 - 2.0 * cy
    sx, sy = 1.0 - cx * cx, 1.0 - cy * cy  # sin^2
    row = (sx + 0.5 * ux * ux).astype(np.float32)
    col = (sy + 0.5 * uy * uy).astype(np.float32)
    out = (2.0 * uy) * ux
    out += col
    out += row
    return out.astype(np.float32, copy=False)


def kernel_otf(kernel: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """rfft2 of ``kernel`` zero-padded to ``shape`` with its centre moved to the origin (complex64)."""
    kh, kw = kernel.shape
    if kh > shape[0] or kw > shape[1]:
        raise ParameterError(f"blur kernel {kh}x{kw} is larger than the padded image {shape[0]}x{shape[1]}")
    buf = np.zeros(shape, dtype=np.float32)
    buf[:kh, :kw] = kernel
    buf = np.roll(buf, (-(kh // 2), -(kw // 2)), axis=(0, 1))
    return sfft.rfft2(buf, workers=-1).astype(np.complex64, copy=False)


def _cosine_ramp(n_pad: int, towards_image: bool) -> np.ndarray:
    """Raised-cosine weights over ``n_pad`` samples: ~1 next to the image, 0 at the far end."""
    d = np.arange(1, n_pad + 1, dtype=np.float32)  # distance from the image edge
    w = 0.5 * (1.0 + np.cos(np.pi * d / (n_pad + 1)))
    return w[::-1].copy() if towards_image else w


def pad_and_taper(channel: np.ndarray, shape: tuple[int, int], fill: float) -> tuple[np.ndarray, tuple[int, int]]:
    """Replicate-pad a 2-D float32 channel to ``shape`` and fade the padding towards ``fill``.

    The padding is split between both sides of each axis; a raised cosine blends the
    replicated border values into ``fill`` so the padded image is smooth and periodic.

    Returns
    -------
    padded : ndarray of float32, ``shape``
    offset : (int, int)
        Row and column of the image's first pixel inside ``padded``.
    """
    h, w = channel.shape
    top = (shape[0] - h) // 2
    left = (shape[1] - w) // 2
    bottom, right = shape[0] - h - top, shape[1] - w - left
    out = np.pad(channel, ((top, bottom), (left, right)), mode="edge")
    # Rows first (full width), then columns (full height): corners get both weights.
    for sl, n_pad, towards in ((slice(0, top), top, True), (slice(top + h, None), bottom, False)):
        if n_pad:
            ramp = _cosine_ramp(n_pad, towards)[:, None]
            block = out[sl]
            block -= fill
            block *= ramp
            block += fill
    for sl, n_pad, towards in ((slice(0, left), left, True), (slice(left + w, None), right, False)):
        if n_pad:
            ramp = _cosine_ramp(n_pad, towards)[None, :]
            block = out[:, sl]
            block -= fill
            block *= ramp
            block += fill
    return out, (top, left)


# --------------------------------------------------------------------------- automatic choice


def _whittle_fit(channel_n: np.ndarray, kernel: np.ndarray) -> tuple[float, float]:
    """Fit the periodogram of a normalised channel to ``c |K|^2 / |D|^2 + s2``; return (c, s2).

    Whittle (Gaussian spectral) likelihood on a Hann-windowed centre crop of at most 1024 px a
    side (at least 4 kernel sizes where the image allows it); the lowest frequencies (the
    window's leakage) and DC are left out.
    """
    from scipy.optimize import minimize

    h, w = channel_n.shape
    side_y = min(h, max(1024, 4 * kernel.shape[0]))
    side_x = min(w, max(1024, 4 * kernel.shape[1]))
    side_y = min(side_y, 1024) if h > 1024 and 4 * kernel.shape[0] <= 1024 else side_y
    side_x = min(side_x, 1024) if w > 1024 and 4 * kernel.shape[1] <= 1024 else side_x
    r0, c0 = (h - side_y) // 2, (w - side_x) // 2
    crop = channel_n[r0:r0 + side_y, c0:c0 + side_x].astype(np.float64)
    crop = crop - crop.mean()
    win = np.hanning(side_y)[:, None] * np.hanning(side_x)[None, :]
    shape = (side_y, side_x)
    periodogram = np.abs(np.fft.rfft2(crop * win)) ** 2 / float(np.sum(win * win))
    if kernel.shape[0] <= side_y and kernel.shape[1] <= side_x:
        k2 = np.abs(kernel_otf(kernel, shape).astype(np.complex128)) ** 2
    else:  # kernel wider than the image: evaluate its OTF on a coarser grid by cropping
        kc = kernel[max(0, (kernel.shape[0] - side_y) // 2 + 1):, max(0, (kernel.shape[1] - side_x) // 2 + 1):]
        kc = kc[: min(kc.shape[0], side_y - (1 - side_y % 2)), : min(kc.shape[1], side_x - (1 - side_x % 2))]
        k2 = np.abs(kernel_otf((kc / kc.sum()).astype(np.float32), shape).astype(np.complex128)) ** 2
    d2 = gradient_spectrum(shape).astype(np.float64)
    fy = np.abs(np.fft.fftfreq(side_y))[:, None]
    fx = np.abs(np.fft.rfftfreq(side_x))[None, :]
    radius = np.sqrt(fy * fy + fx * fx)
    use = radius > 4.0 / min(side_y, side_x)
    p = periodogram[use]
    shape_term = (k2 / np.maximum(d2, 1e-12))[use]

    def nll(log_params: np.ndarray) -> float:
        c, s2 = np.exp(log_params)
        model = c * shape_term + s2
        return float(np.mean(np.log(model) + p / model))

    s2_0 = max(estimate_noise_sigma(channel_n) ** 2, 1e-12)
    c_0 = max(float(np.mean(np.diff(crop, axis=1) ** 2)), 1e-12)
    res = minimize(nll, np.log([c_0, s2_0]), method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-9, "maxiter": 400})
    c, s2 = np.exp(res.x)
    return float(c), float(s2)


def _luminance(arr: np.ndarray) -> np.ndarray:
    return arr if arr.ndim == 2 else arr.astype(np.float32).mean(axis=2)


def estimate_regularisation(image: np.ndarray, kernel: np.ndarray, method: str = "adaptive") -> float:
    """Choose the regularisation knob from the data alone (no ground truth, no tuning per image).

    A Whittle maximum-likelihood fit of the observed power spectrum (normalised image) to
    ``c |K|^2 / |D|^2 + sigma^2`` estimates the gradient variance ``c`` of the sharp image;
    the knob (the gradient prior precision, see the module docstring) is ``kappa_m / c`` with a
    fixed constant per method.

    Parameters
    ----------
    image : ndarray (H, W) or (H, W, 3)
        Blurred linear image, any real dtype (colour: the channel mean is used).
    kernel : ndarray
        Blur kernel (odd sides, non-negative).
    method : str
        ``"adaptive"``, ``"wiener"`` or ``"rls"``.

    Returns
    -------
    float
        The value of ``reg`` to pass to :func:`deconvolve`.
    """
    check_method(method)
    arr = _validate_image(image)
    k = validate_kernel(kernel)
    grey = _luminance(arr).astype(np.float32, copy=False)
    offset, scale = robust_range(grey)
    c, _ = _whittle_fit((grey - offset) / scale, k)
    return float(np.clip(_AUTO_KAPPA[method] / max(c, 1e-30), REG_MIN, REG_MAX))


# --------------------------------------------------------------------------- solvers


def _shrink(g: np.ndarray, lam: float, tmp: np.ndarray) -> np.ndarray:
    """In place ``g <- g^5 / (g^4 + lam^4)`` (float32), using ``tmp`` as scratch."""
    np.multiply(g, g, out=tmp)
    np.multiply(tmp, tmp, out=tmp)  # g^4
    denom = tmp + np.float32(lam ** 4)
    np.divide(tmp, denom, out=tmp)
    np.multiply(g, tmp, out=g)
    return g


def _sparse_targets(smooth: np.ndarray, lam1: float, lam2: float) -> np.ndarray:
    """``b1 = sum_d f_d^T * rho(f_d * smooth; lam_d)`` with the five FO filters (float32).

    Correlations with 2-3 tap filters via ``cv2.filter2D``; the adjoint of a correlation is
    the correlation with the flipped kernel (and flipped anchor).
    """
    import cv2

    half = np.float32(0.5)
    r2 = np.float32(1.0 / math.sqrt(2.0))
    s2 = np.float32(math.sqrt(2.0))
    fx = np.array([[-half, 0, half]], np.float32)
    fxx = np.array([[-r2, 2 * r2, -r2]], np.float32)
    fxy = np.array([[-s2, s2], [s2, -s2]], np.float32)
    border = cv2.BORDER_REPLICATE
    tmp = np.empty_like(smooth)
    b1 = np.zeros_like(smooth)
    g = np.empty_like(smooth)
    specs = (
        (fx, -fx, lam1, (-1, -1), (-1, -1)),
        (fx.T.copy(), -fx.T.copy(), lam1, (-1, -1), (-1, -1)),
        (fxx, fxx, lam2, (-1, -1), (-1, -1)),
        (fxx.T.copy(), fxx.T.copy(), lam2, (-1, -1), (-1, -1)),
        (fxy, fxy, lam2, (-1, -1), (0, 0)),
    )
    for filt, adjoint, lam, anchor, adj_anchor in specs:
        cv2.filter2D(smooth, cv2.CV_32F, filt, dst=g, anchor=anchor, borderType=border)
        _shrink(g, lam, tmp)
        cv2.filter2D(g, cv2.CV_32F, adjoint, dst=tmp, anchor=adj_anchor, borderType=border)
        b1 += tmp
    return b1


def _solve_channel(y: np.ndarray, otf: np.ndarray, k2: np.ndarray, reg_spectrum: np.ndarray | None,
                   method: str, lam: float, sigma_n: float, shape: tuple[int, int],
                   ) -> Generator[int, None, np.ndarray]:
    """Deconvolve one padded, tapered, normalised, zero-mean channel; yields after each step."""
    Y = sfft.rfft2(y, workers=-1)
    Y = Y.astype(np.complex64, copy=False)
    np.multiply(Y, np.conj(otf), out=Y)  # Y <- conj(K) Y
    yield 1
    if method == "wiener":
        X = Y / (k2 + np.float32(lam))
        yield 1
        return sfft.irfft2(X, s=shape, workers=-1)
    if method == "rls":
        denom = reg_spectrum * np.float32(lam)
        denom += k2
        X = Y / denom
        yield 1
        return sfft.irfft2(X, s=shape, workers=-1)
    # adaptive: w4 = lam, w1 = lam / 50
    import cv2

    w4 = np.float32(lam)
    w1 = np.float32(lam / _FO_W4_OVER_W1)
    denom = reg_spectrum * w1
    denom += k2
    x = sfft.irfft2(Y / denom, s=shape, workers=-1)
    yield 1
    np.multiply(reg_spectrum, w4, out=denom)
    denom += k2
    sigma_r = float(_FO_SIGMA_R_PER_NOISE * sigma_n)
    for _ in range(_FO_PASSES):
        # Edge-aware smoothing of the current estimate guides the sparse derivative targets.
        smooth = cv2.ximgproc.dtFilter(x, x, _FO_SIGMA_SPATIAL_PX, sigma_r,
                                       mode=cv2.ximgproc.DTF_RF, numIters=1)
        del x
        b1 = _sparse_targets(smooth, _FO_LAMBDA1_PER_NOISE * sigma_n, _FO_LAMBDA2_PER_NOISE * sigma_n)
        del smooth
        yield 1
        B1 = sfft.rfft2(b1, workers=-1).astype(np.complex64, copy=False)
        del b1
        B1 *= w4
        B1 += Y
        B1 /= denom
        x = sfft.irfft2(B1, s=shape, workers=-1)
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
    channels = [arr] if arr.ndim == 2 else [arr[..., i] for i in range(arr.shape[-1])]
    total = 1 + len(channels) * _STEPS_PER_CHANNEL[method]
    done = 0

    h, w = arr.shape[:2]
    shape = _padded_shape((h, w), k.shape)
    grey = _luminance(arr).astype(np.float32, copy=False)
    offset, scale = robust_range(grey)
    if reg == "auto":
        reg = estimate_regularisation(arr, k, method)
    sigma_n = max(estimate_noise_sigma(grey) / scale, 1e-4)
    lam = float(reg) * sigma_n ** 2
    otf = kernel_otf(k, shape)
    k2 = (otf.real * otf.real + otf.imag * otf.imag).astype(np.float32)
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
        y = ch.astype(np.float32, copy=True)
        y -= np.float32(offset)
        y *= np.float32(1.0 / scale)
        mean = float(y.mean(dtype=np.float64))
        y -= np.float32(mean)
        padded, (r0, c0) = pad_and_taper(y, shape, 0.0)
        del y
        solver = _solve_channel(padded, otf, k2, reg_spectrum, method, lam, sigma_n, shape)
        while True:
            try:
                next(solver)
            except StopIteration as stop:
                x = stop.value
                break
            done += 1
            yield done, total
        del padded
        x = x[r0:r0 + h, c0:c0 + w]
        x += np.float32(mean)
        x *= np.float32(scale)
        x += np.float32(offset)
        if arr.ndim == 2:
            out[...] = x
        else:
            out[..., i] = x
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
        or ``"auto"`` for :func:`estimate_regularisation`.
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
