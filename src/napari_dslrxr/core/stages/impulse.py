"""Impulse-noise (zinger) removal: the statistical switching median of Frosio and Borghese.

A DSLR photographing an X-ray scintillator records, besides the screen light, direct X-ray
hits on its sensor: bright spots of one pixel on the raw mosaic that demosaicing spreads into
2x2 to 4x4 coloured patches. This module detects them with a statistical test and replaces
only the detected pixels; every other pixel is returned bit-for-bit unchanged.

Model (Frosio & Borghese, IEEE TMI 28(1), 2009; Frosio, Abati & Borghese, IJCARS 2008;
``docs/algorithms/impulse.md``). For a pixel value ``x`` and the median ``m``
of the 8 detection samples around it (centre excluded, so ``d`` is Gaussian) the residual
``d = x - m`` is a mixture

    p(d | m) = (1 - P) N(d; 0, s^2(m)) + P u(d)

The samples are the 8 neighbours (``window_px`` 3) or, by default, the 8 pixels two steps
away (``window_px`` 5, a sparse 5x5 window: a patch of up to 3x3 px holds none of them).

* photon-counting channels (grey images, V, raw CFA planes):
  ``s^2(m) = max(a m + b, floor)`` with ``a = k G`` (``G`` the Poisson gain in counts per
  photon-electron, ``k`` the variance of ``x - median`` relative to that of ``x``), ``b``
  absorbing the offset and read noise (``b = k (sigma_e^2 - G o)``), and ``floor`` the
  residual variance measured where the image is darkest: ``k (G (m - o) + sigma_e^2)`` never
  falls below the read-noise term, while the line crosses zero near the black level;
* ratio channels (H, S): a constant variance ``s^2 = b`` of the residual weighted by the
  inverse of the channel's noise, propagated from the count variance of V's model at the
  3x3 medians of S and V (S: ``sqrt(Var[min] + (1-S)^2 Var[max]) / V``, H:
  ``sqrt(Var[V]) / (V S)``); S's variance is fitted where S is defined (S >= min_saturation);
* pulses: uniform over the channel's value range ``V`` (``u = 1/V`` for bright-only pulses,
  ``1/(2V)`` for pulses of either sign).

``a``, ``b`` and the pulse rate ``P`` are fitted by expectation-maximisation on a regular
subsample of the flatter half of the image itself. A pixel is a pulse where the posterior
probability of the pulse component exceeds one half (and, on photon-counting channels, its
Weber contrast exceeds ``min_contrast``). Patches: pixels next to detected pulses are
re-tested, with a higher prior ``neighbour_prior``, against the median of their non-pulse
neighbours in a 7x7 or larger window, repeatedly, so larger patches and tracks are grown
from their rim inward. Detected pixels are replaced by the median of the non-pulse pixels of
the smallest window (3x3 up to 9x9) that holds enough of them.

Structure guards (edges and corners of the screen are not pulses): a seed's residual
variance is at least (spread / 3)^2, the spread being that of the means of point-symmetric
pixel pairs on the square ring at ``max_patch_px`` from it (outside any patch; a linear
ramp does not spread them, an edge's shoulder or a corner does); a grown pixel's is at least the spread of its
window's background, whose exclusions are made point-symmetric so that the median stays
unbiased on a ramp. Hue pixels are tested only where the whole detection window has a
defined hue.

Speed: a full-image prefilter with OpenCV medians (centre included) picks candidates; the
exact test runs on them only; later passes re-test only the neighbourhood of replaced
pixels. A 6000x4000 RGB frame takes about 2 s of CPU (see benchmarks/bench_impulse.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError, ParameterError

__all__ = [
    "ImpulseParams",
    "ImpulseResult",
    "remove_impulses",
    "remove_impulses_cfa",
    "cfa_mask_to_mosaic",
    "demosaic_cleaned_raw",
    "rgb_to_hsv_counts",
    "hsv_counts_to_rgb",
    "dominant_hue",
]

#: Var[x - m] / Var[x] for independent pixels, ``m`` the median of the 8 detection samples
#: around the centre (centre excluded), measured by simulation on Poisson images (mean 50 to
#: 10 000 counts; 1 + Var[m]/Var[x]). The residual is then Gaussian (kurtosis 3.0), unlike
#: the residual to a median that includes the centre (a spike at 0, too light a variance for
#: its tails). Turns the fitted slope into a gain.
MEDIAN_RESIDUAL_VARIANCE_FACTOR = {3: 1.17, 5: 1.17}

#: Candidates for the exact test are pixels whose residual to the cheap centre-including
#: median, divided by this, passes the test: the centre-excluded residual is usually larger
#: by only half an order-statistic spacing. On a NIQA frame this keeps 99.8 % of the seeds of
#: an exact test of every pixel; the few dropped lie in mixed neighbourhoods (next to other
#: pulses or edges), where the patch growth usually finds them.
_PREFILTER_FRACTION = 0.6

#: Replacement / re-test windows (side in px) and the least number of non-pulse pixels each
#: must hold to be used; the first window that qualifies is used.
_REPLACEMENT_WINDOWS_PX = (3, 5, 7, 9)
_REPLACEMENT_MIN_GOOD = (5, 8, 12, 12)

#: Seed test: the spread of the 8 detection samples may exceed the noise by this factor
#: before it raises the residual variance (8 samples estimate a spread only roughly; a
#: factor 2 is rarely reached on a smooth background, always on edges and screen corners).
_SEED_SPREAD_TOLERANCE = 3.0

#: Texture guard. Around a seed, a pixel of the annulus between Chebyshev distances
#: ``_TEXTURE_INNER_PX`` and ``_TEXTURE_OUTER_PX`` is "busy" when its own residual to the
#: fast detection median is at least ``_BUSY_RELATIVE`` of the seed's. A pulse (at most
#: 5x5 px, so never reaching the annulus from any of its pixels) leaves only the noise's
#: tail busy; a track (1-2 px wide) adds the two places where it crosses the annulus. A line
#: pattern, mesh or grid (periodic structure that continues beyond the window) makes a
#: large part of it busy, with residuals of both signs. A seed whose annulus is busier
#: than ``_TEXTURE_BUSY_FRACTION`` is texture, not a pulse. Relative to the seed, not to
#: the noise model: on a frame filled with texture the fitted noise is inflated by it.
#: Measured on line patterns and meshes (2.2-5.3 px period, 60 % modulation) against
#: pulses of every shape (benchmarks/eval_impulse_independent.py): the 1st percentile of
#: texture seeds is at 0.22, the 99th of pulse seeds at 0.14 (tracks 0.24).
#: Weak pulses (4-6 sigma) and texture overlap in that relative measure; the annulus is
#: then also compared with the noise model: more than ``_TEXTURE_NOISY_FRACTION`` of it
#: beyond ``_BUSY_SIGMAS`` noise sigmas is texture too (noise alone: 0.3 %).
_BUSY_RELATIVE = 0.4
_TEXTURE_INNER_PX = 4
_TEXTURE_OUTER_PX = 6
_TEXTURE_BUSY_FRACTION = 0.2
_BUSY_SIGMAS = 3.0
_TEXTURE_NOISY_FRACTION = 0.35

#: EM samples are left out where the image is this many times busier than usual (texture).
#: A tighter cut (at the median) also removed noise-only samples selectively and biased
#: the fitted gain by up to 20 %.
_BUSY_SAMPLE_FACTOR = 1.5

#: Percentage of the EM samples, the darkest, whose residual variance is the floor of the
#: photon-counting variance model (the read-noise term; see ``_dark_end_variance``).
_DARK_END_PERCENT = 1.0

_FLOAT = np.float32

#: Pulse polarities and the sign of the residual each accepts (0: either sign).
SPOT_POLARITIES = ("bright", "dark", "both")
#: Where pulses are detected (see :func:`remove_impulses`; "cfa": raw Bayer planes).
SPACES = ("auto", "grey", "hsv", "cfa")
_POLARITY_SIGN = {"bright": 1, "dark": -1, "both": 0}


# --------------------------------------------------------------------------- parameters


@dataclass
class ImpulseParams:
    """Parameters of :func:`remove_impulses` (TOML section ``[impulse]``).

    Attributes
    ----------
    passes_h, passes_s, passes_v : int
        Detect-and-replace passes on hue, saturation and value of a colour image (0 skips
        the channel; 0 to 10).
    passes_grey : int
        Passes on a grey image and on each raw CFA plane (0 to 10).
    window_px : int
        Detection window, 3 or 5 px: 3 compares a pixel with its 8 neighbours; 5 (default)
        with the 8 pixels two steps away (a sparse 5x5 window), which finds patches up to
        3x3 px directly; larger ones are grown from their rim.
    max_patch_px : int
        Largest pulse patch side (px) to grow into, 1 to 8; sets the number of growth rounds
        and the distance of the ring whose spread measures the background structure. Thin
        tracks need no growth along them: each of their pixels is a seed.
    spots : str
        Polarity of the pulses on photon-counting channels (grey, V, CFA): ``"bright"``
        (direct X-ray hits on the sensor; the default), ``"dark"`` (e.g. an open-beam hit
        turned dark by normalisation, dead clusters) or ``"both"``. H and S pulses are
        always two-sided.
    min_contrast : float
        Photon-counting channels only: a pulse must also exceed the local median by this
        fraction of it (Weber contrast, 0 to 1; Frosio & Borghese 2004 visibility rule), so
        statistically significant but invisible bumps on bright areas are kept.
    neighbour_prior : float
        Prior pulse probability of a pixel touching a detected pulse (0 < p < 1; the fitted
        pulse rate applies elsewhere): pulses come as patches and tracks, so their fainter
        rims are accepted at a lower significance (about 3 sigma at 0.5).
    posterior_threshold : float
        A pixel is a pulse when its posterior pulse probability exceeds this (0 < t < 1).
    min_saturation : float
        Pixels with saturation below this (0 to 1), or next to such pixels (within the
        detection window), are left out of hue filtering: their hue is undefined. The
        saturation noise is fitted where S is at least this.
    min_value_fraction : float
        Pixels with V below this fraction of the 99th percentile of V are left out of hue
        filtering (0 to 1).
    em_samples : int
        Pixels (regular subsample) used for the EM fit (>= 1000).
    em_iterations : int
        Maximum EM iterations (1 to 500).
    space : str
        ``"auto"`` (raw Bayer planes for camera raw input, HSV for RGB, grey for grey),
        ``"grey"``, ``"hsv"`` or ``"cfa"`` (camera raw input only).
    """

    passes_h: int = 3
    passes_s: int = 1
    passes_v: int = 1
    passes_grey: int = 1
    window_px: int = 5
    max_patch_px: int = 4
    spots: str = field(default="bright", metadata={
        "help": "polarity of the pulses on grey, V and CFA channels", "choices": SPOT_POLARITIES})
    min_contrast: float = field(default=0.07, metadata={
        "help": "photon-counting channels: a pulse must also exceed the local median by this "
                "fraction of it (Weber contrast, 0 to 1)"})
    neighbour_prior: float = field(default=0.5, metadata={
        "help": "prior pulse probability of a pixel touching a detected pulse, for patch rims "
                "(0 < p < 1)"})
    posterior_threshold: float = 0.5
    min_saturation: float = 0.05
    min_value_fraction: float = 0.02
    em_samples: int = 250_000
    em_iterations: int = 30
    space: str = field(default="auto", metadata={
        "help": "where pulses are detected: auto (cfa for camera raw, hsv for RGB, grey for grey), "
                "grey, hsv or cfa (raw Bayer planes)", "choices": SPACES})

    def __post_init__(self) -> None:
        for name in ("passes_h", "passes_s", "passes_v", "passes_grey"):
            _check_int(name, getattr(self, name), 0, 10)
        _check_int("window_px", self.window_px, 3, 5)
        if self.window_px not in MEDIAN_RESIDUAL_VARIANCE_FACTOR:
            raise ParameterError(f"impulse.window_px: must be 3 or 5, got {self.window_px}")
        _check_int("max_patch_px", self.max_patch_px, 1, 8)
        _check_int("em_samples", self.em_samples, 1000, 100_000_000)
        _check_int("em_iterations", self.em_iterations, 1, 500)
        if self.space not in SPACES:
            raise ParameterError(f"impulse.space: must be one of {', '.join(SPACES)}, got {self.space!r}")
        if self.spots not in SPOT_POLARITIES:
            raise ParameterError(f"impulse.spots: must be one of {', '.join(SPOT_POLARITIES)}, "
                                 f"got {self.spots!r}")
        _check_float("posterior_threshold", self.posterior_threshold, 0.0, 1.0, open_ends=True)
        _check_float("min_contrast", self.min_contrast, 0.0, 1.0)
        _check_float("neighbour_prior", self.neighbour_prior, 0.0, 1.0, open_ends=True)
        _check_float("min_saturation", self.min_saturation, 0.0, 1.0)
        _check_float("min_value_fraction", self.min_value_fraction, 0.0, 1.0)


def _check_int(name: str, value, lo: int, hi: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ParameterError(f"impulse.{name}: must be an integer, got {value!r}")
    if not lo <= value <= hi:
        raise ParameterError(f"impulse.{name}: must be in [{lo}, {hi}], got {value}")


def _check_float(name: str, value, lo: float, hi: float, open_ends: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ParameterError(f"impulse.{name}: must be a number, got {value!r}")
    ok = (lo < value < hi) if open_ends else (lo <= value <= hi)
    if not ok or not math.isfinite(value):
        brackets = f"({lo}, {hi})" if open_ends else f"[{lo}, {hi}]"
        raise ParameterError(f"impulse.{name}: must be in {brackets}, got {value}")


@dataclass
class ImpulseResult:
    """Output of :func:`remove_impulses` and :func:`remove_impulses_cfa`.

    Attributes
    ----------
    image : ndarray
        Cleaned image, same shape and dtype as the input; pixels outside the masks are
        bit-for-bit the input's.
    masks : dict of str to ndarray of bool
        Replaced pixels per channel: ``{"grey"}``, ``{"H", "S", "V"}`` (each (H, W)) or
        ``{"R", "G1", "G2", "B"}`` (each (h, w), CFA plane resolution).
    gain : dict of str to float
        Estimated Poisson gain per channel in input units per detected quantum (value
        variance / mean above offset); NaN for H and S (constant-variance model).
    pulse_rate : dict of str to float
        Estimated pulse probability ``P`` per channel (first pass).
    noise : dict of str to tuple of float
        Fitted residual variance model ``(a, b)``: ``s^2 = a*m + b`` (input units).
    """

    image: np.ndarray
    masks: dict[str, np.ndarray]
    gain: dict[str, float]
    pulse_rate: dict[str, float]
    noise: dict[str, tuple[float, float]] = field(default_factory=dict)

    def any_mask(self) -> np.ndarray:
        """Union of the channel masks, bool, shape of one mask."""
        masks = list(self.masks.values())
        out = np.zeros(masks[0].shape, bool)
        for m in masks:
            out |= m
        return out


# --------------------------------------------------------------------------- building blocks


@dataclass
class _Component:
    """A polyphase component of a channel (rows r0::step, cols c0::step) and its 3x3 median."""

    r0: int
    c0: int
    step: int
    values: np.ndarray
    median: np.ndarray

    def to_flat(self, flat_in_component: np.ndarray, width: int) -> np.ndarray:
        """Flat indices in the full image of flat indices in this component."""
        rows, cols = np.divmod(flat_in_component, self.values.shape[1])
        return (self.r0 + self.step * rows) * width + (self.c0 + self.step * cols)


def _detection_components(x: np.ndarray, size_px: int) -> list[_Component]:
    """The components the fast detection median works on, each with its median (float32).

    ``size_px`` 3: the whole image and its 3x3 median. 5: the *sparse* 5x5 median over the
    centre and the eight pixels two steps away (rows and columns -2, 0, +2), computed as the
    3x3 median of each of the four polyphase components: a patch of up to 3x3 px around the
    centre holds only one of its nine samples, so the median stays on the background, at the
    cost of one 3x3 median. Both include the centre (cv2.medianBlur), replicated border.
    """
    import cv2

    if size_px == 3:
        values = np.ascontiguousarray(x, dtype=_FLOAT)
        return [_Component(0, 0, 1, values, cv2.medianBlur(values, 3))]
    components = []
    for r0 in (0, 1):
        for c0 in (0, 1):
            values = np.ascontiguousarray(x[r0::2, c0::2], dtype=_FLOAT)
            components.append(_Component(r0, c0, 2, values, cv2.medianBlur(values, 3)))
    return components


#: Batcher's odd-even merge sort of 8 values (19 compare-exchanges), used column-wise.
_SORT8_NETWORK = ((0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (1, 2), (5, 6),
                  (0, 4), (3, 7), (1, 5), (2, 6), (1, 4), (3, 6), (2, 4), (3, 5), (3, 4))


def _ring_median_at(x: np.ndarray, rows: np.ndarray, cols: np.ndarray, size_px: int,
                    with_spread: bool = False):
    """Median of the 8 detection samples around each pixel, centre excluded (float64).

    The samples are those of :func:`_detection_components` without the centre: the 8 neighbours
    (``size_px`` 3) or the 8 pixels two steps away (5). Borders are replicated. The median
    of 8 is the mean of the 4th and 5th values, found by a sorting network over the columns.

    ``with_spread``: also return the spread of the 8 samples, (v6 + v7 - v2 - v3) / 2 of the
    sorted values over 1.325, its expected value for 8 Gaussian samples of unit deviation
    (float64): about the noise on a smooth background, far more on edges and corners.
    """
    step = 1 if size_px == 3 else 2
    dr = np.array([-step, -step, -step, 0, 0, step, step, step])
    dc = np.array([-step, 0, step, -step, step, -step, 0, step])
    flat = _flat_indices(rows, cols, dr, dc, x.shape)
    x_flat = np.ascontiguousarray(x).ravel()
    v = [x_flat[flat[:, k]] for k in range(8)]
    for i, j in _SORT8_NETWORK:
        low = np.minimum(v[i], v[j])
        v[j] = np.maximum(v[i], v[j])
        v[i] = low
    median = 0.5 * (v[3].astype(np.float64) + v[4])
    if not with_spread:
        return median
    spread = ((v[5].astype(np.float64) + v[6]) - (v[1].astype(np.float64) + v[2])) / (2.0 * 1.325)
    return median, spread


def _square_ring_spread(x: np.ndarray, rows: np.ndarray, cols: np.ndarray, radius_px: int) -> np.ndarray:
    """Curvature-and-noise spread of the ring at Chebyshev distance ``radius_px`` (float64).

    The ``8 radius_px`` pixels of the square ring (border replicated) form ``4 radius_px``
    point-symmetric pairs; sqrt(2) (q3 - q1)/1.349 of the pair means is the pixel noise on a
    smooth background or a linear ramp, far more at the shoulder of a sharp edge or at a
    corner of the screen.
    """
    r = int(radius_px)
    dr, dc = _window_offsets(2 * r + 1)
    on_ring = np.maximum(np.abs(dr), np.abs(dc)) == r
    flat = _flat_indices(rows, cols, dr[on_ring], dc[on_ring], x.shape)
    vals = np.ascontiguousarray(x).ravel()[flat].astype(np.float64)
    half = vals.shape[1] // 2
    # Means of point-symmetric pairs (row-major ring: the mirror of k is n - 1 - k): on a
    # linear ramp each equals the centre's value, so only curvature and noise spread them.
    pairs = 0.5 * (vals[:, :half] + vals[:, ::-1][:, :half])
    pairs.sort(axis=1)
    n = half
    return math.sqrt(2.0) * (pairs[:, (3 * (n - 1)) // 4] - pairs[:, (n - 1) // 4]) / 1.349


def _sorted_unique(indices: np.ndarray) -> np.ndarray:
    """Sorted distinct values of an integer array (same result as ``np.unique``).

    numpy 2's hash-based ``np.unique`` took about 15x longer than sort-and-compare on the
    neighbour-index arrays of a 24-megapixel frame.
    """
    values = np.sort(indices, axis=None)
    if values.size == 0:
        return values
    keep = np.empty(values.size, bool)
    keep[0] = True
    np.not_equal(values[1:], values[:-1], out=keep[1:])
    return values[keep]


def _flat_indices(rows: np.ndarray, cols: np.ndarray, dr: np.ndarray, dc: np.ndarray, shape) -> np.ndarray:
    """Flat indices of pixels (rows + dr, cols + dc), shape (N, K), borders replicated."""
    h, w = shape
    reach = int(max(np.abs(dr).max(), np.abs(dc).max()))
    flat = (rows.astype(np.intp) * w + cols)[:, None] + (dr * w + dc)[None, :]
    near_border = (rows < reach) | (rows >= h - reach) | (cols < reach) | (cols >= w - reach)
    if near_border.any():
        rr = np.clip(rows[near_border, None] + dr[None, :], 0, h - 1)
        cc = np.clip(cols[near_border, None] + dc[None, :], 0, w - 1)
        flat[near_border] = rr * w + cc
    return flat


def _window_offsets(size_px: int) -> tuple[np.ndarray, np.ndarray]:
    r = size_px // 2
    dr, dc = np.mgrid[-r:r + 1, -r:r + 1]
    return dr.ravel(), dc.ravel()


def _window_flat_indices(rows: np.ndarray, cols: np.ndarray, size_px: int, shape) -> np.ndarray:
    """Flat indices of the ``size_px`` x ``size_px`` window around each pixel (border replicated)."""
    dr, dc = _window_offsets(size_px)
    return _flat_indices(rows, cols, dr, dc, shape)


def _masked_median_at(x: np.ndarray, excluded: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                      smallest_px: int = 3, symmetric: bool = False, with_spread: bool = False):
    """Median of the non-excluded pixels around each (row, col), float64.

    Tries windows of 3 (or ``smallest_px``), 5, 7 and 9 px and uses, per pixel, the smallest
    with enough non-excluded pixels. Borders are replicated. Returns NaN where even the
    largest window holds no usable pixel. Hue must already be rotated so that the values do
    not straddle the wrap (the median is then the linear one).

    ``symmetric``: a pixel is also left out when its mirror image through the centre is
    excluded. The remaining set is point-symmetric, so on a locally linear ramp (a blurred
    edge) its median is the centre's expected value; excluding the pulses on one side only
    would pull the median towards the other side, and patch growth would then creep along
    the ramp, pixel by pixel, down the gradient.

    ``with_spread``: also return the spread of those pixels, (q3 - q1)/1.349 (the standard
    deviation for Gaussian noise; larger where the window holds structure, float64).
    """
    x_flat = np.ascontiguousarray(x).ravel()
    excluded_flat = np.ascontiguousarray(excluded).ravel()
    out = np.full(rows.shape, np.nan)
    spread = np.full(rows.shape, np.nan) if with_spread else None
    todo = np.arange(rows.size)
    for size, min_good in zip(_REPLACEMENT_WINDOWS_PX, _REPLACEMENT_MIN_GOOD, strict=True):
        if todo.size == 0:
            break
        if size < smallest_px:
            continue
        flat = _window_flat_indices(rows[todo], cols[todo], size, x.shape)
        vals = x_flat[flat].astype(_FLOAT, copy=False)
        bad = excluded_flat[flat] != 0
        if symmetric:
            bad |= bad[:, ::-1]  # row-major window: the mirror of offset k is offset n - 1 - k
        good_count = size * size - np.count_nonzero(bad, axis=1)
        vals[bad] = np.inf
        vals.sort(axis=1)
        enough = good_count >= (min_good if size != _REPLACEMENT_WINDOWS_PX[-1] else 1)
        idx = np.nonzero(enough)[0]
        if idx.size:
            n = good_count[idx]
            lo = np.take_along_axis(vals[idx], ((n - 1) // 2)[:, None], axis=1)[:, 0]
            hi = np.take_along_axis(vals[idx], (n // 2)[:, None], axis=1)[:, 0]
            out[todo[idx]] = 0.5 * (lo.astype(np.float64) + hi)
            if with_spread:
                q1 = np.take_along_axis(vals[idx], ((n - 1) // 4)[:, None], axis=1)[:, 0]
                q3 = np.take_along_axis(vals[idx], ((3 * (n - 1)) // 4)[:, None], axis=1)[:, 0]
                spread[todo[idx]] = (q3.astype(np.float64) - q1) / 1.349
        todo = todo[~enough]
    return (out, spread) if with_spread else out


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

    def variance(self, m: np.ndarray) -> np.ndarray:
        return np.maximum(self.a * m + self.b, self.var_floor)

    def log_odds_constant(self, posterior_threshold: float, rate: float) -> float:
        """2 ln((1-P)/(P u)) + 2 ln(t/(1-t)) - ln(2 pi): the threshold is s^2 (this - ln s^2)."""
        return (2.0 * math.log((1.0 - rate) / (rate * self.pulse_density))
                + 2.0 * math.log(posterior_threshold / (1.0 - posterior_threshold))
                - math.log(2.0 * math.pi))

    def is_pulse(self, d: np.ndarray, m: np.ndarray, posterior_threshold: float,
                 prior: float | None = None, min_variance: np.ndarray | None = None) -> np.ndarray:
        """Posterior pulse probability > threshold, vectorised (float32 inputs allowed).

        r > t  <=>  d^2/s^2 > 2 ln((1-P)/(P u)) + 2 ln(t/(1-t)) - ln(2 pi s^2),
        with ``P`` the fitted pulse rate unless a ``prior`` is given, and ``s^2`` at least
        ``min_variance`` where that is given.
        """
        s2 = self.variance(m)
        if min_variance is not None:
            s2 = np.maximum(s2, min_variance)
        const = self.log_odds_constant(posterior_threshold, self.pulse_rate if prior is None else prior)
        limit = s2 * (const - np.log(s2))
        pulse = (d * d > limit) & (limit > 0) | (limit <= 0)
        if self.polarity > 0:
            pulse &= d > 0
        elif self.polarity < 0:
            pulse &= d < 0
        else:
            pulse &= d != 0
        if self.min_contrast > 0:
            pulse &= np.abs(d) > self.min_contrast * np.abs(m)
        return pulse


def _fit_mixture(d: np.ndarray, m: np.ndarray, *, photon_counting: bool, polarity: int,
                 value_range: float, iterations: int) -> _NoiseModel:
    """Fit a, b and P by EM on residuals ``d`` and medians ``m`` (1-D float64 subsample)."""
    density = 1.0 / value_range if polarity else 1.0 / (2.0 * value_range)
    var_floor = max((1e-4 * value_range) ** 2, 1e-12)
    mad = 1.4826 * float(np.median(np.abs(d)))
    if photon_counting:
        level = np.maximum(m - float(np.percentile(m, 0.5)), 0.0) + 1.0
        scale = 1.4826 * float(np.median(np.abs(d) / np.sqrt(level)))
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
        log_gauss = -0.5 * d2 / s2 - 0.5 * np.log(2.0 * np.pi * s2)
        pulse_log = math.log(model.pulse_rate * density)
        if polarity:
            pulse_log = np.where(d * polarity > 0, pulse_log, -np.inf)
        # responsibilities r = P u / (P u + (1 - P) N), via the log-odds for stability
        log_odds = pulse_log - (math.log(1.0 - model.pulse_rate) + log_gauss)
        resp = 0.5 * (1.0 + np.tanh(0.5 * np.clip(log_odds, -60, 60)))
        new_rate = float(np.clip(resp.mean(), 1e-7, 0.5))
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
    return float(np.median(m[dark])), (1.4826 * float(np.median(np.abs(d[dark])))) ** 2


class _Stacked:
    """A per-pixel map stored component by component: (components, h/step, w/step), float32.

    The fast detection works on polyphase components; keeping its maps in that layout
    avoids strided writes of whole frames. ``at`` reads the values at full-image flat indices.
    """

    def __init__(self, shape, step: int):
        self._height, self.width = shape
        self.step = step
        self.rows, self.cols = -(-shape[0] // step), -(-shape[1] // step)
        self.data = np.zeros((step * step, self.rows, self.cols), _FLOAT)
        self.flat = self.data.reshape(-1)

    def part(self, comp: "_Component") -> np.ndarray:
        """The (writable) block of one component, shaped like its values."""
        k = comp.r0 * self.step + comp.c0
        return self.data[k, :comp.values.shape[0], :comp.values.shape[1]]

    def index(self, flat: np.ndarray) -> np.ndarray:
        if self.step == 1:
            return flat
        rows, cols = np.divmod(flat, self.width)
        return self._index(rows, cols)

    def _index(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        if self.step == 1:
            return rows * self.width + cols
        out = (rows & 1) * (2 * self.rows * self.cols)
        out += (cols & 1) * (self.rows * self.cols)
        out += (rows >> 1) * self.cols
        out += cols >> 1
        return out

    def at(self, flat: np.ndarray) -> np.ndarray:
        return self.flat[self.index(flat)]

    def around(self, rows: np.ndarray, cols: np.ndarray, dr: np.ndarray, dc: np.ndarray) -> np.ndarray:
        """Values at (rows + dr, cols + dc), shape (N, K), borders replicated."""
        reach = int(max(np.abs(dr).max(), np.abs(dc).max()))
        rr = rows.astype(np.intp)[:, None] + dr[None, :]
        cc = cols.astype(np.intp)[:, None] + dc[None, :]
        near_border = ((rows < reach) | (rows >= self._height - reach)
                       | (cols < reach) | (cols >= self.width - reach))
        if near_border.any():
            rr[near_border] = np.clip(rr[near_border], 0, self._height - 1)
            cc[near_border] = np.clip(cc[near_border], 0, self.width - 1)
        return self.flat[self._index(rr, cc)]


def _stacked_medians(components: list[_Component], shape) -> _Stacked:
    out = _Stacked(shape, components[0].step)
    for comp in components:
        out.part(comp)[...] = comp.median
    return out


def _flat_area_sample(components: list[_Component], valid: np.ndarray | None, count: int,
                      photon_counting: bool, x: np.ndarray, fast_residual: "_Stacked") -> np.ndarray:
    """Flat indices of about ``count`` pixels in the flattest half of the image.

    Texture and edges inflate the residual and would bias the noise fit
    (docs/algorithms/impulse.md, section 'Pitfalls'); the fit therefore uses pixels whose
    local slope of the detection median (between
    the direct neighbours, whose medians use other samples than the pixel's own) is at most
    the median slope, the slope being divided by sqrt(m) for photon-counting channels so
    that bright areas are not excluded just for their larger noise. A median flattens fine
    texture (line patterns, meshes), so its slope does not see it; the pixels must also be
    at most ``_BUSY_SAMPLE_FACTOR`` times as busy as the median pixel (a mean of 8
    absolute noise residuals rarely is; texture far more), busy meaning the mean absolute residual to the
    fast median of the 8 pixels three steps away (scaled like the slope; those pixels and
    their median samples all have an odd offset, so they share no pixel with the residual
    the fit uses, and selecting on them does not bias the fitted noise). Regular subsample
    (deterministic).
    """
    shape = h, w = x.shape
    candidates = _subsample_indices(h * w, 2 * count)
    if valid is not None:
        candidates = candidates[valid.ravel()[candidates]]
    if candidates.size < 32:
        return candidates
    rows, cols = np.divmod(candidates, w)
    median = _stacked_medians(components, shape)
    around = median.around(rows, cols, np.array([0, 0, 1, -1]), np.array([1, -1, 0, 0]))
    del median
    slope = np.abs(around[:, 0] - around[:, 1]) + np.abs(around[:, 2] - around[:, 3])
    ring_dr = np.array([-3, -3, -3, 0, 0, 3, 3, 3])
    ring_dc = np.array([-3, 0, 3, -3, 3, -3, 0, 3])
    busy = np.abs(fast_residual.around(rows, cols, ring_dr, ring_dc)).mean(axis=1)
    if photon_counting:
        scale = np.sqrt(np.abs(x.ravel()[candidates] - fast_residual.at(candidates)) + 1.0)
        slope = slope / scale
        busy = busy / scale
    return candidates[(slope <= np.median(slope)) & (busy <= _BUSY_SAMPLE_FACTOR * np.median(busy))]


def _subsample_indices(n: int, count: int) -> np.ndarray:
    """A regular (deterministic) subsample of ``count`` flat indices out of ``n``."""
    if n <= count:
        return np.arange(n)
    step = n / count
    return (np.arange(count) * step).astype(np.int64)


def _clean_channel(x: np.ndarray, *, passes: int, params: ImpulseParams, photon_counting: bool,
                   polarity: int, valid: np.ndarray | None = None, circular: bool = False,
                   value_range: float | None = None, residual_weight: np.ndarray | None = None,
                   in_place: bool = False, fit_region: np.ndarray | None = None):
    """Detect and replace pulses in one float32 channel (``in_place``: in ``x`` itself).

    ``fit_region`` (bool, optional): the noise model is fitted on these pixels only (and
    within ``valid``); detection still covers every valid pixel.

    ``residual_weight`` (constant-variance channels): residuals are multiplied by it before
    the Gaussian model is fitted and applied, so that a channel whose noise is known to
    scale as 1/weight gets a constant variance (H and S: see :func:`_remove_hsv`).

    Only the first pass looks at the whole image. A later pass can only find pulses where
    the previous one changed a detection median, so it re-tests just the pixels within the
    detection window of the pixels replaced before (the same result as a full pass).

    Returns (cleaned float32 channel, mask, model of the first pass or None). Pulse pixels
    get the median of their non-pulse neighbours; others are untouched.
    """
    if not (in_place and x.dtype == _FLOAT and x.flags.c_contiguous):
        x = np.array(x, dtype=_FLOAT, copy=True)
    h, w = x.shape
    mask_total = np.zeros((h, w), bool)
    if passes == 0:
        return x, mask_total, None
    if value_range is None:
        value_range = float(x.max() - x.min())
    value_range = max(value_range, 1e-12)
    components = _detection_components(x, params.window_px)
    fast_residual = _fast_residual(components, (h, w), circular, residual_weight)
    fit_valid = valid if fit_region is None else (fit_region if valid is None else valid & fit_region)
    pick = _flat_area_sample(components, fit_valid, params.em_samples, photon_counting, x, fast_residual)
    if pick.size < 16 and fit_region is not None:  # too few: fit on every valid pixel
        pick = _flat_area_sample(components, valid, params.em_samples, photon_counting, x, fast_residual)
    if pick.size < 16:
        return x, mask_total, None
    d_fit, m_fit = _exact_residual(x, *np.divmod(pick, w), params.window_px, circular, residual_weight)
    model = _fit_mixture(d_fit, m_fit, photon_counting=photon_counting, polarity=polarity,
                         value_range=value_range, iterations=params.em_iterations)
    del d_fit, m_fit, pick
    if photon_counting:
        model.min_contrast = float(params.min_contrast)
    valid_flat = None if valid is None else valid.ravel()
    scratch = np.zeros((h, w), np.uint8)  # 1: pulse of this pass, 2: ring under test
    near_scratch = np.zeros((h, w), np.uint8)  # within 2 px of a pulse (growth's texture guard)
    reach = 1 if params.window_px == 3 else 2
    to_check = None
    for _ in range(passes):
        if to_check is None:
            candidates = _prefilter(components, model, params, fast_residual)
            del components
        else:
            candidates = to_check
        if valid_flat is not None:
            candidates = candidates[valid_flat[candidates]]
        seeds = _exact_test(x, candidates, model, params, circular, residual_weight)
        seeds = seeds[~_in_texture(fast_residual, seeds, x, model)]
        pulses = _grow_patches(x, seeds, model, params, valid_flat, circular, residual_weight, scratch,
                               fast_residual, near_scratch)
        if pulses.size == 0:
            break
        rows, cols = np.divmod(pulses, w)
        # Replacement values come from outside the detected patches. (Leaving out their 1-px
        # rim as well changed the residual pulse energy by 1 % and doubled the damage of
        # false alarms on thin anatomy: measured, not kept.)
        scratch.ravel()[pulses] = 1
        repl = _masked_median_at(x, scratch, rows, cols)
        scratch.ravel()[pulses] = 0
        keep = np.isfinite(repl)
        x.ravel()[pulses[keep]] = repl[keep].astype(_FLOAT)
        fast_residual.flat[fast_residual.index(pulses)] = 0.0  # replaced: no longer busy (texture guard)
        mask_total.ravel()[pulses] = True
        dr, dc = _window_offsets(2 * reach + 1)
        to_check = _sorted_unique(_flat_indices(rows, cols, dr, dc, (h, w)))
    return x, mask_total, model


def _exact_residual(x: np.ndarray, rows: np.ndarray, cols: np.ndarray, size_px: int,
                    circular: bool, residual_weight: np.ndarray | None):
    """Residual to the centre-excluded detection median, and that median (float64)."""
    med = _ring_median_at(x, rows, cols, size_px)
    d = x[rows, cols].astype(np.float64) - med
    if circular:
        d -= np.rint(d)  # into [-0.5, 0.5]: the short way round the hue circle
    if residual_weight is not None:
        d *= residual_weight[rows, cols]
    return d, med


def _fast_residual(components: list[_Component], shape, circular: bool,
                   residual_weight: np.ndarray | None) -> _Stacked:
    """Residual of every pixel to its fast detection median (float32, weighted like the test)."""
    residual = _Stacked(shape, components[0].step)
    for comp in components:
        d = residual.part(comp)
        np.subtract(comp.values, comp.median, out=d)
        if circular:
            d -= np.rint(d)
        if residual_weight is not None:
            d *= residual_weight[comp.r0::comp.step, comp.c0::comp.step]
    return residual


def _prefilter(components: list[_Component], model: _NoiseModel, params: ImpulseParams,
               residual: _Stacked) -> np.ndarray:
    """Flat indices of pulse candidates from the residuals to the cheap centre-including medians.

    Nearly a superset of the pulses of the exact test (see ``_PREFILTER_FRACTION``): the
    residual to the fast median must exceed
    ``_PREFILTER_FRACTION`` of the smallest threshold the exact test can use at that level
    (the log term of the threshold is bounded by its value at the largest variance), so the
    full-image work is a handful of array operations without logarithms.
    """
    width = residual.width
    const = model.log_odds_constant(params.posterior_threshold, model.pulse_rate)
    fraction2 = _PREFILTER_FRACTION ** 2
    if model.a > 0:
        m_max = max(float(comp.median.max()) for comp in components)
        factor = const - math.log(max(model.a * m_max + model.b, model.var_floor))
    else:
        s2 = max(model.b, model.var_floor)
        factor = const - math.log(s2)
    found = []
    for comp in components:
        d = residual.part(comp).copy()
        if factor <= 0:  # degenerate fit: test every pixel exactly
            candidates = d * model.polarity > 0 if model.polarity else d != 0
        elif model.a > 0:
            s2 = np.multiply(comp.median, _FLOAT(model.a * fraction2 * factor), dtype=_FLOAT)
            s2 += _FLOAT(model.b * fraction2 * factor)
            np.maximum(s2, _FLOAT(model.var_floor * fraction2 * factor), out=s2)
            candidates = d * _FLOAT(model.polarity) > 0 if model.polarity else None
            d *= d
            candidates = d > s2 if candidates is None else candidates & (d > s2)
        else:
            threshold = _FLOAT(_PREFILTER_FRACTION * math.sqrt(s2 * factor))
            candidates = d * _FLOAT(model.polarity) > threshold if model.polarity else np.abs(d) > threshold
        found.append(comp.to_flat(np.flatnonzero(candidates), width))
    return np.concatenate(found)


def _in_texture(residual: _Stacked, pixels: np.ndarray, x: np.ndarray, model: "_NoiseModel",
                reference: np.ndarray | None = None, ignore: np.ndarray | None = None,
                chunk: int = 65536) -> np.ndarray:
    """True where the annulus around a pixel is busier than a pulse's can be (texture guard).

    ``residual``: the fast-median residual map of :func:`_prefilter`; ``pixels``: flat
    indices; ``reference``: the residual busy pixels are compared with (default: each
    pixel's own to the fast median; a patch rim uses its excess over its background),
    never less than ``_BUSY_SIGMAS`` noise sigmas; ``x`` and ``model``: the
    channel and its noise model (for the noise-relative count); ``ignore`` (flat uint8,
    optional): pixels left out of the annulus (next to detected pulses, whose fast median
    the pulse pulls up). Fewer than a third of the annulus left: not texture.
    """
    out = np.zeros(pixels.size, bool)
    if pixels.size == 0:
        return out
    dr, dc = _window_offsets(2 * _TEXTURE_OUTER_PX + 1)
    on = np.maximum(np.abs(dr), np.abs(dc)) >= _TEXTURE_INNER_PX
    dr, dc = dr[on], dc[on]
    flat_x = x.ravel()

    for start in range(0, pixels.size, chunk):
        part = pixels[start:start + chunk]
        rows, cols = np.divmod(part, x.shape[1])
        own_residual = residual.at(part)
        own = own_residual if reference is None else reference[start:start + chunk]
        if model.a > 0:
            own_noise2 = model.variance(flat_x[part] - own_residual)
        else:
            own_noise2 = max(model.b, model.var_floor)
        # At least the noise-relative level: a weak pulse or rim is not texture for noise.
        level = np.maximum(np.abs(own) * _BUSY_RELATIVE, _BUSY_SIGMAS * np.sqrt(own_noise2)).astype(_FLOAT)
        idx = _flat_indices(rows, cols, dr, dc, x.shape)
        around_signed = residual.around(rows, cols, dr, dc)
        around = np.abs(around_signed)
        counted = np.ones(idx.shape, bool) if ignore is None else ignore[idx] == 0
        n_counted = np.count_nonzero(counted, axis=1)
        busy = np.count_nonzero((around > level[:, None]) & counted, axis=1) > _TEXTURE_BUSY_FRACTION * n_counted
        if model.a > 0:  # photon counting: variance at the fast median x - residual
            noise2 = model.variance(flat_x[idx] - around_signed).astype(_FLOAT)
        else:
            noise2 = _FLOAT(max(model.b, model.var_floor))
        around *= around
        noisy = (around > _FLOAT(_BUSY_SIGMAS ** 2) * noise2) & counted
        busy |= np.count_nonzero(noisy, axis=1) > _TEXTURE_NOISY_FRACTION * n_counted
        out[start:start + chunk] = busy & (n_counted * 3 >= dr.size)
    return out


def _exact_test(x: np.ndarray, candidates: np.ndarray, model: _NoiseModel, params: ImpulseParams,
                circular: bool, residual_weight: np.ndarray | None) -> np.ndarray:
    """The candidates (flat indices) that are pulses by the posterior test."""
    if candidates.size == 0:
        return candidates
    rows, cols = np.divmod(candidates, x.shape[1])
    d, med = _exact_residual(x, rows, cols, params.window_px, circular, None)
    spread = _square_ring_spread(x, rows, cols, params.max_patch_px)
    if residual_weight is not None:
        weight = residual_weight[rows, cols]
        d *= weight
        spread *= weight
    # Structure guard: where the background around the candidate spreads far more than the
    # noise (an edge, the corner of the screen), the residual is not Gaussian around the
    # median; the variance is then at least (spread / _SEED_SPREAD_TOLERANCE)^2. The spread
    # is taken just outside the largest patch, so the patch itself never inflates it.
    spread /= _SEED_SPREAD_TOLERANCE
    return candidates[model.is_pulse(d, med, params.posterior_threshold, min_variance=spread * spread)]


def _grow_patches(x: np.ndarray, seeds: np.ndarray, model: _NoiseModel, params: ImpulseParams,
                  valid_flat: np.ndarray | None, circular: bool,
                  residual_weight: np.ndarray | None, scratch: np.ndarray,
                  fast_residual: _Stacked, near_scratch: np.ndarray) -> np.ndarray:
    """Add neighbours of detected pulses that are pulses against their background.

    Each round tests the ring of pixels next to the pulses against the median of the
    pixels of a 7x7 (or larger) window that are neither pulses nor in the ring, so the
    still undetected core of a large patch does not pull the background up; a patch is
    peeled from its rim inward. The window is large enough to surround the pixel on an edge
    (a 3x3 window minus the patch would hold only pixels on one side). Ring pixels get the
    prior pulse probability ``params.neighbour_prior``: pulses come as patches and tracks,
    so their fainter rims are accepted at a lower significance.

    Grown pixels also pass the texture guard (:func:`_in_texture`), relative to their
    excess over the background and ignoring pixels within 2 px of the pulses found so far.

    ``seeds`` and the result are flat indices; ``scratch`` and ``near_scratch`` (uint8,
    zero) mark pulses and ring, and the neighbourhood of pulses; both are zero on return.
    """
    if seeds.size == 0:
        return seeds
    h, w = x.shape
    marks = scratch.ravel()
    prior = max(params.neighbour_prior, model.pulse_rate)
    dr8 = np.array([-1, -1, -1, 0, 0, 1, 1, 1])
    dc8 = np.array([-1, 0, 1, -1, 1, -1, 0, 1])
    pulses = seeds
    marks[pulses] = 1
    near_flat = near_scratch.ravel()
    dr5, dc5 = _window_offsets(5)
    near_marked = [_flat_indices(*np.divmod(seeds, w), dr5, dc5, (h, w))]
    near_flat[near_marked[0]] = 1
    for _ in range(params.max_patch_px):
        rows, cols = np.divmod(pulses, w)
        ring = _sorted_unique(_flat_indices(rows, cols, dr8, dc8, (h, w)))
        ring = ring[marks[ring] == 0]
        if valid_flat is not None:
            ring = ring[valid_flat[ring]]
        if ring.size == 0:
            break
        marks[ring] = 2
        ring_rows, ring_cols = np.divmod(ring, w)
        med, spread = _masked_median_at(x, scratch, ring_rows, ring_cols, smallest_px=7,
                                        symmetric=True, with_spread=True)
        d = x.ravel()[ring].astype(np.float64) - med
        if circular:
            d -= np.rint(d)
        if residual_weight is not None:
            weight = residual_weight.ravel()[ring]
            d *= weight
            spread *= weight
        ok = np.isfinite(d)
        new = np.zeros(ring.shape, bool)
        new[ok] = model.is_pulse(d[ok], med[ok], params.posterior_threshold, prior=prior,
                                 min_variance=spread[ok] ** 2)
        marks[ring] = 0
        if new.any():
            # Texture guard as for seeds, relative to the pixel's excess over its background.
            grown = ring[new]
            texture = _in_texture(fast_residual, grown, x, model, d[new], near_flat)
            new[np.flatnonzero(new)[texture]] = False
        if not new.any():
            break
        marks[ring[new]] = 1
        near_marked.append(_flat_indices(*np.divmod(ring[new], w), dr5, dc5, (h, w)))
        near_flat[near_marked[-1]] = 1
        pulses = np.concatenate([pulses, ring[new]])
    marks[pulses] = 0
    for marked in near_marked:
        near_flat[marked] = 0
    return pulses


def _to_dtype(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Cast replacement values to the image dtype (rounded and clipped for integers)."""
    dtype = np.dtype(dtype)
    if dtype.kind in "ui":
        info = np.iinfo(dtype)
        return np.clip(np.rint(values), info.min, info.max).astype(dtype)
    return values.astype(dtype)


def _gain(model: _NoiseModel | None, params: ImpulseParams) -> float:
    if model is None or model.a <= 0:
        return float("nan")
    return model.a / MEDIAN_RESIDUAL_VARIANCE_FACTOR[params.window_px]


# --------------------------------------------------------------------------- grey


def _remove_grey(image: np.ndarray, params: ImpulseParams) -> ImpulseResult:
    x = image.astype(_FLOAT)
    cleaned, mask, model = _clean_channel(x, passes=params.passes_grey, params=params,
                                          photon_counting=True, polarity=_POLARITY_SIGN[params.spots])
    out = image.copy()
    if mask.any():
        # Only pulse pixels are written: medians computed in float32 (exact for integer
        # counts below 2**24), rounded for integer images.
        out[mask] = _to_dtype(cleaned[mask].astype(np.float64), image.dtype)
    return ImpulseResult(out, {"grey": mask}, {"grey": _gain(model, params)},
                         {"grey": model.pulse_rate if model else float("nan")},
                         {"grey": (model.a, model.b) if model else (float("nan"), float("nan"))})


def _remove_grey_of_rgb(image: np.ndarray, params: ImpulseParams) -> ImpulseResult:
    """Detect on the channel sum (still photon counting) and replace R, G, B at the pulses."""
    grey = image.astype(_FLOAT).sum(axis=2)
    _, mask, model = _clean_channel(grey, passes=params.passes_grey, params=params,
                                    photon_counting=True, polarity=_POLARITY_SIGN[params.spots])
    out = image.copy()
    if mask.any():
        rows, cols = np.nonzero(mask)
        for c in range(3):
            chan = image[..., c].astype(_FLOAT)
            repl = _masked_median_at(chan, mask, rows, cols)
            out[rows, cols, c] = _to_dtype(repl, image.dtype)
    return ImpulseResult(out, {"grey": mask}, {"grey": _gain(model, params)},
                         {"grey": model.pulse_rate if model else float("nan")},
                         {"grey": (model.a, model.b) if model else (float("nan"), float("nan"))})


# --------------------------------------------------------------------------- HSV


def _erode(mask: np.ndarray, size_px: int) -> np.ndarray:
    """Pixels whose whole ``size_px`` square window is in ``mask`` (bool; border replicated)."""
    import cv2

    kernel = np.ones((size_px, size_px), np.uint8)
    eroded = cv2.erode(np.ascontiguousarray(mask).view(np.uint8), kernel,
                       borderType=cv2.BORDER_REPLICATE)
    return eroded.view(bool)


def _median3(x: np.ndarray) -> np.ndarray:
    """3x3 median (float32, new array, replicated border)."""
    import cv2

    return cv2.medianBlur(np.ascontiguousarray(x, dtype=_FLOAT), 3)


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
    below = None
    if math.isfinite(model.dark_level) and model.dark_level > 0:
        below = out < _FLOAT(model.dark_level)
        var_at_dark = max(model.a * model.dark_level + model.b, model.var_floor, 1e-12)
        scaled_below = out[below] * _FLOAT(var_at_dark / model.dark_level)
    out *= _FLOAT(model.a)
    out += _FLOAT(model.b)
    np.maximum(out, _FLOAT(max(model.var_floor, 1e-12)), out=out)
    if below is not None:
        out[below] = np.maximum(scaled_below, _FLOAT(1e-12))
    return out


def _saturation_weight(s: np.ndarray, v: np.ndarray, model: "_NoiseModel | None") -> np.ndarray:
    """Inverse noise of the saturation, normalised to a median of 1 (float32, new array).

    ``S = 1 - min/max`` with ``max = V`` and ``min = V (1 - S)``; first-order propagation:
    ``Var[S] = (Var[min] + (1 - S)^2 Var[max]) / V^2`` with the count variances of
    :func:`_count_variance`. With Poisson counts and no offset this is
    ``G (1 - S)(2 - S) / V``; over a black level in the dark it is about
    ``2 sigma_e^2 / V^2``, far smaller than a ``1/V`` law scaled from the screen would say.
    Computed in blocks of rows (bounded temporaries on 24 Mpx frames).
    """
    height, width = s.shape
    weight = np.empty((height, width), _FLOAT)
    rows_per_block = max(1, (1 << 20) // max(width, 1))
    for r0 in range(0, height, rows_per_block):
        r1 = min(height, r0 + rows_per_block)
        v_block = v[r0:r1]
        one_minus_s = np.subtract(_FLOAT(1.0), s[r0:r1], dtype=_FLOAT)
        np.clip(one_minus_s, _FLOAT(0.0), _FLOAT(1.0), out=one_minus_s)
        var_total = _count_variance(v_block * one_minus_s, model)
        one_minus_s *= one_minus_s
        one_minus_s *= _count_variance(v_block, model)
        var_total += one_minus_s
        np.sqrt(var_total, out=var_total)
        np.divide(np.maximum(v_block, _FLOAT(0.0)), var_total, out=weight[r0:r1])
    weight /= max(float(np.median(weight[::7, ::7])), 1e-12)
    return weight


def rgb_to_hsv_counts(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split RGB (any real dtype, counts) into hue, saturation and value, float32.

    Uses OpenCV's float conversion (the standard hexcone formulas, as
    ``skimage.color.rgb2hsv``, but with V kept in the input's units).

    Returns
    -------
    hue : ndarray, float32, in [0, 1] (0 red, 1/3 green, 2/3 blue; 0 where undefined; 1 = 0)
    saturation : ndarray, float32, in [0, 1] ((max - min)/max; 0 where max is 0)
    value : ndarray, float32, max(R, G, B) in the input's units (counts)
    """
    import cv2

    height, width = rgb.shape[:2]
    hue, sat, val = (np.empty((height, width), _FLOAT) for _ in range(3))
    rows_per_block = max(1, (1 << 20) // max(width, 1))  # bounded temporaries (~12 MB)
    for r0 in range(0, height, rows_per_block):
        r1 = min(height, r0 + rows_per_block)
        block = cv2.cvtColor(np.ascontiguousarray(rgb[r0:r1], dtype=_FLOAT), cv2.COLOR_RGB2HSV)
        hue[r0:r1], sat[r0:r1], val[r0:r1] = block[..., 0], block[..., 1], block[..., 2]
    # Hue can round up to exactly 1.0 (360 degrees); every use wraps it modulo 1.
    hue *= _FLOAT(1.0 / 360.0)
    return hue, sat, val


def hsv_counts_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rgb_to_hsv_counts`; float64 (..., 3) in the units of ``v``."""
    h = np.asarray(h, np.float64) % 1.0
    s = np.clip(np.asarray(s, np.float64), 0.0, 1.0)
    v = np.asarray(v, np.float64)
    h6 = h * 6.0
    sector = np.floor(h6).astype(np.int64) % 6
    f = h6 - np.floor(h6)
    p = v * (1 - s)
    q = v * (1 - s * f)
    t = v * (1 - s * (1 - f))
    choices_r = [v, q, p, p, t, v]
    choices_g = [t, v, v, q, p, p]
    choices_b = [p, p, t, v, v, q]
    out = np.empty(h.shape + (3,), np.float64)
    out[..., 0] = np.choose(sector, choices_r)
    out[..., 1] = np.choose(sector, choices_g)
    out[..., 2] = np.choose(sector, choices_b)
    return out


def dominant_hue(h: np.ndarray, valid: np.ndarray, bins: int = 360) -> float:
    """Most frequent hue (bin centre in [0, 1)) among ``valid`` pixels (regular subsample)."""
    step = max(1, int(math.sqrt(h.size / 1_000_000)))
    sel = h[::step, ::step][valid[::step, ::step]]
    if sel.size == 0:
        return 0.0
    counts = np.bincount(np.minimum((sel * bins).astype(np.int64), bins - 1), minlength=bins)
    return (int(np.argmax(counts)) + 0.5) / bins


def _remove_hsv(image: np.ndarray, params: ImpulseParams) -> ImpulseResult:
    # Channels are cleaned in place: the cleaned H, S, V are the input's wherever their
    # mask is False, so they rebuild the RGB of every changed pixel.
    h, s, v = rgb_to_hsv_counts(image)
    v_top = float(np.percentile(v[:: max(1, v.shape[0] // 512), :: max(1, v.shape[1] // 512)], 99))
    masks: dict[str, np.ndarray] = {}
    gain: dict[str, float] = {}
    rate: dict[str, float] = {}
    noise: dict[str, tuple[float, float]] = {}

    def _store(name, mask, model, photon):
        masks[name] = mask
        gain[name] = _gain(model, params) if photon else float("nan")
        rate[name] = model.pulse_rate if model else float("nan")
        noise[name] = (model.a, model.b) if model else (float("nan"), float("nan"))

    # V first: bright zingers are clearest there, and a cleaner V defines the hue mask better.
    v_new, mask_v, model_v = _clean_channel(v, passes=params.passes_v, params=params,
                                            photon_counting=True, polarity=_POLARITY_SIGN[params.spots],
                                            in_place=True)
    _store("V", mask_v, model_v, True)
    # S and H are ratios of photon counts. Their noise follows from that of the counts,
    # Var[c] = G (c - o) + sigma_e^2 (V's fitted model, read-noise floor included; see
    # _count_variance and _saturation_weight). Residuals are weighted by the inverse of that noise (normalised
    # to a median of 1), so that one constant Gaussian variance fits the whole image, the
    # dark surround of the screen (read noise over a black level) included.
    # The weights use 3x3 medians of S and V: a pixel's own noise must not set its own
    # weight (a count low by chance raises S and would also raise its weight).
    v_local = _median3(v_new)
    s_local = _median3(s)
    weight_s = _saturation_weight(s_local, v_local, model_v)
    del v_local  # recomputed for the hue (memory: 24 Mpx frames)
    # The first-order propagation holds where max - min is well above its noise; in the
    # unsaturated dark surround S is the range of three nearly equal noisy counts and the
    # weighted residual is narrower there. The constant variance is fitted where S is
    # defined (as for hue), so that the screen's variance is not underestimated.
    s_defined = s_local >= _FLOAT(params.min_saturation)
    del s_local
    s_new, mask_s, model_s = _clean_channel(s, passes=params.passes_s, params=params,
                                            photon_counting=False, polarity=0, value_range=1.0,
                                            residual_weight=weight_s, in_place=True,
                                            fit_region=s_defined)
    del s_defined
    _store("S", mask_s, model_s, False)
    del weight_s
    hue_valid = (s_new >= params.min_saturation) & (v_new >= params.min_value_fraction * v_top)
    # A hue is tested against the hues of its detection samples, so they must be defined too:
    # a pixel just above the saturation cut in the dark surround would otherwise be compared
    # with the random hues of its unsaturated neighbours.
    hue_valid = _erode(hue_valid, params.window_px)
    hue_mode = dominant_hue(h, hue_valid)
    h_rot = h
    h_rot += _FLOAT(0.5 - hue_mode)
    h_rot -= np.floor(h_rot)
    # Hue noise: sqrt(Var[V]) / (V S) (the hexcone hue is a difference of two channels over
    # max - min = V S).
    v_local = _median3(v_new)
    weight_h = _count_variance(v_local, model_v)
    np.sqrt(weight_h, out=weight_h)
    np.divide(v_local, weight_h, out=weight_h)
    del v_local
    weight_h *= s_new
    typical = weight_h[::7, ::7][hue_valid[::7, ::7]]
    weight_h /= max(float(np.median(typical)) if typical.size else 1.0, 1e-12)
    h_new, mask_h, model_h = _clean_channel(h_rot, passes=params.passes_h, params=params,
                                            photon_counting=False, polarity=0,
                                            valid=hue_valid, circular=True, value_range=1.0,
                                            residual_weight=weight_h, in_place=True)
    del weight_h
    _store("H", mask_h, model_h, False)
    out = image.copy()
    changed = mask_h | mask_s | mask_v
    if changed.any():
        rows, cols = np.nonzero(changed)
        hh = (h_new[rows, cols] + (hue_mode - 0.5)) % 1.0
        rgb = hsv_counts_to_rgb(hh, s_new[rows, cols], v_new[rows, cols])
        out[rows, cols] = _to_dtype(rgb, image.dtype)
    return ImpulseResult(out, {"H": mask_h, "S": mask_s, "V": mask_v}, gain, rate, noise)


# --------------------------------------------------------------------------- public API


def remove_impulses(image: np.ndarray, params: ImpulseParams | None = None, *,
                    space: str | None = None) -> ImpulseResult:
    """Detect and replace impulse noise (zingers) in a grey or RGB image.

    Parameters
    ----------
    image : ndarray
        ``(H, W)`` grey or ``(H, W, 3)`` RGB; uint8, uint16, float32 or float64, **linear**
        values (counts; never gamma-encoded), at least 8x8 px.
    params : ImpulseParams, optional
        Defaults: H 3 passes, S 1, V 1, grey 1; 5x5 detection median; bright-only pulses.
    space : {"auto", "grey", "hsv"}, optional
        Default ``params.space``. ``"auto"``: grey for 2-D input, HSV for RGB. ``"grey"`` on RGB detects on R+G+B
        and replaces all three channels at the detected pixels. ``"hsv"``: H, S and V
        separately (H circular, rotated so the dominant hue sits at 0.5; pixels with small S
        or V are left out of hue filtering).

    Returns
    -------
    ImpulseResult
        Cleaned image (same shape and dtype), per-channel masks, gain and pulse rate.

    Raises
    ------
    InputError
        Wrong shape, dtype, NaN values or a too small image.
    ParameterError
        Unknown ``space`` or ``space="hsv"`` on a grey image.
    """
    from ..io import validate_image

    params = ImpulseParams() if params is None else params
    if not isinstance(params, ImpulseParams):
        raise ParameterError(f"impulse: params must be ImpulseParams, got {type(params).__name__}")
    space = params.space if space is None else space
    if space == "cfa":
        raise ParameterError("impulse: space 'cfa' needs the raw Bayer planes of a camera raw file "
                             "(remove_impulses_cfa); this image is already demosaiced")
    if space not in ("auto", "grey", "hsv"):
        raise ParameterError(f"impulse: space must be auto, grey or hsv, got {space!r}")
    arr = np.asarray(image)
    checked = validate_image(arr, "image")
    if checked.shape != arr.shape or checked.dtype != arr.dtype:
        raise InputError("image", f"expected (H, W) or (H, W, 3) uint8/uint16/float32/float64, "
                                  f"got shape {arr.shape} dtype {arr.dtype}")
    if arr.ndim == 2:
        if space == "hsv":
            raise ParameterError("impulse: space 'hsv' needs an RGB image, got a grey one")
        return _remove_grey(arr, params)
    if space == "grey":
        return _remove_grey_of_rgb(arr, params)
    return _remove_hsv(arr, params)


def remove_impulses_cfa(planes: np.ndarray, params: ImpulseParams | None = None) -> ImpulseResult:
    """Detect and replace zingers on raw Bayer planes, before demosaicing spreads them.

    Parameters
    ----------
    planes : ndarray, float32, shape (4, h, w)
        CFA planes R, G1, G2, B in counts above black (``RawFrame.cfa_planes``).
    params : ImpulseParams, optional
        ``passes_grey`` passes per plane.

    Returns
    -------
    ImpulseResult
        ``image`` float32 (4, h, w); masks, gain and pulse rate keyed R, G1, G2, B.
    """
    params = ImpulseParams() if params is None else params
    arr = np.asarray(planes)
    if arr.ndim != 3 or arr.shape[0] != 4:
        raise InputError("CFA planes", f"expected shape (4, h, w), got {arr.shape}")
    if arr.dtype.kind != "f" and arr.dtype.kind not in "ui":
        raise InputError("CFA planes", f"unsupported dtype {arr.dtype}")
    if min(arr.shape[1:]) < 8:
        raise InputError("CFA planes", f"planes are {arr.shape[1]}x{arr.shape[2]} px; at least 8x8 needed")
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        raise InputError("CFA planes", "NaN or infinite values")
    out = arr.copy()
    masks, gain, rate, noise = {}, {}, {}, {}
    for i, name in enumerate(("R", "G1", "G2", "B")):
        plane = arr[i]
        cleaned, mask, model = _clean_channel(plane.astype(_FLOAT), passes=params.passes_grey,
                                              params=params, photon_counting=True,
                                              polarity=_POLARITY_SIGN[params.spots])
        if mask.any():
            out[i][mask] = _to_dtype(cleaned[mask].astype(np.float64), arr.dtype)
        masks[name] = mask
        gain[name] = _gain(model, params)
        rate[name] = model.pulse_rate if model else float("nan")
        noise[name] = (model.a, model.b) if model else (float("nan"), float("nan"))
    return ImpulseResult(out, masks, gain, rate, noise)


def cfa_mask_to_mosaic(masks: dict[str, np.ndarray], plane_offsets, shape: tuple[int, int]) -> np.ndarray:
    """Place per-plane masks at their Bayer positions in a (H, W) bool mosaic mask."""
    out = np.zeros(shape, bool)
    for (name, mask), (r, c) in zip(masks.items(), plane_offsets, strict=True):
        sub = out[r::2, c::2]
        hh, ww = min(sub.shape[0], mask.shape[0]), min(sub.shape[1], mask.shape[1])
        sub[:hh, :ww] = mask[:hh, :ww]
    return out


def demosaic_cleaned_raw(path, cleaned_planes: np.ndarray, raw_frame) -> np.ndarray:
    """Demosaic a raw file after putting cleaned CFA planes back into its mosaic.

    Opens ``path`` again with rawpy, writes the cleaned values (plus each plane's black
    level, rounded, clipped to [0, white level]) into ``raw_image_visible`` where they
    differ from the original planes, and demosaics with
    :func:`napari_dslrxr.core.io.postprocess_linear`, as :func:`~napari_dslrxr.core.io.read_raw`
    does. With unchanged planes the result equals ``read_image(path).data`` (tested).

    Parameters
    ----------
    path : path-like
        The raw file the planes came from.
    cleaned_planes : ndarray, float32, (4, h, w)
        Counts above black, R, G1, G2, B (from :func:`remove_impulses_cfa`).
    raw_frame : napari_dslrxr.core.io.RawFrame
        The frame read from ``path``: original planes, plane offsets, black and white level.

    Returns
    -------
    ndarray, uint16, (H, W, 3)
        Linear RGB.
    """
    import rawpy

    from ..io import postprocess_linear

    cleaned = np.asarray(cleaned_planes)
    if cleaned.shape != raw_frame.cfa_planes.shape:
        raise InputError(str(path), f"cleaned planes {cleaned.shape} do not match the file's "
                                    f"{raw_frame.cfa_planes.shape}")
    try:
        with rawpy.imread(str(path)) as raw:
            visible = raw.raw_image_visible
            for plane, original, (r, c), black in zip(cleaned, raw_frame.cfa_planes,
                                                       raw_frame.plane_offsets, raw_frame.black_level,
                                                       strict=True):
                changed = plane != original
                if not changed.any():
                    continue
                rows, cols = np.nonzero(changed)
                values = np.clip(np.rint(plane[rows, cols].astype(np.float64) + float(black)), 0,
                                 raw_frame.white_level)
                visible[2 * rows + r, 2 * cols + c] = values.astype(visible.dtype)
            return postprocess_linear(raw)
    except InputError:
        raise
    except Exception as exc:  # rawpy.LibRawError and friends
        raise InputError(str(path), f"cannot demosaic the cleaned raw data ({exc})") from None
