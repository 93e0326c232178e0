"""The automatic choice of the deconvolution's regularisation, and how far to trust it.

:func:`model_regularisation` fits the observed power spectrum (Whittle likelihood) to a
texture-plus-noise model and returns the MSE-optimal weight under it;
:func:`choose_regularisation` keeps that value only while the solver's noise gain in flat
regions stays below :data:`AUTO_MAX_NOISE_GAIN` (else raises it), and says when the estimate
rests on weak ground (step-like or flat images, noise-free data, a bound, the cap);
:func:`estimate_regularisation` is the capped value (what ``reg="auto"`` uses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from .deblur_params import REG_MAX, REG_MIN, check_method
from .deblur_solvers import (_channel_noise, _channels, _luminance, _noise_floor, _solve_channel, _validate_image,
                             estimate_noise_sigma, noise_sigma_tiles, robust_range, validate_kernel)
from .fourier import fo_derivative_spectrum, gradient_spectrum, kernel_otf

#: Per-method multipliers of the model-optimal weight in the automatic choice
#: (rls, adaptive: of s2 / c; wiener: of the model-MSE-optimal constant NSR).
_AUTO_KAPPA = {"wiener": 0.4, "rls": 1.3, "adaptive": 2.0}

# --------------------------------------------------------------------------- automatic choice


def _whittle_fit(channel_n: np.ndarray, kernel: np.ndarray) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Fit the periodogram of a normalised channel to ``c |K|^2 / |D|^2 + s2``.

    Whittle (Gaussian spectral) likelihood on a Hann-windowed centre crop of at most 1024 px a
    side (larger when the kernel needs it); DC and the lowest frequencies (the window's
    leakage) are left out.

    Returns
    -------
    c : float
        Variance of the sharp image's forward-difference gradient (normalised units).
    s2 : float
        Average white-noise variance (normalised units).
    k2, d2 : ndarray
        ``|K|^2`` and ``|D|^2`` on the crop's rfft2 grid (for model-based choices).
    """
    from scipy.optimize import minimize

    h, w = channel_n.shape
    side_y = min(h, max(1024, 4 * kernel.shape[0]))
    side_x = min(w, max(1024, 4 * kernel.shape[1]))
    r0, c0 = (h - side_y) // 2, (w - side_x) // 2
    crop = channel_n[r0:r0 + side_y, c0:c0 + side_x].astype(np.float64)
    crop = crop - crop.mean()
    win = np.hanning(side_y)[:, None] * np.hanning(side_x)[None, :]
    shape = (side_y, side_x)
    periodogram = np.abs(np.fft.rfft2(crop * win)) ** 2 / float(np.sum(win * win))
    kc = kernel
    if kc.shape[0] > side_y or kc.shape[1] > side_x:  # kernel wider than the image: central part
        ry = min(kc.shape[0] // 2, (side_y - 1) // 2)
        rx = min(kc.shape[1] // 2, (side_x - 1) // 2)
        cy, cx = kc.shape[0] // 2, kc.shape[1] // 2
        kc = kc[cy - ry:cy + ry + 1, cx - rx:cx + rx + 1]
        kc = (kc / kc.sum()).astype(np.float32)
    otf = kernel_otf(kc, shape).astype(np.complex128)
    k2 = otf.real ** 2 + otf.imag ** 2
    d2 = gradient_spectrum(shape).astype(np.float64)
    fy = np.abs(np.fft.fftfreq(side_y))[:, None]
    fx = np.abs(np.fft.rfftfreq(side_x))[None, :]
    use = np.sqrt(fy * fy + fx * fx) > 4.0 / min(side_y, side_x)
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
    return float(c), float(s2), k2, d2


def _wiener_mse_optimal_nsr(c: float, s2: float, k2: np.ndarray, d2: np.ndarray) -> float:
    """Constant noise-to-signal ratio minimising the model MSE for signal spectrum ``c / |D|^2``.

    ``MSE(lam) = sum_w (lam^2 S_x + |K|^2 s2) / (|K|^2 + lam)^2``, ``S_x = c / |D|^2`` (DC,
    which the solver keeps, excluded).
    """
    from scipy.optimize import minimize_scalar

    valid = d2 > 1e-9
    sx = c / d2[valid]
    kk = k2[valid]

    def mse(log_lam: float) -> float:
        lam = math.exp(log_lam)
        return float(np.sum((lam * lam * sx + kk * s2) / (kk + lam) ** 2))

    res = minimize_scalar(mse, bounds=(math.log(1e-12), math.log(1e3)), method="bounded")
    return float(math.exp(res.x))


def estimate_regularisation(image: np.ndarray, kernel: np.ndarray, method: str = "adaptive") -> float:
    """The automatic ``reg``: the data model's choice, capped for flat-region noise.

    ``choose_regularisation(image, kernel, method).reg``; see :func:`choose_regularisation`
    (which also says how reliable the choice is) and :func:`model_regularisation`.
    """
    return choose_regularisation(image, kernel, method).reg


def model_regularisation(image: np.ndarray, kernel: np.ndarray, method: str = "adaptive") -> float:
    """Choose the regularisation knob from the data alone (no ground truth, no tuning per image).

    A Whittle maximum-likelihood fit of the observed power spectrum of the normalised image to
    ``c |K|^2 / |D|^2 + s2`` estimates the gradient variance ``c`` of the sharp image and the
    average noise variance ``s2`` (signal-dependent noise included). Under that model the
    MSE-optimal weights are:

    * ``"rls"``: ``lam = s2 / c`` (the Wiener-optimal Tikhonov weight), times ``kappa = 1.3``;
    * ``"adaptive"``: ``w4 = kappa s2 / c`` with ``kappa = 2`` (the sparse prior's derivative
      targets carry the edges, so it can afford a stronger pull);
    * ``"wiener"``: the constant noise-to-signal ratio minimising the model's predicted MSE,
      times ``kappa = 0.4`` (a constant ratio cannot follow the 1/f^2 spectrum; on radiographs
      the model optimum over-smoothed by about 2.5x).

    The kappas are fixed constants calibrated once on synthetic phantoms and one radiograph
    (never per image). The returned knob is ``lam / sigma_n^2`` (see the module docstring).

    Parameters
    ----------
    image : ndarray (H, W) or (H, W, 3)
        Blurred linear image, any real dtype (colour: fitted per channel, geometric mean).
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
    _, scale = robust_range(_luminance(arr).astype(np.float32, copy=False))
    log_lams = []
    for ch in _channels(arr):  # colour: per channel (the noise is per channel), geometric mean
        normalised = ch.astype(np.float32) * np.float32(1.0 / scale)
        c, s2, k2, d2 = _whittle_fit(normalised, k)
        c = max(c, 1e-30)
        if method == "wiener":
            lam = _AUTO_KAPPA[method] * _wiener_mse_optimal_nsr(c, s2, k2, d2)
        else:
            lam = _AUTO_KAPPA[method] * s2 / c
        log_lams.append(math.log(max(lam, 1e-30)))
    sigma_n = _channel_noise(arr, scale)
    return float(np.clip(math.exp(float(np.mean(log_lams))) / sigma_n ** 2, REG_MIN, REG_MAX))


#: Flat-region noise gain (output / input noise) the automatic choice aims at: 10 % below the
#: promised 2x, for the structure and the signal-dependent noise a white-noise model misses.
AUTO_MAX_NOISE_GAIN = 1.8

#: Share of the (noise-corrected) gradient energy in the strongest 5 % of pixels above which an
#: image counts as step-like: a few edges, no texture (the spectral model assumes texture).
#: Measured: a blurred step 0.87, the edge samples 0.85-0.94; CR chest and leg crops 0.52-0.55,
#: the SABER target's star 0.34.
_STEP_LIKE_ENERGY_SHARE = 0.75


@dataclass
class RegularisationChoice:
    """The automatic regularisation and how far it can be trusted.

    Attributes
    ----------
    reg : float
        The knob to pass to :func:`deconvolve`.
    model_reg : float
        The data model's estimate (:func:`model_regularisation`) before the noise cap.
    noise_gain : float
        Flat-region noise gain at ``reg`` (output / input noise, measured on white noise).
    model_noise_gain : float
        The same at ``model_reg``.
    capped : bool
        ``reg`` was raised above ``model_reg`` to keep the noise gain at ``max_noise_gain``.
    reliable : bool
        False when the estimate rests on weak ground (step-like or flat image, noise-free
        data, an estimate at its bound, or the cap was needed).
    warnings : list of str
        One line per reason, for the user.
    """

    reg: float
    model_reg: float
    noise_gain: float
    model_noise_gain: float
    capped: bool
    reliable: bool
    warnings: list

    def as_dict(self) -> dict:
        return {"reg": self.reg, "model_reg": self.model_reg, "noise_gain": round(self.noise_gain, 3),
                "model_noise_gain": round(self.model_noise_gain, 3), "capped": self.capped,
                "reliable": self.reliable, "warnings": list(self.warnings)}


def flat_noise_gain(kernel: np.ndarray, method: str, reg: float, sigma_n: float, size_px: int = 128, *,
                    local_sigma: float | None = None) -> float:
    """Noise gain of the solver in a flat region: output / input std on white noise.

    A flat region is a constant plus noise. The solver sees the image normalised to unit
    range with relative noise ``sigma_n``; its weight is ``reg sigma_n^2`` and the sparse
    prior's thresholds scale with ``sigma_n``. So a seeded white-noise channel through the
    same solve (periodic: white noise needs no padding) gives the gain there, the sparse
    prior's shrinkage included. ``local_sigma`` (default ``sigma_n``) is the noise of the
    flat region itself: with Poisson noise a bright region is noisier than the average, so
    relatively less of it falls under the prior's thresholds.
    """
    k = validate_kernel(kernel)
    side = sfft.next_fast_len(max(int(size_px), 4 * max(k.shape)), real=True)
    shape = (side, side)
    noise = np.random.default_rng(0).standard_normal(shape).astype(np.float32) * np.float32(local_sigma or sigma_n)
    otf_conj = kernel_otf(k, shape)
    k2 = np.square(otf_conj.real)
    k2 += np.square(otf_conj.imag)
    np.conjugate(otf_conj, out=otf_conj)
    reg_spectrum = {"rls": gradient_spectrum, "adaptive": fo_derivative_spectrum}.get(method)
    solver = _solve_channel(noise.copy(), otf_conj, k2, reg_spectrum(shape) if reg_spectrum else None, method,
                            float(reg) * sigma_n ** 2, sigma_n, shape)
    while True:
        try:
            next(solver)
        except StopIteration as stop:
            out = stop.value
            break
    return float(out.std() / noise.std())


def _step_like(grey: np.ndarray, sigma_n_abs: float) -> bool:
    """True when a few strong edges hold most of the gradient energy (noise energy removed)."""
    arr = np.asarray(grey, np.float32)
    if arr.size > 4_000_000:
        arr = arr[::2, ::2]
    gy, gx = np.gradient(arr)
    energy = (gx * gx + gy * gy).ravel()
    energy = np.maximum(energy - np.float32(sigma_n_abs ** 2), 0)  # each difference carries noise
    total = float(energy.sum())
    if total <= 0:
        return False
    top = np.partition(energy, int(0.95 * energy.size))[int(0.95 * energy.size):]
    return float(top.sum()) / total > _STEP_LIKE_ENERGY_SHARE


def choose_regularisation(image: np.ndarray, kernel: np.ndarray, method: str = "adaptive", *,
                          max_noise_gain: float = AUTO_MAX_NOISE_GAIN) -> RegularisationChoice:
    """The automatic ``reg``, capped so flat regions get at most ``max_noise_gain`` x the noise.

    :func:`model_regularisation` fits a spectral model (texture with a 1/f^2 spectrum plus
    white noise). On step-like images (a few edges, no texture) or nearly flat ones the fit
    has little to go on and can choose a weight that amplifies flat-region noise many times
    (and rings at the edges). The fallback is a cap: when :func:`flat_noise_gain` at the
    model's value exceeds ``max_noise_gain``, ``reg`` is raised (bisection on log reg) to the
    smallest value that keeps it. The choice is flagged unreliable, with a reason, when the
    cap was needed, the image is step-like, the noise is at the estimator's floor
    (noise-free data) or the estimate sits at a bound.

    Returns
    -------
    RegularisationChoice
    """
    check_method(method)
    arr = _validate_image(image)
    k = validate_kernel(kernel)
    model_reg = model_regularisation(arr, k, method)
    warnings = []
    grey = _luminance(arr).astype(np.float32, copy=False)
    _, scale = robust_range(grey)
    sigma_n = _channel_noise(arr, scale)
    if sigma_n <= _noise_floor(0.0):
        warnings.append("the image looks noise-free (noise at the estimator's floor)")
    if model_reg >= REG_MAX or model_reg <= REG_MIN:
        warnings.append(f"the estimate sits at its bound ({model_reg:.3g}): the image is nearly flat or pure noise")
    signal_variance = float(np.var(grey[::2, ::2] if grey.size > 4_000_000 else grey)) - (sigma_n * scale) ** 2
    if signal_variance < 4.0 * (sigma_n * scale) ** 2:
        warnings.append("nearly flat image: little signal above the noise, so deblurring does little")
    if _step_like(grey, sigma_n * scale):
        warnings.append("step-like image (a few strong edges, little texture): the spectral model has little to fit")
    # the noisiest flat regions (bright, with Poisson noise) decide: the 90th percentile tile
    local_sigma = max(float(np.percentile(noise_sigma_tiles(grey), 90)) / scale, sigma_n)

    def gain_at(reg_value: float) -> float:
        return flat_noise_gain(k, method, reg_value, sigma_n, local_sigma=local_sigma)

    model_gain = gain_at(model_reg)
    reg, gain, capped = model_reg, model_gain, False
    if model_gain > max_noise_gain:
        capped = True
        low, high = math.log(model_reg), math.log(model_reg)
        gain_high = model_gain
        while gain_high > max_noise_gain and high < math.log(REG_MAX):
            low, high = high, min(high + math.log(10.0), math.log(REG_MAX))
            gain_high = gain_at(math.exp(high))
        for _ in range(8):  # bisection on log reg: about 1 % of a decade
            middle = 0.5 * (low + high)
            gain_middle = gain_at(math.exp(middle))
            if gain_middle > max_noise_gain:
                low = middle
            else:
                high, gain_high = middle, gain_middle
        reg, gain = math.exp(high), gain_high
        warnings.append(f"the model's estimate {model_reg:.3g} would raise flat-region noise {model_gain:.1f}x; "
                        f"raised to {reg:.3g} (noise x{gain:.1f})")
    return RegularisationChoice(reg=float(reg), model_reg=float(model_reg), noise_gain=float(gain),
                                model_noise_gain=float(model_gain), capped=capped, reliable=not warnings,
                                warnings=warnings)


