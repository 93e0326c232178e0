"""Synthetic edge radiographs blurred by a PSF model (tests, benchmarks, the demo and the sample data).

Built independently of the edge fit's Fourier-domain forward model, so a fit to these images
checks the fit rather than repeating it.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ParameterError
from ..psf.model import PSFModel, magnification_factor


def _projected_lsf(t: np.ndarray, width_scale: float, shape_power: float) -> np.ndarray:
    """Spatial-domain line spread of a unit-sum isotropic ``exp(-(r / width_scale)^p)``."""
    from scipy.special import k1

    # Narrower than the grid step: the sampled profile no longer sums to 1 (a core of 0.01 px
    # scale would weigh 1.2x, 0.001 px 10x, against the tail), so it is a delta instead.
    if width_scale < t[1] - t[0]:
        out = np.zeros_like(t)
        out[np.argmin(np.abs(t))] = 1.0 / (t[1] - t[0])
        return out
    u = np.abs(t) / width_scale
    if shape_power == 1.0:
        # integral over the line of exp(-r) is 2 |t| K1(|t|); the 2-D integral is 2 pi.
        with np.errstate(invalid="ignore"):
            val = np.where(u > 0, u * k1(np.where(u > 0, u, 1.0)), 1.0)
        return val / (np.pi * width_scale)
    if shape_power == 2.0:
        return np.exp(-u ** 2) / (math.sqrt(math.pi) * width_scale)
    raise ParameterError(f"shape_power must be 1 or 2, got {shape_power}")


def synthesize_edge_image(model: PSFModel, source_to_object_mm: float, source_to_detector_mm: float,
                          shape: tuple[int, int], normal_angle_deg: float, *, offset_px: float = 0.0,
                          low: float = 0.0, high: float = 1.0, supersample: int = 8,
                          step_px: float = 1.0 / 32.0) -> np.ndarray:
    """Noise-free, pixel-area-integrated radiograph of an ideal straight edge blurred by ``model``.

    Built independently of the fit's Fourier-domain forward model: the line spread function is
    the spatial-domain projection of each PSF component (``|t| K1`` for ``p = 1``), the
    components are convolved numerically on a fine grid, integrated to the ESF, and every pixel
    is the mean of ``supersample**2`` point samples of the ESF.

    Parameters
    ----------
    model : PSFModel
    source_to_object_mm, source_to_detector_mm : float
        Geometry (mm).
    shape : (rows, cols)
    normal_angle_deg : float
        Angle of the edge normal (pointing to the bright side) from the column axis, degrees;
        0 gives a vertical edge (bright on the right), 90 a horizontal edge (bright below).
    offset_px : float
        Signed distance of the edge line from the image centre, pixels.
    low, high : float
        Transmission on the dark and bright sides.
    supersample : int
        Point samples per pixel and axis.
    step_px : float
        Fine-grid spacing of the LSF convolution, pixels.

    Returns
    -------
    ndarray of float64, ``shape``
    """
    from scipy.signal import fftconvolve

    phi = math.radians(normal_angle_deg)
    c, s = math.cos(phi), math.sin(phi)
    m1 = magnification_factor(source_to_object_mm, source_to_detector_mm)
    p = model.shape_power
    kappa = 2.0 * math.log(2.0) ** (1.0 / p)
    pitch = model.pixel_pitch_mm
    h, w = shape
    half_diag = 0.5 * math.hypot(h, w) + abs(offset_px) + 2
    # The elliptical spot exp(-((x/ax)^2 + (y/ay)^2)^(p/2)) projects onto the normal as an
    # isotropic profile of width sqrt((ax c)^2 + (ay s)^2).
    ax = model.source_fwhm_x_mm * m1 / pitch / kappa
    ay = model.source_fwhm_y_mm * m1 / pitch / kappa
    src_scale = math.hypot(ax * c, ay * s)
    core_scale = model.detector_fwhm_core_mm / pitch / kappa
    if model.core_from_mtf:   # reach of the MTF-defined core: 30 scales (heavy stretched-exponential tails)
        core_scale = 30.0 * model.detector_core_mtf_scale_mm / pitch / 40.0
    tail_scale = model.detector_fwhm_tail_mm / pitch / kappa
    reach = half_diag + 40.0 * max(src_scale, core_scale, 0.1) + (60.0 * tail_scale if model.detector_weight_core < 1 else 0)
    n_half = int(math.ceil(reach / step_px))
    t = np.arange(-n_half, n_half + 1) * step_px   # odd length, centred: 'same' convolution keeps t = 0
    if model.core_from_mtf:
        # The 1-D line spread of an isotropic PSF is the inverse transform of its radial MTF.
        from ..psf.mtf_shapes import generalised_mtf

        freq = np.fft.rfftfreq(t.size, d=step_px)
        core_mtf = generalised_mtf(freq * model.detector_core_mtf_scale_mm / pitch, model.detector_core_mtf_power,
                                   model.detector_core_mtf_linnik)
        lsf_core = np.fft.fftshift(np.fft.irfft(core_mtf, t.size)) / step_px
    else:
        lsf_core = _projected_lsf(t, core_scale, p)
    lsf_det = model.detector_weight_core * lsf_core
    if model.detector_weight_core < 1:
        lsf_det = lsf_det + (1 - model.detector_weight_core) * _projected_lsf(t, tail_scale, p)
    lsf = fftconvolve(lsf_det, _projected_lsf(t, src_scale, p), mode="same") * step_px if src_scale > 0 else lsf_det
    esf = np.cumsum(lsf) * step_px
    esf -= 0.5 * lsf * step_px   # trapezoid rule
    esf /= esf[-1]
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    rows = np.arange(h) - 0.5 * (h - 1)
    cols = np.arange(w) - 0.5 * (w - 1)
    out = np.zeros(shape)
    for dy in sub:
        for dx in sub:
            d = (cols[None, :] + dx) * c + (rows[:, None] + dy) * s - offset_px
            out += np.interp(d, t, esf)
    out /= supersample ** 2
    return low + (high - low) * out
