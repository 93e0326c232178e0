"""Noise model of a diagnosis: signal-dependent variance and a noise power spectrum.

Camera noise is rarely white: demosaicing, scintillator light spread and binning smooth it, so
neighbouring pixels are correlated and a per-pixel weight alone overstates how many independent
samples a recording holds (smooth model terms then look far more significant than they are).

Model: ``n(q) = sqrt(v(mu(q))) c(q)`` with ``v(mu) = K (mu - b) + s_r^2`` and ``c`` a
stationary unit-variance field of short correlation range with normalised power spectrum
``P(f)``. The fit minimises ``|W u|^2`` with ``u = (y - mu) / sqrt(v)`` and ``W`` the
prewhitening filter ``1 / sqrt(P)`` (so the whitened residual of the true model is white with
unit variance and ``χ²/dof ≈ 1``).

Estimation uses the variogram ``γ(d) = ½ E[(u(q + d) - u(q))²] = C(0) - C(d)``:

* ``C(0)`` (the variance, the "sill") is ``γ`` at a lag beyond the correlation range;
  ``C(d) = C(0) - γ(d)`` at short lags. Differences over a few pixels cancel smooth model
  mismatch, so the estimate is not inflated by the very effects the diagnosis looks for.
* From a residual, only *flat* pixels are used (the expected image varies by less than a
  fraction of the noise over the largest lag) so edge mismatch stays out as well.
* From repeated frames, the even/odd half difference is pure noise: every pixel is used.

``P(f) = Σ_d ρ(d) cos(2π f·d)`` (``ρ = C / C(0)``) is floored at a small fraction of
its mean; where it is floored the whitened noise has less than unit power. The variance of
the whitened noise (the true model's χ² per sample) is measured on the data
(:meth:`NoiseModel.calibrate`) and used as the number of effective samples, so the reported
χ²/dof of the true model is 1.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..robust import MAD_TO_SIGMA, robust_sigma

SHORT_LAG_PX = 5      # correlation assumed to vanish beyond this lag (coarse pixels)
SILL_LAG_PX = 7       # lag used for the sill (variance)
SPECTRUM_FLOOR = 0.3   # P(f) floor (fraction of its mean): caps the gain at high frequencies
#: Mirror padding (px) of the prewhitening: a periodic transform joins the noise of opposite
#: borders, where the field is then uncorrelated across the seam and the whitening (which
#: amplifies the frequencies correlated noise lacks) inflates it (whitened variance 0.65
#: within 6 px of the border against 0.38 inside, on a lag-1 0.78 null at 128²)
WHITEN_PAD_PX = 8


@dataclass
class NoiseModel:
    """Variance law and correlation of the noise on the fitted grid.

    Attributes
    ----------
    poisson_gain : float
        ``K`` of ``v = K (mu - b) + s_r^2`` (fitted-grid DN).
    read_variance : float
        ``s_r^2`` (fitted-grid DN²).
    correlation : dict
        ``{(dy, dx): rho}`` for the short lags of one half-plane (rho(0, 0) = 1).
    source : str
        ``"repeats"`` or ``"residual"``.
    """

    poisson_gain: float
    read_variance: float
    correlation: dict = field(default_factory=dict)
    source: str = "residual"
    n_samples: int = 0
    _inv_sqrt_spectrum: np.ndarray | None = field(default=None, repr=False)
    _shape: tuple[int, int] | None = field(default=None, repr=False)
    _padded_shape: tuple[int, int] | None = field(default=None, repr=False)
    effective_fraction: float = 1.0

    @property
    def lag1_correlation(self) -> float:
        """Mean of the row and column lag-1 correlations."""
        return 0.5 * (self.correlation.get((0, 1), 0.0) + self.correlation.get((1, 0), 0.0))

    @property
    def is_white(self) -> bool:
        return self._inv_sqrt_spectrum is None

    @property
    def variance_smoothing_px(self) -> float:
        """Noise smoothed after it was generated (demosaicing, light spread) has, at each pixel,
        the variance of its neighbourhood: ``Σ k(d)² v(q - d)``. For a Gaussian smoothing kernel
        ``k`` whose correlation has lag-1 value ``ρ₁``, ``k²`` is a Gaussian of sigma
        ``sqrt(-1 / (2 ln ρ₁)) / 2``; zero for white noise."""
        if self.is_white:
            return 0.0
        rho1 = float(np.clip(self.lag1_correlation, 0.01, 0.95))
        return float(np.sqrt(-1.0 / (2.0 * np.log(rho1))) / 2.0)

    def variance(self, expected_dn: np.ndarray, offset_dn: float) -> np.ndarray:
        v = self.poisson_gain * np.clip(expected_dn - offset_dn, 0.0, None) + self.read_variance
        sigma = self.variance_smoothing_px
        if sigma > 0.05 and np.ndim(v) == 2:
            from scipy import ndimage

            v = ndimage.gaussian_filter(v, sigma, mode="reflect")
        return v

    def prepare(self, shape: tuple[int, int]) -> None:
        """Build the prewhitening filter for images of ``shape`` (identity for white noise)."""
        self._shape = tuple(shape)
        self._inv_sqrt_spectrum = None
        self.effective_fraction = 1.0
        off = {d: r for d, r in self.correlation.items() if d != (0, 0)}
        if not off:
            return
        # Noise in the estimate of each rho is ~1/sqrt(n); below that the noise is white.
        limit = max(0.02, 5.0 / np.sqrt(max(self.n_samples, 1)))
        if max(abs(r) for r in off.values()) < limit:
            return
        from scipy import fft as sfft

        # the filter acts on the mirror-padded field (see WHITEN_PAD_PX)
        h, w = self._padded_shape = tuple(sfft.next_fast_len(n + 2 * WHITEN_PAD_PX, real=True) for n in shape)
        fy = np.fft.fftfreq(h)[:, None]
        fx = np.fft.rfftfreq(w)[None, :]
        spectrum = np.ones((h, w // 2 + 1))
        for (dy, dx), rho in off.items():
            # untapered: a taper would bias the spectrum; where the truncated sum dips below
            # zero (estimation noise) the floor below takes over
            spectrum += 2.0 * rho * np.cos(2.0 * np.pi * (fy * dy + fx * dx))
        floor = SPECTRUM_FLOOR * float(spectrum.mean())
        clipped = np.maximum(spectrum, floor)
        # E|W c|² per pixel = mean over frequencies of P / P_clipped (< 1 only where floored)
        self.effective_fraction = float(np.mean(spectrum.clip(0, None) / clipped))
        self._inv_sqrt_spectrum = 1.0 / np.sqrt(clipped)

    def calibrate(self, normalised: np.ndarray, use: np.ndarray, level: np.ndarray | None = None,
                  tolerance: np.ndarray | None = None) -> None:
        """Measure the variance of the whitened noise (sill over ``use``): the expected χ² per
        sample of the true model. Below 1 where the spectrum is floored (those frequencies hold
        little noise power and are not amplified); measured rather than predicted, because the
        prediction from an estimated spectrum is off by up to 10 %. The filter is not rescaled:
        at low frequencies, where smooth terms live, the whitened noise has unit power."""
        if self._inv_sqrt_spectrum is None:
            return
        gam = [g for g in variogram(self.whiten(normalised), use, _sill_lags(), level, tolerance).values()
               if np.isfinite(g)]
        if gam:
            self.effective_fraction = float(np.mean(gam))

    def whiten(self, u: np.ndarray) -> np.ndarray:
        """Prewhitened field ``W u`` (``u`` already divided by ``sqrt(v)``, zero where masked)."""
        if self._inv_sqrt_spectrum is None:
            return u
        from scipy import fft as sfft

        p = WHITEN_PAD_PX
        h, w = u.shape
        nh, nw = self._padded_shape
        padded = np.pad(u, ((p, nh - h - p), (p, nw - w - p)), mode="symmetric")
        return sfft.irfft2(sfft.rfft2(padded) * self._inv_sqrt_spectrum, s=padded.shape)[p:p + h, p:p + w]

    def to_json(self, binning: int = 1) -> dict:
        return {"source": self.source,
                "poisson_gain_dn": self.poisson_gain * binning**2,
                "read_noise_dn": float(np.sqrt(max(self.read_variance, 0.0)) * binning),
                "lag1_correlation": round(self.lag1_correlation, 4),
                "white": self.is_white,
                "effective_fraction": round(self.effective_fraction, 4)}


def _lag_slices(shape: tuple[int, int], dy: int, dx: int):
    """Slices (a, b) with b = a shifted by (dy, dx) (dy >= 0)."""
    h, w = shape
    ra, rb = slice(0, h - dy), slice(dy, h)
    if dx >= 0:
        ca, cb = slice(0, w - dx), slice(dx, w)
    else:
        ca, cb = slice(-dx, w), slice(0, w + dx)
    return (ra, ca), (rb, cb)


#: Below this many values a plain partition is as fast as the bracketed selection.
_SELECT_MIN_SIZE = 20000
#: Values sampled to bracket an order statistic (:func:`_order_statistics`).
_SELECT_SAMPLE = 4096


def _order_statistics(values: np.ndarray, ranks: list[int]) -> list:
    """The values at sorted positions ``ranks`` (ascending) of finite ``values``, exactly as
    ``np.partition`` gives them, but faster on large arrays: a strided sample brackets the
    ranks, and only the values inside the bracket are partitioned (when the bracket misses,
    the whole array is)."""
    n = values.size
    if n >= _SELECT_MIN_SIZE:
        sample = np.sort(values[::n // _SELECT_SAMPLE])
        m = sample.size
        margin = int(3.0 * np.sqrt(m))  # ~6 standard errors of a sample quantile's rank
        lo_i, hi_i = ranks[0] * m // n - margin, ranks[-1] * m // n + margin
        if lo_i >= 0 and hi_i < m:
            lo, hi = sample[lo_i], sample[hi_i]
            below = int(np.count_nonzero(values < lo))
            inside = values[(values >= lo) & (values <= hi)]
            if below <= ranks[0] and ranks[-1] < below + inside.size:
                part = np.partition(inside, [r - below for r in ranks])
                return [part[r - below] for r in ranks]
    part = np.partition(values, ranks)
    return [part[r] for r in ranks]


def _median(values: np.ndarray):
    """``np.median`` of finite 1-D ``values`` (the same number, to the bit)."""
    n = values.size
    ranks = [n // 2 - 1, n // 2] if n % 2 == 0 else [n // 2]
    # np.median takes the mean of the middle one or two values
    return np.mean(np.array(_order_statistics(values, ranks), dtype=values.dtype))


def _robust_half_ms(diff: np.ndarray) -> float:
    """½ mean square of differences after clipping far outliers (pulses, stray edges)."""
    if diff.size < 50:
        return float("nan")
    # robust_sigma(diff), with the exact medians selected faster (the bulk of the noise estimate)
    sigma = float(MAD_TO_SIGMA * _median(np.abs(diff - _median(diff))))
    kept = diff[np.abs(diff) < 6.0 * max(sigma, 1e-300)]
    # a 6-sigma clip of a Gaussian keeps 1 - 2e-9 of its variance: no correction needed
    return 0.5 * float(np.mean(kept**2))


def lag_differences(field_: np.ndarray, lags, level: np.ndarray | None = None,
                    level_tolerance: np.ndarray | None = None) -> dict:
    """Per lag ``(dy, dx)``: slices ``(a, b)``, the differences ``field[b] - field[a]`` and, if
    ``level`` is given, the pairs whose levels differ by less than ``level_tolerance`` (else
    None). Independent of the pixel selection: :func:`variogram` over many selections of one
    field (bins of level) computes them once."""
    out = {}
    for dy, dx in lags:
        a, b = _lag_slices(field_.shape, dy, dx)
        same_level = None if level is None else np.abs(level[b] - level[a]) < level_tolerance[a]
        out[(dy, dx)] = (a, b, field_[b] - field_[a], same_level)
    return out


def variogram(field_: np.ndarray, mask: np.ndarray, lags, level: np.ndarray | None = None,
              level_tolerance: np.ndarray | None = None, partner: np.ndarray | None = None,
              differences: dict | None = None) -> dict:
    """``γ(d)`` for each lag ``(dy, dx)`` over pixel pairs inside ``mask`` (the second pixel
    inside ``partner`` instead, if given; and, if ``level`` is given, whose levels differ by
    less than ``level_tolerance``). ``differences``: :func:`lag_differences` of the same field,
    level and tolerance, if already computed."""
    out = {}
    for lag in lags:
        a, b, diff, same_level = (differences[lag] if differences is not None
                                  else lag_differences(field_, [lag], level, level_tolerance)[lag])
        both = mask[a] & (mask[b] if partner is None else partner[b])
        if same_level is not None:
            both = both & same_level
        out[lag] = _robust_half_ms(diff[both])
    return out


def _half_plane_lags(radius: int):
    return [(dy, dx) for dy in range(0, radius + 1) for dx in range(-radius, radius + 1)
            if (dy > 0 or dx > 0)]


def _sill_lags():
    """Lags beyond the correlation range in eight directions (more pairs: a tighter sill)."""
    a, b = SILL_LAG_PX, SILL_LAG_PX + 2
    return [(0, a), (a, 0), (a, a), (a, -a), (0, b), (b, 0), (4, a), (a, -4)]


def flat_pixels(expected_dn: np.ndarray, variance_dn2: np.ndarray, mask: np.ndarray,
                tolerance_sigma: float = 0.3, size: int = 7) -> np.ndarray:
    """Pixels where the expected image varies by less than ``tolerance_sigma`` noise sigmas
    within ``size // 2`` px (edges, where model mismatch concentrates, stay out); pairs of
    pixels are further required to have nearly equal levels (:func:`variogram`)."""
    from scipy import ndimage

    spread = ndimage.maximum_filter(expected_dn, size) - ndimage.minimum_filter(expected_dn, size)
    flat = mask & (spread < tolerance_sigma * np.sqrt(variance_dn2))
    if flat.sum() < 2000:  # little flat area: loosen rather than fail
        flat = mask & (spread < np.quantile(spread[mask], 0.3) + 1e-12)
    return flat


def _variance_law(residual: np.ndarray, level: np.ndarray, use: np.ndarray, offset_dn: float,
                  tolerance: np.ndarray | None = None, n_bins: int = 16, lags=None,
                  correlation: float = 0.0) -> tuple[float, float]:
    """``K, s_r^2`` of ``v = K (level - b) + s_r^2`` from ``γ / (1 - ρ)`` per bin of ``level``:
    the sill (``lags`` beyond the correlation range, ``ρ = 0``) or short lags with their
    correlation ``ρ`` (many more flat pairs: a tighter estimate)."""
    lags = lags or _sill_lags()

    signal = level - offset_dn
    values = signal[use]
    if values.size < 200:
        raise InputError(None, "too few flat pixels to estimate the noise model")
    # quantile edges and equal-width edges: a small dark region (an opaque block) gets a bin
    edges = np.unique(np.concatenate([np.quantile(values, np.linspace(0, 1, n_bins + 1)),
                                      np.linspace(values.min(), values.max(), n_bins + 1)]))
    # merge edges closer than 1/64 of the range: a large uniform region (open field) must be
    # one bin, not many scattered subsets of it
    min_width = max(float(np.ptp(values)) / 64.0, 1e-9)
    kept = [edges[0]]
    for e in edges[1:]:
        if e - kept[-1] >= min_width:
            kept.append(e)
    kept[-1] = max(kept[-1], float(values.max()))
    edges = np.array(kept if len(kept) > 1 else [values.min(), values.max()], dtype=float)
    edges[-1] += 1e-9
    which = np.full(signal.shape, -1)
    which[use] = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, len(edges) - 2)
    xs, vs, ws = [], [], []
    differences = lag_differences(residual, lags, None if tolerance is None else level, tolerance)
    for b in range(len(edges) - 1):
        sel = which == b
        if sel.sum() < 60:
            continue
        # first pixel in the bin, second anywhere flat at the same level: a bin of a large
        # uniform region is a scattered subset of it, and pairs inside it alone are few
        gam = [g for g in variogram(residual, sel, lags, partner=use, differences=differences).values()
               if np.isfinite(g)]
        if not gam:
            continue
        xs.append(float(signal[sel].mean()))
        vs.append(float(np.mean(gam)) / (1.0 - correlation))
        ws.append(float(sel.sum()))
    xs, vs, ws = np.array(xs), np.array(vs), np.array(ws)
    if len(xs) >= 2 and np.ptp(xs) > 0:
        design = np.stack([xs, np.ones_like(xs)], 1)
        wt = np.sqrt(ws) / vs  # a variance estimate's error is ∝ v / sqrt(n)
        (k, s2), *_ = np.linalg.lstsq(design * wt[:, None], vs * wt, rcond=None)
        k, s2 = float(k), float(s2)
    else:
        k, s2 = 0.0, float(np.mean(vs))
    if k < 0:
        k, s2 = 0.0, float(np.average(vs, weights=ws))
    if s2 <= 0:
        s2 = max(1e-6 * float(np.mean(vs)), float(np.min(vs)) * 0.01)
    return k, s2


def _correlation(normalised: np.ndarray, use: np.ndarray, level: np.ndarray | None = None,
                 tolerance: np.ndarray | None = None) -> tuple[dict, int]:
    gam = variogram(normalised, use, _half_plane_lags(SHORT_LAG_PX) + _sill_lags(), level, tolerance)
    sill_values = [gam[d] for d in _sill_lags() if np.isfinite(gam[d])]
    sill = float(np.mean(sill_values))
    rho = {(0, 0): 1.0}
    for d in _half_plane_lags(SHORT_LAG_PX):
        if np.isfinite(gam[d]):
            rho[d] = float((sill - gam[d]) / sill)
    return rho, int(use.sum())


def estimate_from_residual(residual_dn: np.ndarray, expected_dn: np.ndarray, offset_dn: float,
                           mask: np.ndarray, previous: NoiseModel | None = None) -> NoiseModel:
    """Noise model from the residual of the current fit (flat pixels, variogram)."""
    if previous is None:
        # rough global variance from pixel differences (robust; refined on the next call)
        d = np.diff(residual_dn, axis=1)[mask[:, 1:] & mask[:, :-1]]
        sigma2 = robust_sigma(d) ** 2 / 2.0
        rough = np.full(residual_dn.shape, max(sigma2, 1e-12))
    else:
        rough = previous.variance(expected_dn, offset_dn)
    use = flat_pixels(expected_dn, rough, mask)
    tolerance = 0.3 * np.sqrt(rough)
    k, s2 = _variance_law(residual_dn, expected_dn, use, offset_dn, tolerance)
    model = NoiseModel(k, s2, source="residual")
    normalised = np.where(mask, residual_dn / np.sqrt(model.variance(expected_dn, offset_dn)), 0.0)
    model.correlation, model.n_samples = _correlation(normalised, use, expected_dn, tolerance)
    # Refine the variance law from lag-1 pairs over pixels flat within 1 px (several times more
    # pairs than at the sill lag), with the correlation just estimated.
    rho1 = float(np.clip(model.lag1_correlation, -0.5, 0.95))
    use_short = flat_pixels(expected_dn, model.variance(expected_dn, offset_dn), mask, size=3)
    model.poisson_gain, model.read_variance = _variance_law(
        residual_dn, expected_dn, use_short, offset_dn, 0.3 * np.sqrt(model.variance(expected_dn, offset_dn)),
        lags=[(0, 1), (1, 0)], correlation=rho1)
    normalised = np.where(mask, residual_dn / np.sqrt(model.variance(expected_dn, offset_dn)), 0.0)
    model.prepare(residual_dn.shape)
    model.calibrate(normalised, use, expected_dn, tolerance)
    return model


def estimate_from_noise_sample(noise_dn: np.ndarray, level_dn: np.ndarray,
                               variance_law: tuple[float, float] | None = None) -> NoiseModel:
    """Noise model from a pure noise field with the recording's noise (e.g. the halved
    even/odd difference of repeated frames), ``level_dn`` the mean image (absolute DN).

    ``variance_law`` ``(K, c)`` with ``v = K level + c`` if already known; else from the sill.
    """
    mask = np.isfinite(noise_dn)
    if variance_law is None:
        k, s2 = _variance_law(noise_dn, level_dn, mask, 0.0)
    else:
        k, s2 = variance_law
    model = NoiseModel(float(k), float(s2), source="repeats")
    normalised = noise_dn / np.sqrt(np.maximum(model.variance(level_dn, 0.0), 1e-12))
    model.correlation, model.n_samples = _correlation(normalised, mask)
    model.prepare(noise_dn.shape)
    model.calibrate(normalised, mask)
    return model
