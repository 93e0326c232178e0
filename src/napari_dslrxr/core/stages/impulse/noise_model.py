"""Noise model of the impulse stage: the Gaussian + uniform-pulse mixture of the residual,
fitted by expectation-maximisation, and the count variance derived from it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...robust import robust_sigma
from .params import _FLOAT, MEDIAN_RESIDUAL_VARIANCE_FACTOR, ImpulseParams

#: Percentage of the EM samples, the darkest, whose residual variance is the floor of the
#: photon-counting variance model (the read-noise term; see ``_dark_end``).
_DARK_END_PERCENT = 1.0


@dataclass
class _NoiseModel:
    """Residual mixture of one channel: s^2 = a*m + b, pulse rate P, pulse density u."""

    a: float
    b: float
    pulse_rate: float
    pulse_density: float
    polarity: int  # +1 bright pulses only, -1 dark only, 0 either sign
    var_floor: float
    min_contrast: float = 0.0
    #: Photon-counting channels: median level of the darkest fit samples (nan if unknown).
    dark_level: float = float("nan")
    #: Count variance over the variance ``a`` and ``b`` describe: 1, except for V of
    #: near-grey colour frames (``detection._match_channel_tail``), whose residual is a
    #: maximum of channels and narrower than one channel's.
    count_variance_scale: float = 1.0

    def variance(self, m: np.ndarray) -> np.ndarray:
        return np.maximum(self.a * m + self.b, self.var_floor)

    def log_odds_constant(self, posterior_threshold: float, rate: float) -> float:
        """2 ln((1-P)/(P u)) + 2 ln(t/(1-t)) - ln(2 pi): the threshold is s^2 (this - ln s^2)."""
        return (2.0 * math.log((1.0 - rate) / (rate * self.pulse_density))
                + 2.0 * math.log(posterior_threshold / (1.0 - posterior_threshold))
                - math.log(2.0 * math.pi))

    def test_limit(self, s2: np.ndarray, posterior_threshold: float, prior: float | None = None) -> np.ndarray:
        """The bound ``s^2 (const - ln s^2)`` that ``d^2`` must exceed at variance ``s2``
        (:meth:`is_pulse`). As a function of ``s2`` it rises up to ``exp(const - 1)`` and
        falls beyond."""
        const = self.log_odds_constant(posterior_threshold, self.pulse_rate if prior is None else prior)
        return s2 * (const - np.log(s2))

    def is_pulse(self, d: np.ndarray, m: np.ndarray, posterior_threshold: float,
                 prior: float | None = None, min_variance: np.ndarray | None = None,
                 min_contrast: float | None = None) -> np.ndarray:
        """Posterior pulse probability > threshold, vectorised (float32 inputs allowed).

        r > t  <=>  d^2/s^2 > 2 ln((1-P)/(P u)) + 2 ln(t/(1-t)) - ln(2 pi s^2),
        with ``P`` the fitted pulse rate unless a ``prior`` is given, and ``s^2`` at least
        ``min_variance`` where that is given. ``min_contrast``: the Weber contrast rule's
        fraction instead of the model's (0: none).
        """
        s2 = self.variance(m)
        if min_variance is not None:
            s2 = np.maximum(s2, min_variance)
        limit = self.test_limit(s2, posterior_threshold, prior)
        pulse = (d * d > limit) & (limit > 0) | (limit <= 0)
        if self.polarity > 0:
            pulse &= d > 0
        elif self.polarity < 0:
            pulse &= d < 0
        else:
            pulse &= d != 0
        contrast = self.min_contrast if min_contrast is None else min_contrast
        if contrast > 0:
            pulse &= np.abs(d) > contrast * np.abs(m)
        return pulse


#: Bounds of the fitted pulse rate.
_MIN_RATE, _MAX_RATE = 1e-7, 0.5


def _responsibilities(model: _NoiseModel, d: np.ndarray, d2: np.ndarray, s2: np.ndarray) -> np.ndarray:
    """Pulse responsibilities r = P u / (P u + (1 - P) N) of residuals ``d`` (squares ``d2``,
    Gaussian variances ``s2``) under ``model``'s rate, density and polarity."""
    log_gauss = -0.5 * d2 / s2 - 0.5 * np.log(2.0 * np.pi * s2)
    pulse_log = math.log(model.pulse_rate * model.pulse_density)
    if model.polarity:
        pulse_log = np.where(d * model.polarity > 0, pulse_log, -np.inf)
    # via the log-odds for stability
    log_odds = pulse_log - (math.log(1.0 - model.pulse_rate) + log_gauss)
    return 0.5 * (1.0 + np.tanh(0.5 * np.clip(log_odds, -60, 60)))


