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

from collections.abc import Callable, Generator

import numpy as np

from .deblur_params import METHODS, REG_MAX, REG_MIN, DeconvolutionParams, check_method, check_reg
from .deblur_solvers import (_FO_PASSES, _channel_noise, _channels, _luminance, _solve_channel, _validate_image,
                             estimate_noise_sigma, robust_range, validate_kernel)
from .fourier import fo_derivative_spectrum, gradient_spectrum, kernel_otf, pad_and_taper, padded_shape

#: The stage's public face: its parameters, checks and noise estimate live beside it.
__all__ = ["METHODS", "REG_MIN", "REG_MAX", "DeconvolutionParams", "check_method", "check_reg", "validate_kernel",
           "estimate_noise_sigma", "deconvolve_steps", "deconvolve"]


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
