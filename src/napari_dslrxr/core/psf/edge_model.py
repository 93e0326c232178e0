"""The forward model of the edge fit: the transfer functions of the exponential-power PSF
components and the edge spread function on a fine 1-D grid (see :mod:`.edge_fit` for the method).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import fft as sfft

from ..errors import ParameterError
from .mtf_shapes import generalised_mtf

#: Default spacing (pixels) of the fine grid on which the ESF is evaluated.
DEFAULT_ESF_STEP_PX = 1.0 / 16.0
_WEIGHT_BOUNDS = (0.5, 1.0)
#: Grid spacing (pixels) of the smooth tail part of the ESF, and the smallest tail FWHM allowed.
_TAIL_STEP_PX = 0.5
_TAIL_FWHM_MIN_PX = 4.0
_LOG_FWHM_MIN = math.log(1e-3)
#: Bounds of the generalised core's MTF power ``q`` and Linnik parameter ``u`` in the fit.
_CORE_POWER_BOUNDS = (0.6, 2.0)
_CORE_LINNIK_BOUNDS = (0.0, 3.0)



def _radial_otf(nu: np.ndarray, shape_power: float) -> tuple[np.ndarray, np.ndarray]:
    """Normalised 2-D Fourier transform of ``exp(-r^p)`` at radial frequency ``nu`` and ``nu * dG/dnu``."""
    if shape_power == 1.0:
        q = 1.0 + (2.0 * np.pi * nu) ** 2
        g = q ** -1.5
        return g, -3.0 * (2.0 * np.pi * nu) ** 2 * g / q
    if shape_power == 2.0:
        g = np.exp(-(np.pi * nu) ** 2)
        return g, -2.0 * (np.pi * nu) ** 2 * g
    raise ParameterError(f"shape_power must be 1 (exponential) or 2 (Gaussian) for edge fitting, got {shape_power}")


def _sinc_and_derivative(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``sinc(x) = sin(pi x)/(pi x)`` and its derivative in ``x``."""
    s = np.sinc(x)
    with np.errstate(divide="ignore", invalid="ignore"):
        ds = np.where(np.abs(x) > 1e-8, (np.cos(np.pi * x) - s) / np.where(x == 0, 1.0, x), 0.0)
    return s, ds


def _solve_levels(esf: np.ndarray, values: np.ndarray, weight: np.ndarray) -> tuple[float, float]:
    """Weighted least-squares dark and bright levels ``(a, b)`` of ``values ~ a (1 - esf) + b esf``.

    Variable projection: the levels enter linearly, so they are solved in closed form for every
    blur and edge position; the gradient of the reduced cost is the partial gradient at these
    levels (their own partial derivatives vanish), so it stays exact.
    """
    one_minus = 1.0 - esf
    w_one_minus, w_esf = weight * one_minus, weight * esf
    s00, s01, s11 = _dot(w_one_minus, one_minus), _dot(w_one_minus, esf), _dot(w_esf, esf)
    r0, r1 = _dot(w_one_minus, values), _dot(w_esf, values)
    det = s00 * s11 - s01 * s01
    if not det > 1e-12 * max(s00 * s11, 1e-300):
        level = float(values.mean())
        return level, level
    return (s11 * r0 - s01 * r1) / det, (s00 * r1 - s01 * r0) / det


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """Vector dot product without BLAS (multi-threaded BLAS stalls on tiny products on a busy machine)."""
    return float(np.einsum("i,i->", a, b))