def _fit_mixture(d: np.ndarray, m: np.ndarray, *, photon_counting: bool, polarity: int,
                 value_range: float, iterations: int) -> _NoiseModel:
    """Fit a, b and P by EM on residuals ``d`` and medians ``m`` (1-D float64 subsample)."""
    density = 1.0 / value_range if polarity else 1.0 / (2.0 * value_range)
    var_floor = max((1e-4 * value_range) ** 2, 1e-12)
    mad = robust_sigma(d, center=0.0)
    if photon_counting:
        level = np.maximum(m - float(np.percentile(m, 0.5)), 0.0) + 1.0
        scale = robust_sigma(d / np.sqrt(level), center=0.0)
        a, b = max(scale * scale, 0.0), max(var_floor, 0.0)
        dark_level, dark_variance = _dark_end(d, m)
        var_floor = max(var_floor, dark_variance)
    else:
        a, b = 0.0, max(mad * mad, var_floor)
        dark_level = float("nan")
    model = _NoiseModel(a, b, 0.01, density, polarity, var_floor)
    d2 = d * d
    for _ in range(iterations):
        s2 = model.variance(m)
        resp = _responsibilities(model, d, d2, s2)
        new_rate = float(np.clip(resp.mean(), _MIN_RATE, _MAX_RATE))
        weight = 1.0 - resp
        if photon_counting:
            # Weighted least squares of d^2 on (m, 1) with weights (1 - r)/s^4
            # (Var[d^2] = 2 s^4 under the Gaussian), the Gaussian-variance M-step.
            wls = weight / (s2 * s2)
            sxx = np.sum(wls * m * m); sx = np.sum(wls * m); s1 = np.sum(wls)
            sxy = np.sum(wls * m * d2); sy = np.sum(wls * d2)
            det = sxx * s1 - sx * sx
            a_new = (sxy * s1 - sx * sy) / det if det > 0 else 0.0
            if a_new <= 0:
                a_new, b_new = 0.0, sy / s1
            else:
                b_new = (sxx * sy - sx * sxy) / det
        else:
            a_new, b_new = 0.0, float(np.sum(weight * d2) / max(np.sum(weight), 1e-30))
        change = abs(a_new - model.a) / max(model.a, 1e-30) + abs(b_new - model.b) / max(abs(model.b), var_floor)
        model = _NoiseModel(float(a_new), float(b_new), new_rate, density, polarity, var_floor)
        if change < 1e-4:
            break
    model.dark_level = dark_level
    return model


def _dark_end(d: np.ndarray, m: np.ndarray) -> tuple[float, float]:
    """Level (median ``m``) and robust residual variance of the darkest samples.

    The darkest ``_DARK_END_PERCENT`` of the samples are used.

    The photon-counting variance ``G (m - o) + sigma_e^2`` never falls below the read-noise
    term ``sigma_e^2``, but the straight line ``a m + b`` fitted to it crosses zero near the
    offset ``o``; below the camera's black level plus a few counts (the dark surround of the
    screen) it would promise a noise far below the real one and flag read noise as pulses.
    Measured (1.4826 MAD, so pulses do not inflate it) where the image is darkest, it is the
    floor of the variance model; on an image without dark parts it is the variance at its
    darkest level and changes nothing above it. (nan, 0) when there are too few samples.
    """
    dark = m <= np.percentile(m, _DARK_END_PERCENT)
    if np.count_nonzero(dark) < 50:
        return float("nan"), 0.0
    return float(np.median(m[dark])), robust_sigma(d[dark], center=0.0) ** 2


def _gain(model: _NoiseModel | None, params: ImpulseParams) -> float:
    if model is None or model.a <= 0:
        return float("nan")
    return model.a * model.count_variance_scale / MEDIAN_RESIDUAL_VARIANCE_FACTOR[params.window_px]


