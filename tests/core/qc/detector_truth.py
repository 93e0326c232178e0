"""Synthetic X-ray detectors with analytic MTF, NNPS and DQE, written independently of the
code under test (only numpy and scipy.special).

Two detectors, both counting Poisson-distributed absorbed photons (fluence eta * q):

* ``ideal``: each absorbed photon adds one count to the pixel it lands in (square aperture of
  side p, fill factor 1). Presampled MTF = |sinc(f p)|; the aliased sum of sinc²(f p - k) over k
  is 1, so the digital NNPS is white, 1 / (eta q), and DQE(f) = eta sinc²(f p).
* ``spread``: each absorbed photon spreads a fixed (not random) Gaussian light distribution of
  standard deviation ``sigma_mm`` after detection; a pixel collects ``gain`` DN per photon
  times the fraction of the light on its aperture; independent Gaussian read noise
  ``read_noise_dn`` is added. With a(x) = light kernel (*) pixel box and A its Fourier
  transform, A(f) = p² sinc(f_x p) sinc(f_y p) exp(-2 pi² sigma² |f|²):
  MTF(f) = |A(f)| / p²,
  NPS(f) = gain² eta q sum_{k,l} |A(f - (k, l)/p)|² + read_noise² p² (1 + 1/n_darks),
  NNPS = NPS / (gain eta q p²)², DQE = MTF² / (q NNPS).
  Photons sit at the centres of sub-cells of p/s: the edge's mean then holds the blur over a
  sub-cell (a factor sinc(f p/s) in the MTF, kept in the truth); the noise of a lattice of
  Poisson sources equals the continuous one up to alias terms at s/p, negligible here.

The edge: transmission 1 on one side of a straight line and ``edge_floor`` on the other; the
fraction of a square cell on the bright side is the exact CDF of the sum of two uniform
variables (the cell projected on the edge normal).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, special

RQA5_SNR2_PER_UGY = 29653.0  # photons / mm² / µGy, IEC 62220-1-1:2015 Table 2


@dataclass
class Detector:
    pitch_mm: float
    eta: float
    air_kerma_ugy: float
    sigma_mm: float = 0.0      # 0 = ideal photon-counting pixel
    gain_dn: float = 1.0
    read_noise_dn: float = 0.0
    offset_dn: float = 0.0
    edge_floor: float = 0.05

    @property
    def q(self) -> float:
        return self.air_kerma_ugy * RQA5_SNR2_PER_UGY

    @property
    def mean_dn(self) -> float:
        return self.gain_dn * self.eta * self.q * self.pitch_mm ** 2


def _cell_fraction(u_mm: np.ndarray, cell_mm: float, theta: float) -> np.ndarray:
    """Fraction of a square cell (side cell_mm, centre at signed distance u from the line whose
    normal makes angle theta with the x axis) on the positive side."""
    a = 0.5 * cell_mm * abs(math.cos(theta))
    b = 0.5 * cell_mm * abs(math.sin(theta))

    def h(t):
        return np.maximum(t, 0.0) ** 2 / 2.0

    return (h(u_mm + a + b) - h(u_mm + a - b) - h(u_mm - a + b) + h(u_mm - a - b)) / (4.0 * a * b)


def _gauss_pixel_weight(offset_mm: np.ndarray, pitch_mm: float, sigma_mm: float) -> np.ndarray:
    """1-D fraction of a Gaussian light spot (centre at offset) falling on a pixel of side p."""
    s = sigma_mm * math.sqrt(2.0)
    return 0.5 * (special.erf((offset_mm + pitch_mm / 2) / s) - special.erf((offset_mm - pitch_mm / 2) / s))


def _spread_to_pixels(counts: np.ndarray, sub: int, pitch_mm: float, sigma_mm: float, margin: int) -> np.ndarray:
    """Pixel values sum_m counts_m * a(x_pixel - x_m) for photons at sub-cell centres."""
    delta = pitch_mm / sub
    reach = int(math.ceil(5 * sigma_mm / pitch_mm)) + 1

    def along(arr, axis):
        out = None
        for r in range(sub):
            phase = np.take(arr, np.arange(r, arr.shape[axis], sub), axis=axis)
            # pixel i centre minus the photon of phase r in pixel i' : ((i - i') s + (s-1)/2 - r) delta
            k = np.arange(-reach, reach + 1)
            weights = _gauss_pixel_weight((k * sub + (sub - 1) / 2.0 - r) * delta, pitch_mm, sigma_mm)
            res = ndimage.correlate1d(phase, weights[::-1], axis=axis, mode="constant")
            out = res if out is None else out + res
        return out

    pix = along(along(counts, 0), 1)
    return pix[margin:-margin, margin:-margin]


def flat_frame(det: Detector, shape, rng, *, sub: int = 2) -> np.ndarray:
    """One open-beam frame (DN, float64)."""
    if det.sigma_mm == 0:
        img = det.gain_dn * rng.poisson(det.eta * det.q * det.pitch_mm ** 2, size=shape).astype(float)
    else:
        margin = int(math.ceil(5 * det.sigma_mm / det.pitch_mm)) + 2
        lam = det.eta * det.q * (det.pitch_mm / sub) ** 2
        counts = rng.poisson(lam, size=((shape[0] + 2 * margin) * sub, (shape[1] + 2 * margin) * sub)).astype(float)
        img = det.gain_dn * _spread_to_pixels(counts, sub, det.pitch_mm, det.sigma_mm, margin)
    return img + det.offset_dn + det.read_noise_dn * rng.standard_normal(shape)


def dark_frame(det: Detector, shape, rng) -> np.ndarray:
    return det.offset_dn + det.read_noise_dn * rng.standard_normal(shape)


def edge_frame(det: Detector, shape, rng, *, angle_deg: float = 2.0, vertical_edge: bool = True,
               sub: int = 4) -> np.ndarray:
    """A straight edge through the frame centre, ``angle_deg`` from the column (or row) axis."""
    theta = math.radians(angle_deg)
    if det.sigma_mm == 0:
        sub, margin = 1, 0
    else:
        margin = int(math.ceil(5 * det.sigma_mm / det.pitch_mm)) + 2
    cell = det.pitch_mm / sub
    n_r, n_c = (shape[0] + 2 * margin) * sub, (shape[1] + 2 * margin) * sub
    # cell centres in mm, origin at the frame centre
    y = ((np.arange(n_r) + 0.5) / sub - margin - shape[0] / 2) * det.pitch_mm
    x = ((np.arange(n_c) + 0.5) / sub - margin - shape[1] / 2) * det.pitch_mm
    yy, xx = np.meshgrid(y, x, indexing="ij")
    if vertical_edge:
        u = xx * math.cos(theta) - yy * math.sin(theta)
    else:
        u = yy * math.cos(theta) - xx * math.sin(theta)
    frac = _cell_fraction(u, cell, theta)
    transmission = det.edge_floor + (1 - det.edge_floor) * frac
    lam = det.eta * det.q * cell ** 2 * transmission
    counts = rng.poisson(lam).astype(float)
    if det.sigma_mm == 0:
        img = det.gain_dn * counts
    else:
        img = det.gain_dn * _spread_to_pixels(counts, sub, det.pitch_mm, det.sigma_mm, margin)
    return img + det.offset_dn + det.read_noise_dn * rng.standard_normal(shape)


def _alias_sum(f: np.ndarray, det: Detector, n_alias: int = 6) -> np.ndarray:
    """sum_k sinc²(f p - k) exp(-4 pi² sigma² (f - k/p)²): one axis of sum |A|² / p⁴."""
    if det.sigma_mm == 0:
        return np.ones_like(f, dtype=float)  # sum_k sinc²(x - k) = 1 exactly
    total = np.zeros_like(f, dtype=float)
    for k in range(-n_alias, n_alias + 1):
        fk = f - k / det.pitch_mm
        total += np.sinc(fk * det.pitch_mm) ** 2 * np.exp(-4 * math.pi ** 2 * det.sigma_mm ** 2 * fk ** 2)
    return total


def truth_mtf(det: Detector, f: np.ndarray, angle_deg: float = 2.0, sub: int = 4) -> np.ndarray:
    """Presampled MTF along the edge normal (aperture projected at the edge angle)."""
    th = math.radians(angle_deg)
    fx, fy = f * math.cos(th), f * math.sin(th)
    m = np.abs(np.sinc(fx * det.pitch_mm) * np.sinc(fy * det.pitch_mm))
    if det.sigma_mm > 0:
        m = m * np.exp(-2 * math.pi ** 2 * det.sigma_mm ** 2 * f ** 2)
        m = m * np.abs(np.sinc(fx * det.pitch_mm / sub) * np.sinc(fy * det.pitch_mm / sub))
    return m


def truth_nnps_cut(det: Detector, f: np.ndarray, roi_px: int, half_width: int, n_darks: int) -> np.ndarray:
    """NNPS along one axis, averaged over the rows +-1 ... +-half_width beside the axis."""
    beside = np.arange(1, half_width + 1) / (roi_px * det.pitch_mm)
    across = float(np.mean(_alias_sum(beside, det)))
    photon = _alias_sum(np.asarray(f, float), det) * across / (det.eta * det.q)
    read = det.read_noise_dn ** 2 * (1 + (1.0 / n_darks if n_darks else 0.0)) * det.pitch_mm ** 2 / det.mean_dn ** 2
    return photon + read


def truth_dqe(det: Detector, f, roi_px: int, half_width: int, n_darks: int, angle_deg: float = 2.0):
    return truth_mtf(det, f, angle_deg) ** 2 / (det.q * truth_nnps_cut(det, f, roi_px, half_width, n_darks))


def plain_nnps_cut(flats, darks, pitch_mm: float, roi_px: int, half_width: int) -> tuple[np.ndarray, np.ndarray]:
    """A plain reference NNPS: non-overlapping ROIs tiling the frame, each minus its own plane
    fit, 2-D periodogram, horizontal cut beside the axis. Returns (f at native samples, cut)."""
    dark = np.mean(darks, axis=0) if len(darks) else 0.0
    cuts = []
    yy, xx = np.mgrid[0:roi_px, 0:roi_px]
    basis = np.stack([np.ones(roi_px * roi_px), xx.ravel(), yy.ravel()], axis=1)
    for flat in flats:
        sig = flat - dark
        mean = sig.mean()
        for r in range(0, sig.shape[0] - roi_px + 1, roi_px):
            for c in range(0, sig.shape[1] - roi_px + 1, roi_px):
                roi = sig[r:r + roi_px, c:c + roi_px]
                coef = np.linalg.lstsq(basis, roi.ravel(), rcond=None)[0]
                det = roi - (basis @ coef).reshape(roi.shape)
                nps = np.abs(np.fft.fft2(det)) ** 2 * pitch_mm ** 2 / roi_px ** 2 / mean ** 2
                rows = list(range(1, half_width + 1)) + list(range(roi_px - half_width, roi_px))
                cuts.append(nps[rows, : roi_px // 2 + 1].mean(axis=0))
    return np.arange(roi_px // 2 + 1) / (roi_px * pitch_mm), np.mean(cuts, axis=0)


def shaped_edge_frame(mtf, pitch_mm: float, shape, rng, *, angle_deg: float = 2.0, sub: int = 4,
                      counts: float = 20000.0, floor: float = 0.05) -> np.ndarray:
    """A near-vertical edge blurred by an isotropic detector MTF ``mtf(f)`` (cycles/mm), then
    pixel-integrated, with Poisson noise of ``counts`` on the bright side.

    The exact cell fractions on a grid of p/sub are filtered by ``mtf`` (FFT, frame padded by
    edge values) and summed over each pixel's sub x sub cells: the box-average of the cells and
    their sum make exactly the pixel aperture, so the presampled MTF is mtf(f) sinc(f p) (up to
    the sub-grid's aliasing, negligible when mtf(sub / (2p)) is small).
    """
    theta = math.radians(angle_deg)
    n_r, n_c = shape[0] * sub, shape[1] * sub
    y = ((np.arange(n_r) + 0.5) / sub - shape[0] / 2) * pitch_mm
    x = ((np.arange(n_c) + 0.5) / sub - shape[1] / 2) * pitch_mm
    yy, xx = np.meshgrid(y, x, indexing="ij")
    t = floor + (1 - floor) * _cell_fraction(xx * math.cos(theta) - yy * math.sin(theta), pitch_mm / sub, theta)
    padded = np.pad(t, ((n_r // 2, n_r // 2), (n_c // 2, n_c // 2)), mode="edge")
    fy = np.fft.fftfreq(padded.shape[0], d=pitch_mm / sub)
    fx = np.fft.rfftfreq(padded.shape[1], d=pitch_mm / sub)
    blurred = np.fft.irfft2(np.fft.rfft2(padded) * mtf(np.hypot(fy[:, None], fx[None, :])), s=padded.shape)
    cells = blurred[n_r // 2:n_r // 2 + n_r, n_c // 2:n_c // 2 + n_c]
    return rng.poisson(counts * cells.reshape(shape[0], sub, shape[1], sub).mean(axis=(1, 3))).astype(float)