class _EsfGrid:
    """Periodic 1-D grid on which one part of the ESF (and its parameter derivatives) is evaluated.

    Parameters
    ----------
    period_px : float
        Minimum period; must exceed twice the data half-range plus the reach of the blur part.
    step_px : float
        Grid spacing (pixels).
    """

    def __init__(self, period_px: float, step_px: float):
        n = sfft.next_fast_len(int(math.ceil(period_px / step_px)), real=True)
        n += n % 2
        self.n = n
        self.step = step_px
        self.period = n * step_px
        self.freq = np.arange(n // 2 + 1) / self.period          # cycles per pixel
        self.inv_2pi_i_f = np.zeros(n // 2 + 1, dtype=complex)
        self.inv_2pi_i_f[1:-1] = 1.0 / (2j * np.pi * self.freq[1:-1])   # Nyquist bin dropped
        t = (np.arange(n) - n // 2) * step_px                  # fft-shifted positions
        self.ramp = 0.5 + t / self.period

    def esf(self, otf: np.ndarray) -> np.ndarray:
        """ESF on the shifted grid (index ``n//2`` is ``t = 0``)."""
        s = sfft.irfft(otf * self.inv_2pi_i_f, self.n) / self.step
        return self.ramp + np.roll(s, self.n // 2)

    def derivative(self, dotf: np.ndarray) -> np.ndarray:
        """Derivative of the ESF grid for an OTF derivative ``dotf`` (shifted grid)."""
        return np.roll(sfft.irfft(dotf * self.inv_2pi_i_f, self.n) / self.step, self.n // 2)

    def backproject(self, i0: np.ndarray, frac: np.ndarray, r: np.ndarray) -> np.ndarray:
        """rfft of the residual spread onto the grid (adjoint of linear interpolation), unshifted."""
        grid = (np.bincount(i0, r * (1.0 - frac), minlength=self.n)
                + np.bincount(i0 + 1, r * frac, minlength=self.n))
        return sfft.rfft(np.roll(grid, -(self.n // 2)))

    def inner(self, dotf: np.ndarray, backprojected_rfft: np.ndarray) -> float:
        """``<derivative(dotf), R>`` computed in the Fourier domain (Parseval for irfft)."""
        y = dotf * self.inv_2pi_i_f
        return float(2.0 / self.n * np.real(y * np.conj(backprojected_rfft)).sum() / self.step)

    def locate(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pos = d / self.step + self.n // 2
        i0 = np.floor(pos).astype(np.int64)
        if i0.min() < 0 or i0.max() + 1 >= self.n:
            raise ParameterError("edge fit: pixel distance outside the ESF grid (internal error)")
        return i0, pos - i0


def _part_otf(grid: _EsfGrid, fwhm: dict, component_fwhm_px: float, m1: float, phi: float,
              shape_power: float, need_derivatives: bool, core_shape: tuple[float, float] | None = None):
    """OTF along the edge normal of ``source * pixel * component`` and its derivatives.

    Derivatives are taken w.r.t. the log FWHMs ``sx``, ``sy``, the component's log FWHM
    (``"component"``) and the normal angle ``phi``. With ``core_shape = (q, u)`` the component
    is the generalised core (:func:`~.mtf_shapes.generalised_mtf`) of scale ``component_fwhm_px``,
    with derivatives w.r.t. its log scale (``"component"``), ``"power"`` and ``"linnik"``.
    """
    f = grid.freq
    kappa = 2.0 * math.log(2.0) ** (1.0 / shape_power)
    c, s = math.cos(phi), math.sin(phi)
    fx, fy = fwhm["sx"], fwhm["sy"]
    q = (fx * c) ** 2 + (fy * s) ** 2
    src, src_d = _radial_otf(f * (m1 * math.sqrt(q)) / kappa, shape_power)
    shape_derivs = {}
    if core_shape is None:
        comp, comp_d = _radial_otf(f * component_fwhm_px / kappa, shape_power)
    else:
        comp, d = generalised_mtf(f * component_fwhm_px, core_shape[0], core_shape[1], derivatives=True)
        comp_d = d["scale"]
        shape_derivs = {"power": d["power"], "linnik": d["linnik"]}
    sinc_c, dsinc_c = _sinc_and_derivative(f * c)
    sinc_s, dsinc_s = _sinc_and_derivative(f * s)
    pix = sinc_c * sinc_s
    src_pix = src * pix
    otf = src_pix * comp
    if not need_derivatives:
        return otf, None
    if q > 0:
        dlog_w = {"sx": (fx * c) ** 2 / q, "sy": (fy * s) ** 2 / q, "phi": c * s * (fy ** 2 - fx ** 2) / q}
    else:
        dlog_w = {"sx": 0.0, "sy": 0.0, "phi": 0.0}
    src_d_pix_comp = src_d * pix * comp
    dpix_dphi = dsinc_c * (-f * s) * sinc_s + sinc_c * dsinc_s * (f * c)
    derivs = {
        "sx": src_d_pix_comp * dlog_w["sx"],
        "sy": src_d_pix_comp * dlog_w["sy"],
        "component": src_pix * comp_d,
        "phi": src_d_pix_comp * dlog_w["phi"] + src * comp * dpix_dphi,
    }
    for name, value in shape_derivs.items():
        derivs[name] = src_pix * value
    return otf, derivs