def _count_variance(values: np.ndarray, model: "_NoiseModel | None") -> np.ndarray:
    """Noise variance of counts ``values`` (float32, new array) from V's fitted model.

    ``max(a c + b, floor)``: the photon-counting line and its read-noise floor (in units of
    the detection residual; only ratios of these variances are used). Below the darkest
    level V was fitted on (the minimum channel of a saturated colour can lie far below it)
    the line is not extrapolated (its intercept is poorly determined there); the variance
    falls in proportion to the counts instead, Poisson without offset. Without a V model
    (no V pass, or too small an image) plain Poisson, ``Var[c]`` proportional to ``c``.
    """
    out = np.maximum(values, _FLOAT(0.0), dtype=_FLOAT)
    if model is None or model.a <= 0:
        out += _FLOAT(1e-12)
        return out
    below = scaled = None
    if math.isfinite(model.dark_level) and model.dark_level > 0:
        below = out < _FLOAT(model.dark_level)
        if below.any():
            # The whole block scaled and copied where below: a boolean gather and scatter of
            # the dark pixels took 1.5x as long on 24 Mpx frames (same values).
            var_at_dark = max(model.a * model.dark_level + model.b, model.var_floor, 1e-12)
            scaled = np.multiply(out, _FLOAT(var_at_dark / model.dark_level))
            np.maximum(scaled, _FLOAT(1e-12), out=scaled)
    out *= _FLOAT(model.a)
    out += _FLOAT(model.b)
    np.maximum(out, _FLOAT(max(model.var_floor, 1e-12)), out=out)
    if scaled is not None:
        np.copyto(out, scaled, where=below)
    return out


#: The fitted noise is shrunk when it is more than this many times (in variance) what the
#: prediction residual supports (:func:`_shrink_to_prediction`). Measured on frames filled
#: with a mesh (2.2-5.3 px periods): 200-10 000 times; a correct fit on noise is near 1, and
#: noise correlated between neighbours (demosaicing) could make the prediction up to a few
#: times better than the truth, so the margin is wide.
_INFLATION_LIMIT = 10.0
#: The same limit on raw CFA planes, whose noise is independent between pixels (no
#: demosaicing), so that a right fit is near 1 there (measured: 0.97-1.4 on the planes of
#: pulse frames, 1.0-1.9 on radiographs holding a texture patch). Frames filled with a mesh
#: or a line pattern give 2-3000 (dim planes, the mesh aliased: 2-10); at 10, a mesh with
#: its red and blue planes at 9.6 and 4.0 kept the inflated fit and had a third of its
#: pixels flagged.
_RAW_INFLATION_LIMIT = 3.0
#: EM iterations of the pulse rate refitted after a shrink (converges in a few).
_RATE_REFIT_ITERATIONS = 50
#: Half-width (px) of the neighbourhood of the linear predictor (5x5 minus the centre: 24
#: weights; a mesh of two crossing gratings is a sum of at most 9 complex exponentials,
#: each of which the predictor must reproduce).
_PREDICTOR_REACH_PX = 2
#: Pixels the predictor's weights are fitted on and that its residual is read at.
_PREDICTOR_SAMPLES = 32768


