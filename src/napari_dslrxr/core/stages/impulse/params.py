"""Parameters (TOML section ``[impulse]``) and result of the impulse stage."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...param_fields import validate_fields

_FLOAT = np.float32

#: Pulse polarities and the sign of the residual each accepts (0: either sign).
SPOT_POLARITIES = ("bright", "dark", "both")
#: Where pulses are detected (see :func:`remove_impulses`; "cfa": raw Bayer planes).
SPACES = ("auto", "grey", "hsv", "cfa")
_POLARITY_SIGN = {"bright": 1, "dark": -1, "both": 0}

#: Var[x - m] / Var[x] for independent pixels, ``m`` the median of the 8 detection samples
#: around the centre (centre excluded), measured by simulation on Poisson images (mean 50 to
#: 10 000 counts; 1 + Var[m]/Var[x]). The residual is then Gaussian (kurtosis 3.0), unlike
#: the residual to a median that includes the centre (a spike at 0, too light a variance for
#: its tails). Turns the fitted slope into a gain.
MEDIAN_RESIDUAL_VARIANCE_FACTOR = {3: 1.17, 5: 1.17}


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
    min_object_sigma_px : float
        Grey and V channels: a compact detected patch that is a smooth Gaussian hill at least
        this wide (sigma, px) on its background, like a small dense object (a calcification, a
        marker bead) blurred by the screen, is structure and is left as it is (0.5 to 4 px;
        about the screen's blur; 4 turns the test off). Pulses from sensor hits are sharper.
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

    passes_h: int = field(default=3, metadata={
        "help": "detect-and-replace passes on hue (0 skips)", "unit": "passes", "min": 0, "max": 10})
    passes_s: int = field(default=1, metadata={
        "help": "passes on saturation (0 skips)", "unit": "passes", "min": 0, "max": 10})
    passes_v: int = field(default=1, metadata={
        "help": "passes on value V = max(R, G, B) (0 skips)", "unit": "passes", "min": 0, "max": 10})
    passes_grey: int = field(default=1, metadata={
        "help": "passes on a grey image and on each raw CFA plane (0 skips)", "unit": "passes", "min": 0, "max": 10})
    window_px: int = field(default=5, metadata={
        "help": "median window of the first detection: 3 = the 8 neighbours, 5 = the 8 pixels two steps away "
                "(finds patches up to 3x3 px)", "unit": "px", "choices": (3, 5)})
    max_patch_px: int = field(default=4, metadata={
        "help": "largest pulse patch side grown into", "unit": "px", "min": 1, "max": 8})
    spots: str = field(default="bright", metadata={
        "help": "polarity of the pulses on grey, V and CFA channels", "choices": SPOT_POLARITIES})
    min_contrast: float = field(default=0.07, metadata={
        "help": "photon-counting channels: a pulse must also exceed the local median by this "
                "fraction of it (Weber contrast)", "unit": "fraction", "min": 0.0, "max": 1.0})
    neighbour_prior: float = field(default=0.5, metadata={
        "help": "prior pulse probability of a pixel touching a detected pulse, for patch rims",
        "unit": "probability", "min": 0.0, "max": 1.0, "open_range": True})
    posterior_threshold: float = field(default=0.5, metadata={
        "help": "a pixel is a pulse when its posterior pulse probability exceeds this",
        "unit": "probability", "min": 0.0, "max": 1.0, "open_range": True})
    min_object_sigma_px: float = field(default=1.4, metadata={
        "help": "a compact patch that is a Gaussian hill at least this wide (sigma) on its background, like a "
                "small dense object blurred by the screen, is left as structure (4 turns the test off)",
        "unit": "px", "min": 0.5, "max": 4.0})
    min_saturation: float = field(default=0.05, metadata={
        "help": "pixels with saturation below this are left out of hue filtering", "unit": "fraction",
        "min": 0.0, "max": 1.0})
    min_value_fraction: float = field(default=0.02, metadata={
        "help": "pixels with V below this fraction of the 99th percentile are left out of hue filtering",
        "unit": "fraction", "min": 0.0, "max": 1.0})
    em_samples: int = field(default=250_000, metadata={
        "help": "pixels subsampled for the EM fit", "unit": "px", "min": 1000, "max": 100_000_000})
    em_iterations: int = field(default=30, metadata={
        "help": "maximum EM iterations", "unit": "iterations", "min": 1, "max": 500})
    space: str = field(default="auto", metadata={
        "help": "where pulses are detected: auto (cfa for camera raw, hsv for RGB, grey for grey), "
                "grey, hsv or cfa (raw Bayer planes)", "choices": SPACES})

    def __post_init__(self) -> None:
        validate_fields(self, "impulse")


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


def _to_dtype(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Cast replacement values to the image dtype (rounded and clipped for integers)."""
    dtype = np.dtype(dtype)
    if dtype.kind in "ui":
        info = np.iinfo(dtype)
        return np.clip(np.rint(values), info.min, info.max).astype(dtype)
    return values.astype(dtype)
