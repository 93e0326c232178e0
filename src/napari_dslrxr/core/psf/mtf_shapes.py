"""Radial shapes of the blur components: their MTFs and the FWHM <-> scale conversions.

* every spatially defined component has the exponential-power profile ``exp(-(s * r) ** p)``
  with ``s = 2 * ln(2) ** (1 / p) / FWHM`` (:func:`fwhm_to_scale`, :func:`scale_to_fwhm`); its
  normalised 2-D Fourier transform is :func:`exponential_power_mtf` (``p = 1`` or ``2``);
* the generalised detector core is defined by its radial MTF ``(1 + u (f s)^q)^(-1/u)``
  (:func:`generalised_mtf`; see ``docs/algorithms/psf.md``, section 'Model').
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ParameterError

#: Below this ``u * (f s)^q`` the Linnik MTF and its derivative in ``u`` use their series in ``u``.
_LINNIK_SERIES_LIMIT = 1e-4


def generalised_mtf(x: np.ndarray, power: float, linnik: float, *, derivatives: bool = False):
    """Radial MTF ``(1 + u x^q)^(-1/u)`` of the generalised detector core (``x = f * scale``).

    A generalised Linnik characteristic function: positive-definite (a PSF that is a positive
    mixture of stable laws) for ``0 < q <= 2`` and ``u >= 0``. ``u = 0`` is the stretched
    exponential ``exp(-x^q)`` (the limit), ``u = 1, q = 2`` the Lorentzian ``1 / (1 + x^2)``.

    Parameters
    ----------
    x : ndarray
        Frequency times the scale (``f * s``, dimensionless, >= 0).
    power, linnik : float
        ``q`` in ``(0, 2]`` and ``u >= 0``.
    derivatives : bool
        Also return ``dM/dlog(s)``, ``dM/dq`` and ``dM/du``.

    Returns
    -------
    ndarray, or (ndarray, dict) with keys ``"scale"``, ``"power"``, ``"linnik"``.
    """
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        z = np.where(x > 0, x, 0.0) ** power
        uz = linnik * z
        small = uz < _LINNIK_SERIES_LIMIT
        if linnik > 0:
            log_term = np.where(small, z * (1.0 - 0.5 * uz), np.log1p(uz) / linnik)
        else:
            log_term = z
        mtf = np.exp(-log_term)
        if not derivatives:
            return mtf
        dl_dz = 1.0 / (1.0 + uz)
        if linnik > 0:
            exact = (uz / (1.0 + uz) - np.log1p(uz)) / (linnik * linnik)
            dl_du = np.where(small, -0.5 * z * z + (2.0 / 3.0) * linnik * z ** 3, exact)
        else:
            dl_du = -0.5 * z * z
        log_x = np.where(x > 0, np.log(np.where(x > 0, x, 1.0)), 0.0)
        dl_dq = dl_dz * z * log_x
        dl_dscale = dl_dz * power * z
    derivs = {"scale": -mtf * dl_dscale, "power": -mtf * dl_dq, "linnik": -mtf * np.nan_to_num(dl_du)}
    return mtf, derivs


def exponential_power_mtf(nu: np.ndarray, shape_power: float) -> np.ndarray:
    """Normalised 2-D Fourier transform of ``exp(-r^p)`` at radial frequency ``nu`` (p = 1 or 2)."""
    if shape_power == 1.0:
        return (1.0 + (2.0 * np.pi * nu) ** 2) ** -1.5
    if shape_power == 2.0:
        return np.exp(-(np.pi * nu) ** 2)
    raise ParameterError(f"an analytic MTF needs shape_power 1 or 2, got {shape_power}")


def _mtf_cutoff(scale: float, power: float, linnik: float, level: float = 1e-5) -> float:
    """Frequency (inverse units of ``scale``) above which the generalised MTF is below ``level``."""
    z = -math.log(level) if linnik <= 0 else (level ** -linnik - 1.0) / linnik
    return z ** (1.0 / power) / scale


def fwhm_to_scale(fwhm: float, shape_power: float) -> float:
    """Scale ``s`` of ``exp(-(s r)^p)`` with the given full width at half maximum.

    Parameters
    ----------
    fwhm : float
        Full width at half maximum (any length unit, > 0).
    shape_power : float
        Exponential-power ``p``.

    Returns
    -------
    float
        ``s = 2 ln(2)^(1/p) / fwhm`` in inverse units of ``fwhm``.
    """
    return 2.0 * math.log(2.0) ** (1.0 / shape_power) / fwhm


def scale_to_fwhm(scale: float, shape_power: float) -> float:
    """Inverse of :func:`fwhm_to_scale`."""
    return 2.0 * math.log(2.0) ** (1.0 / shape_power) / scale