@dataclass
class _Predictor:
    """A linear predictor of each pixel from its 5x5 neighbours (centre excluded).

    ``weights``: one per offset of ``offsets`` (row, column arrays), then the intercept;
    ``noise_gain``: ``1 + sum(w^2)``, the variance of the residual on white noise of unit
    variance. Periodic texture (a line pattern, a mesh, a grid: sums of a few complex
    exponentials) is predicted exactly by such a filter, noise and pulses are not.
    """

    weights: np.ndarray
    offsets: tuple[np.ndarray, np.ndarray]
    noise_gain: float

    @classmethod
    def fitted(cls, x: np.ndarray, pixels: np.ndarray) -> tuple["_Predictor", np.ndarray, np.ndarray]:
        """Least-squares weights over ``pixels`` (flat indices; a regular subsample of them).

        Returns (the predictor, the subsample's positions in ``pixels``, its residuals)."""
        from .neighbourhoods import _subsample_indices, _window_offsets

        dr, dc = _window_offsets(2 * _PREDICTOR_REACH_PX + 1)
        off_centre = (dr != 0) | (dc != 0)
        predictor = cls(np.zeros(int(off_centre.sum()) + 1), (dr[off_centre], dc[off_centre]), 1.0)
        at = _subsample_indices(pixels.size, _PREDICTOR_SAMPLES)
        sample = pixels[at]
        design = predictor._design(x, sample)
        centre = x.ravel()[sample].astype(np.float64)
        # Normal equations (25x25; the SVD solver took 0.2-0.5 s on a loaded machine), with a
        # vanishing ridge so that a constant image still has a solution. einsum, not BLAS:
        # a few ms on one core, where waking BLAS threads cost more than the sums.
        gram = np.einsum("ij,ik->jk", design, design)
        gram[np.diag_indices_from(gram)] += 1e-9 * max(float(np.trace(gram)), 1e-30) / gram.shape[0]
        predictor.weights = np.linalg.solve(gram, np.einsum("ij,i->j", design, centre))
        predictor.noise_gain = 1.0 + float(np.sum(predictor.weights[:-1] ** 2))
        return predictor, at, centre - np.einsum("ij,j->i", design, predictor.weights)

    def _design(self, x: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        from .neighbourhoods import _flat_indices

        rows, cols = np.divmod(pixels, x.shape[1])
        around = np.ascontiguousarray(x).ravel()[_flat_indices(rows, cols, *self.offsets, x.shape)]
        return np.column_stack([around.astype(np.float64), np.ones(pixels.size)])

    def residual_at(self, x: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """Pixel value minus its prediction at ``pixels`` (flat indices), float64."""
        return x.ravel()[pixels].astype(np.float64) - np.einsum("ij,j->i", self._design(x, pixels), self.weights)


def _shrink_to_prediction(model: _NoiseModel, x: np.ndarray, pick: np.ndarray, level: np.ndarray,
                          residual_factor: float, weight: np.ndarray | None = None,
                          limit: float = _INFLATION_LIMIT) -> "_Predictor | None":
    """Shrink a noise model fitted on texture to the noise the prediction residual shows.

    The model is fitted on residuals to a median, which fine periodic texture (2-5 px)
    dominates when it fills the frame: there is no flat area to fit on, and the fitted
    noise is then hundreds of times too wide, which makes the pulse test degenerate
    (everything a pulse) and lifts the texture guard's noise floor above the texture. The
    residual of a linear predictor (:class:`_Predictor`, fitted on ``pick``) is free of
    such texture. Where the model's variance (per pixel: ``model.variance /
    residual_factor``) is more than ``limit`` (:data:`_INFLATION_LIMIT`) times what that residual
    supports (robustly, so pulses do not count), ``a``, ``b`` and the floor are scaled
    down to it. ``level``: the detection median of each pixel of ``pick``
    (photon-counting variance); ``weight``: the channel's residual weight
    (constant-variance channels). Returns the predictor when the model was shrunk (the
    frame is texture throughout), else None.
    """
    if pick.size < 256:
        return None
    predictor, at, residual = _Predictor.fitted(x, pick)
    if weight is not None:
        residual = residual * weight.ravel()[pick[at]]
    pixel_variance = model.variance(level[at]) / residual_factor
    scale = robust_sigma(residual / np.sqrt(pixel_variance * predictor.noise_gain), center=0.0) ** 2
    if not (0.0 < scale < 1.0 / limit):
        return None
    model.a *= scale
    model.b *= scale
    model.var_floor *= scale
    # The pulse rate was fitted on the texture too (its peaks beyond the inflated Gaussian:
    # rates of 0.1-0.26 on frames filled with a mesh, which lower the posterior test's
    # threshold to about 2 sigmas); refitted, with the shrunk variance held, on the prediction
    # residual at the median residual's scale (as :func:`detection._unpredicted` tests it).
    d = residual * math.sqrt(residual_factor / predictor.noise_gain)
    d2, s2 = d * d, model.variance(level[at])
    for _ in range(_RATE_REFIT_ITERATIONS):
        rate = float(np.clip(_responsibilities(model, d, d2, s2).mean(), _MIN_RATE, _MAX_RATE))
        converged = abs(rate - model.pulse_rate) <= 1e-3 * model.pulse_rate
        model.pulse_rate = rate
        if converged:
            break
    return predictor
