"""Multiscale contrast enhancement, MUSICA-style (stage vi).

A Laplacian pyramid (Burt-Adelson: ``g_{l+1} = pyrDown(g_l)``, ``b_l = g_l -
pyrUp(g_{l+1})`` with explicit output sizes, so any image size works without padding)
splits the value-of-interest scaled image into zero-mean detail bands. Each band's
coefficients go through a power-law conversion (Vuylsteke & Schoeters, SPIE 2167, 1994)::

    y = a_l * M_l * sgn(x) * (|x| / M_l) ** p          p = 1 - 0.7 * detail_contrast

which amplifies small coefficients more than large ones (subtle detail up, strong edges
kept). Noise lives in the smallest coefficients, so near zero the mapping is blended towards
the identity (unit gain) with a weight ``1 - exp(-(|x| / x_c)^4)``, ``x_c = noise_floor *
sigma_0`` and ``sigma_0`` the robust noise level of the finest band (1.4826 MAD): noise-level
coefficients keep gain ~1, and the power law takes over above the noise floor. ``M_l`` is the
99.5th percentile of ``|b_l|`` inside the region. ``a_l`` is ``edge_sharpness`` for the
finest band, ``bone_contrast`` for the coarser bands (mid and large structures such as bone
and organ outlines). Reconstruction sums the modified bands back onto the coarsest level.

Halo guard. A gain above 1 on the coefficients of a strong edge (collimator, skin line,
metal) is a band-limited overshoot: a bright rim on one side and a dark band on the other,
as wide as the band's scale. Radiologists reject such halos, so the gain ``G`` of each
coefficient is pulled back to 1 where the band holds a strong edge::

    G' = 1 + (G - 1) / (1 + (m_loc / e_l) ** 4)      e_l = 0.25 * halo_step

``m_loc`` is the largest ``|b_l|`` in a 7 x 7 neighbourhood (so the weaker coefficients on
the flanks of a strong edge get the same unit gain as its peak, and the edge keeps its
shape) and ``e_l`` the peak coefficient of a step of ``halo_step`` value-of-interest units
(a unit step's largest Laplacian coefficient is 0.23-0.38 at every level). Steps well below
``halo_step`` (subtle detail, trabeculae, vessels) get the full power-law gain.

Coarse bands: a local Laplacian remapping. In the coarse bands (level 2 and coarser) any
coefficient gain shows as a band as wide as the band (tens of pixels) beside every lucent or
dense area, and the 7 x 7 guard either leaves that halo (threshold above the step) or takes
the gain away from all structure near the step. So the coarse bands come from a fast local
Laplacian filter (Paris, Hasinoff & Kautz 2011; Aubry et al. 2014) of the level-2 Gaussian
image ``g_2``: for reference levels ``gamma_k`` spaced ``coarse_halo_step`` apart over the
region's 0.5-99.5 % range of ``g_2``, the image remapped around ``gamma_k``::

    r_k(v) = gamma_k + d * (beta + (a - beta) * exp(-d^2 / (2 s^2)))     d = v - gamma_k

(``a`` = ``bone_contrast``, ``beta`` = ``coarse_edge_gain``, ``s`` = ``coarse_halo_step``) is
decomposed into a Laplacian pyramid, and each output coefficient is interpolated between the
two ``k`` whose ``gamma_k`` bracket the Gaussian pyramid's value there. Differences smaller than
``s`` from the local level are amplified by up to ``a``; differences well above ``s`` (the edge
of a lung, an air gap, the skin line) get ``beta`` on both sides alike, so a strong edge is
compressed (``beta`` < 1: latitude without a halo) but gets no overshoot. ``coarse_halo_step
= 0`` maps the coarse bands like the fine ones (power law with gain ``bone_contrast`` from
level 1 on, and the 7 x 7 guard at ``halo_step``: the former behaviour). Measured in docs/safety.md ("Display without damage").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import InputError
from ..param_fields import validate_fields
from ..robust import robust_sigma as _robust_sigma


@dataclass
class ContrastParams:
    """Parameters of multiscale contrast enhancement (TOML section ``[contrast]``).

    Attributes
    ----------
    enabled : bool
    detail_contrast : float
        Strength of the enhancement of subtle detail, 0 (off) to 1 (strongest); sets the
        power ``p = 1 - 0.7 * detail_contrast`` of the coefficient mapping.
    bone_contrast : float
        Gain of mid and coarse structure (bone, organ outlines) smaller than
        ``coarse_halo_step``, 0.5 to 6 (the coarse bands' local Laplacian remapping; with
        ``coarse_halo_step = 0`` the power-law gain of every band but the finest).
    edge_sharpness : float
        Gain of the fine bands (levels 0 and 1: edges, fine texture), 0.5 to 3.
    noise_floor : float
        Coefficients below this many noise standard deviations of the finest band keep unit
        gain (the linear segment near zero), 0 to 10.
    levels : int
        Pyramid levels; 0 = automatic (coarsest band about 32 px), 1 to 12.
    halo_step : float
        Edges with a step larger than about this (value-of-interest units) keep unit gain, so
        strong edges get no halo; 0 = off (0 to 2).
    coarse_halo_step : float
        Range of the coarse bands' local Laplacian remapping (level 2 and coarser): differences
        from the local level below about this are raised by ``bone_contrast``, larger ones
        (strong edges) get ``coarse_edge_gain`` on both sides, so no halo (0 to 2 VOI
        units); 0 = the power-law mapping and 7 x 7 guard of the fine bands there (halos).
    coarse_edge_gain : float
        Gain of coarse differences well above ``coarse_halo_step`` (0.3 to 1): below 1
        compresses large steps (thick and thin parts shown together) without a halo.
    """

    enabled: bool = field(default=True, metadata={"help": "apply multiscale (MUSICA-style) contrast enhancement"})
    detail_contrast: float = field(default=0.3, metadata={
        "help": "strength of subtle-detail enhancement: 0 = off, 1 = strongest (power p = 1 - 0.7 x this)",
        "unit": "strength", "min": 0.0, "max": 1.0})
    bone_contrast: float = field(default=4.0, metadata={
        "help": "gain of mid and coarse structures (bone, organ outlines) below the coarse halo step",
        "unit": "gain", "min": 0.5, "max": 6.0})
    edge_sharpness: float = field(default=1.0, metadata={
        "help": "gain of the fine bands (edges, fine texture)", "unit": "gain", "min": 0.5, "max": 3.0})
    noise_floor: float = field(default=4.0, metadata={
        "help": "coefficients below this many noise sigmas (finest band) keep unit gain, so noise is not amplified",
        "unit": "sigma", "min": 0.0, "max": 10.0})
    levels: int = field(default=0, metadata={
        "help": "pyramid levels; 0 = automatic (coarsest band about 32 px)", "unit": "levels", "min": 0, "max": 12})
    halo_step: float = field(default=0.3, metadata={
        "help": "edges with a step above about this keep unit gain (no halo at strong edges); 0 = off",
        "unit": "VOI units", "min": 0.0, "max": 2.0})
    coarse_halo_step: float = field(default=0.04, metadata={
        "help": "coarse bands: differences below about this are raised, larger ones (strong edges) keep "
                "coarse_edge_gain, so no halo; 0 = power-law mapping there as in the fine bands",
        "unit": "VOI units", "min": 0.0, "max": 2.0})
    coarse_edge_gain: float = field(default=0.7, metadata={
        "help": "gain of coarse differences above the coarse halo step: below 1 compresses strong steps "
                "without a halo", "unit": "gain", "min": 0.3, "max": 1.0})

    def __post_init__(self) -> None:
        validate_fields(self, "contrast")


def auto_levels(shape: tuple[int, int], coarsest_px: int = 32) -> int:
    """Number of levels so that the coarsest band is about ``coarsest_px`` on the short side."""
    short = min(shape[:2])
    return int(max(1, min(12, np.floor(np.log2(max(short, 2) / coarsest_px)) + 1)))


def laplacian_pyramid(image: np.ndarray, levels: int) -> list[np.ndarray]:
    """Laplacian pyramid ``[b_0, ..., b_{L-1}, g_L]`` (float32, explicit sizes, no padding)."""
    current = np.ascontiguousarray(image, np.float32)
    bands = []
    for _ in range(levels):
        if min(current.shape) < 4:
            break
        down = cv2.pyrDown(current)
        up = cv2.pyrUp(down, dstsize=(current.shape[1], current.shape[0]))
        current -= up  # reuse the buffer: current becomes the band
        bands.append(current)
        current = down
    bands.append(current)
    return bands


def reconstruct_pyramid(bands: list[np.ndarray]) -> np.ndarray:
    """Inverse of :func:`laplacian_pyramid` (sums bands onto the expanded residual)."""
    current = bands[-1]
    for band in reversed(bands[:-1]):
        up = cv2.pyrUp(current, dstsize=(band.shape[1], band.shape[0]))
        up += band
        current = up
    return current


def robust_sigma(values: np.ndarray) -> float:
    """1.4826 x median absolute deviation (a noise sigma robust to structure)."""
    v = np.asarray(values, np.float32).ravel()
    if v.size > 1_000_000:
        v = v[:: v.size // 500_000]
    return _robust_sigma(v)


def map_coefficients(band: np.ndarray, *, gain: float, power: float, max_coef: float,
                     noise_level: float, edge_level: float = 0.0) -> np.ndarray:
    """Power-law coefficient mapping with a unit-gain segment near zero (in place, float32).

    Parameters
    ----------
    band : ndarray, float32
        Detail coefficients (modified in place and returned).
    gain : float
        ``a_l``.
    power : float
        ``p`` in (0, 1]; 1 = linear.
    max_coef : float
        ``M_l``: coefficients of this size get gain ``a_l``.
    noise_level : float
        ``x_c``: below it the gain blends to 1.
    edge_level : float
        ``e_l``: where the 7 x 7 neighbourhood holds a coefficient much larger than this the
        gain blends to 1 (halo guard); 0 = off.
    """
    max_coef = max(float(max_coef), 1e-9)
    mag = np.abs(band)
    edge_weight = None
    if edge_level > 0:
        edge_weight = cv2.dilate(mag, np.ones((7, 7), np.uint8), borderType=cv2.BORDER_REPLICATE)
        edge_weight *= np.float32(1.0 / edge_level)  # w_e = 1 / (1 + (m_loc / e_l)^4)
        np.square(edge_weight, out=edge_weight)
        np.square(edge_weight, out=edge_weight)
        edge_weight += 1.0
        np.reciprocal(edge_weight, out=edge_weight)
    # power-law gain a (|x|/M)^(p-1), capped so that a zero coefficient stays finite
    pl_gain = np.maximum(mag, max_coef * 1e-4)
    pl_gain *= np.float32(1.0 / max_coef)
    np.power(pl_gain, np.float32(power - 1.0), out=pl_gain)
    pl_gain *= np.float32(gain)
    if noise_level > 0:
        weight = mag  # reuse buffer: w = 1 - exp(-(|x|/x_c)^4)
        weight *= np.float32(1.0 / noise_level)
        np.square(weight, out=weight)
        np.square(weight, out=weight)
        np.negative(weight, out=weight)
        np.exp(weight, out=weight)
        np.subtract(1.0, weight, out=weight)
        pl_gain -= 1.0
        pl_gain *= weight
        pl_gain += 1.0
    if edge_weight is not None:
        pl_gain -= 1.0
        pl_gain *= edge_weight
        pl_gain += 1.0
    band *= pl_gain
    return band


#: Most reference levels of the coarse bands' local Laplacian remapping (their spacing widens
#: beyond ``coarse_halo_step`` when the image's range would need more).
MAX_REFERENCE_LEVELS = 48
#: VOI-unit range the coarse bands' reference levels cover at most: the display window (0..1)
#: and a margin; 47 spacings of the default ``coarse_halo_step`` (0.04) span 1.88.
COARSE_LEVELS_RANGE = (-0.4, 1.4)


def local_laplacian_bands(image: np.ndarray, n_bands: int, *, detail_gain: float, edge_gain: float,
                          range_sigma: float, value_range: tuple[float, float]) -> list[np.ndarray]:
    """Laplacian pyramid of a fast local Laplacian filter of ``image``: ``[b_0, ..., g_n]``.

    Parameters
    ----------
    image : ndarray, float32, (H, W)
    n_bands : int
        Detail bands wanted (fewer when the image gets smaller than 4 px).
    detail_gain : float
        Gain ``a`` of differences from the local level much smaller than ``range_sigma``.
    edge_gain : float
        Gain ``beta`` of differences much larger than ``range_sigma``.
    range_sigma : float
        ``s`` of the remapping ``r(v) = g + d (beta + (a - beta) exp(-d^2 / 2 s^2))``, ``d = v - g``;
        also the reference levels' spacing.
    value_range : (float, float)
        Range covered by reference levels; values beyond use the nearest level.

    Returns
    -------
    list of ndarray
        Detail bands then the Gaussian residual of ``image`` (unchanged), as
        :func:`laplacian_pyramid` returns them, ready for :func:`reconstruct_pyramid`.
    """
    g = np.ascontiguousarray(image, np.float32)
    lo, hi = float(value_range[0]), float(min(max(value_range[1], value_range[0]), np.finfo(np.float32).max))
    spacing = max(float(range_sigma), (hi - lo) / (MAX_REFERENCE_LEVELS - 1), 1e-6)
    count = max(2, int(np.ceil((hi - lo) / spacing)) + 1)
    gauss = [g]
    while len(gauss) <= n_bands and min(gauss[-1].shape) >= 4:
        gauss.append(cv2.pyrDown(gauss[-1]))
    n_bands = len(gauss) - 1
    # position of each pyramid value among the reference levels (hat-function interpolation)
    positions = [np.clip((level - np.float32(lo)) * np.float32(1.0 / spacing), 0, count - 1) for level in gauss[:-1]]
    out = [np.zeros_like(level) for level in gauss[:-1]]
    inv_two_s2 = np.float32(-0.5 / float(range_sigma) ** 2)
    for k in range(count):
        reference = np.float32(lo + k * spacing)
        diff = g - reference
        remapped = np.square(diff)
        remapped *= inv_two_s2
        np.exp(remapped, out=remapped)
        remapped *= np.float32(detail_gain - edge_gain)
        remapped += np.float32(edge_gain)
        remapped *= diff
        remapped += reference
        bands = laplacian_pyramid(remapped, n_bands)
        for band, acc, pos in zip(bands[:n_bands], out, positions):
            weight = np.abs(pos - np.float32(k))
            np.subtract(1.0, weight, out=weight)
            np.maximum(weight, 0.0, out=weight)
            weight *= band
            acc += weight
    out.append(gauss[-1])
    return out


def enhance_contrast(image: np.ndarray, params: ContrastParams | None = None,
                     mask: np.ndarray | None = None) -> np.ndarray:
    """MUSICA-style multiscale contrast enhancement of a VOI-scaled log image.

    Parameters
    ----------
    image : ndarray, float32, (H, W)
        Value-of-interest scaled image (about 0..1, log/attenuation domain).
    params : ContrastParams, optional
    mask : ndarray, bool, (H, W), optional
        Region used to measure ``M_l`` and the noise level; None = all pixels.

    Returns
    -------
    ndarray, float32, (H, W)
        Enhanced image in the same units (identity when disabled or detail_contrast = 0
        and all gains, ``coarse_edge_gain`` included, are 1).

    Raises
    ------
    InputError
        When the image holds NaN or infinite values (and the stage is enabled).
    """
    params = params or ContrastParams()
    x = np.asarray(image, np.float32)
    if not params.enabled:
        return x.copy()
    # one NaN would spread through every pyramid band into the whole output (the sum is NaN or
    # infinite exactly when a value is not finite, and costs one pass)
    if not np.isfinite(np.sum(x, dtype=np.float64)):
        raise InputError("image", "contains NaN or infinite values; the contrast stage needs finite values")
    levels = params.levels or auto_levels(x.shape)
    power = 1.0 - 0.7 * float(params.detail_contrast)
    noise_level = 0.0
    use_mask = mask is not None and mask.shape == x.shape and not mask.all()
    coarse_step = float(params.coarse_halo_step)
    # with the local Laplacian remapping, the power law maps only the fine bands (levels 0, 1)
    bands = laplacian_pyramid(x.copy(), min(levels, 2) if coarse_step > 0 else levels)
    for index, band in enumerate(bands[:-1]):
        sample = _region_sample(band, mask if use_mask else None, 2**index)
        if index == 0:
            noise_level = float(params.noise_floor) * robust_sigma(sample)
        max_coef = float(np.percentile(np.abs(sample), 99.5)) if sample.size else 1.0
        gain = params.edge_sharpness if index == 0 or coarse_step > 0 else params.bone_contrast
        # the noise floor shrinks by ~2 per level (noise is roughly white); keep it per level
        level_noise = noise_level / (2.0**index)
        map_coefficients(band, gain=gain, power=power, max_coef=max_coef, noise_level=level_noise,
                         edge_level=0.25 * float(params.halo_step))
    coarse_bands = levels - (len(bands) - 1)
    if coarse_step > 0 and coarse_bands > 0:
        residual = bands[-1]
        values = _region_sample(residual, mask if use_mask else None, 2 ** (len(bands) - 1))
        lo, hi = (float(v) for v in np.percentile(values, [0.5, 99.5])) if values.size else (0.0, 1.0)
        # Levels only where the display can show something (VOI units: the window is 0..1): a
        # wider range would space them beyond the remapping's width, and detail between two
        # levels would get the edge gain instead of the detail gain.
        lo, hi = max(lo, COARSE_LEVELS_RANGE[0]), min(hi, COARSE_LEVELS_RANGE[1])
        lo, hi = (lo, hi) if lo < hi else COARSE_LEVELS_RANGE
        bands[-1] = reconstruct_pyramid(local_laplacian_bands(
            residual, coarse_bands, detail_gain=float(params.bone_contrast),
            edge_gain=float(params.coarse_edge_gain), range_sigma=coarse_step, value_range=(lo, hi)))
    return reconstruct_pyramid(bands)


def _region_sample(band: np.ndarray, mask: np.ndarray | None, scale: int) -> np.ndarray:
    """Values of a pyramid level (``scale`` = its subsampling) inside ``mask``, about 1 Mpx at most.

    A regular subsample: boolean indexing of a 24 Mpx band would cost more than the pyramid itself.
    """
    step = max(1, int(np.sqrt(band.size / 1_000_000)))
    sub = band[::step, ::step]
    if mask is None:
        return sub.ravel()
    full_step = step * scale
    sub_mask = mask[::full_step, ::full_step][: sub.shape[0], : sub.shape[1]]
    sub = sub[: sub_mask.shape[0], : sub_mask.shape[1]]
    return sub[sub_mask] if sub_mask.any() else sub.ravel()
