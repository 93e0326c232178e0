"""Object region and value-of-interest scaling (stage iii).

The region is where the exposed screen (or, for display radiographs, the collimated field)
is: :func:`detect_screen` (module :mod:`.screen`) finds a screen quadrilateral on strong
evidence only, :func:`detect_collimation` (module :mod:`.collimation`) finds collimator
blades. This module holds their shared parameters and region type, the polygon helpers and
the value-of-interest window.

:func:`voi_window` picks the values of interest inside the region: percentiles of the
histogram after excluding the direct-exposure mode (unattenuated beam), the standard CR/DR
"exposure recognition" step that makes the later gains image-independent.

:func:`rectify` optionally warps the quadrilateral onto a rectangle (perspective correction).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import InputError
from ..param_fields import validate_fields


@dataclass
class RegionParams:
    """Parameters of the region and scaling stage (TOML section ``[region]``).

    Attributes
    ----------
    enabled : bool
        Detect the screen; when false the whole frame is the region.
    analysis_size_px : int
        Longest side (px) of the downsampled copy used for detection (128 to 4096).
    shrink_fraction : float
        Move each corner towards the centre by this fraction of the quadrilateral's size, to
        drop the screen's soft rim (0 to 0.2).
    rectify : bool
        Warp the quadrilateral onto a rectangle (perspective correction).
    voi_low_percentile, voi_high_percentile : float
        Percentiles (0 to 100) of the attenuation values inside the region mapped to 0 and 1.
    exclude_direct_exposure : bool
        Leave the direct-exposure (unattenuated) mode out of the value-of-interest histogram.
    polygon_xy : list of [x, y]
        User override of the screen corners (4 points, pixels, TL, TR, BR, BL); empty = detect.
    min_border_contrast_sigma : float
        A point of the screen's border counts as evidence when the screen just inside is
        brighter than the surround just outside by this many noise sigmas of the measurement
        (the step averaged over 9 px along the border and 5 px across each side; 3 to 100).
    min_border_coverage : float
        Share of the border's length (sides along the frame's edge excluded) that must show
        that contrast before a screen is accepted (0.3 to 1).
    max_bright_surround : float
        Largest share of the surround (away from the border) that may be as bright as the
        screen's edge; a brighter surround means the candidate is anatomy, or only the
        brightest part of a screen (direct exposure beside a limb that absorbs nearly as much
        as the room is dark), not a whole screen (0 to 0.5). Measured on camera frames of
        real anatomy: whole screens leave at most 0.06 % of the surround that bright, parts of
        screens 1-6 %.
    detect_collimation : bool
        For display radiographs (CR/DR, :func:`napari_dslrxr.core.pipeline.enhance_radiograph`
        and the contrast widget): find collimator blades with :func:`detect_collimation` and
        use the exposed field as the region. Camera frames ignore it (they use the screen).
    collimation_inset_px : float
        Move each found collimator edge at least this many pixels into the field (0 to 200), so
        the blade's penumbra (the soft inner side of the edge) counts as outside; further where
        the penumbra is measured to reach further (``drop_penumbra`` of
        :func:`detect_collimation`: a soft blade's faint tail would show as a grey line beside
        the black shutter).
    """

    enabled: bool = field(default=True, metadata={"help": "detect the exposed screen; false = the whole frame is the region"})
    analysis_size_px: int = field(default=1024, metadata={
        "help": "longest side of the downsampled copy used for detection", "unit": "px", "min": 128, "max": 4096})
    shrink_fraction: float = field(default=0.01, metadata={
        "help": "move each corner inward by this fraction of the screen size (drops the soft rim)",
        "unit": "fraction", "min": 0.0, "max": 0.2})
    rectify: bool = field(default=False, metadata={"help": "warp the screen quadrilateral onto a rectangle (perspective correction)"})
    voi_low_percentile: float = field(default=0.5, metadata={
        "help": "percentile of the attenuation inside the region shown as black", "unit": "%", "min": 0.0, "max": 50.0})
    voi_high_percentile: float = field(default=99.5, metadata={
        "help": "percentile of the attenuation inside the region shown as white", "unit": "%", "min": 50.0, "max": 100.0})
    exclude_direct_exposure: bool = field(default=True, metadata={
        "help": "leave the unattenuated (direct-exposure) background out of the value-of-interest window"})
    polygon_xy: list = field(default_factory=list, metadata={
        "help": "user override of the screen corners [[x, y], ...] (4 points, px, TL TR BR BL); [] = detect",
        "unit": "px", "points": 4})
    min_border_contrast_sigma: float = field(default=5.0, metadata={
        "help": "border contrast (screen inside minus surround) that counts as evidence, in pixel-noise sigmas",
        "unit": "sigma", "min": 3.0, "max": 100.0})
    min_border_coverage: float = field(default=0.7, metadata={
        "help": "share of the screen border's length that must show that contrast (else the whole frame is used)",
        "unit": "fraction", "min": 0.3, "max": 1.0})
    max_bright_surround: float = field(default=0.01, metadata={
        "help": "largest share of the surround as bright as the screen's edge (else the whole frame is used)",
        "unit": "fraction", "min": 0.0, "max": 0.5})
    detect_collimation: bool = field(default=True, metadata={
        "help": "display radiographs only: find collimator blades and use the exposed field as the region"})
    collimation_inset_px: float = field(default=10.0, metadata={
        "help": "move each found collimator edge at least this far into the field, further where the "
                "blade's penumbra is measured to reach further (drops the penumbra under the black shutter)",
        "unit": "px", "min": 0.0, "max": 200.0})

    def __post_init__(self) -> None:
        validate_fields(self, "region")


@dataclass
class Region:
    """The exposed screen area and the values of interest.

    Attributes
    ----------
    mask : ndarray, bool, (H, W)
        Pixels inside the (shrunk) quadrilateral.
    polygon_xy : ndarray, float64, (4, 2)
        Corners (x, y) in pixels, order top-left, top-right, bottom-right, bottom-left.
    detected : bool
        False when the polygon came from the user or is the whole frame.
    evidence : dict
        What the detection found and how strongly (see :func:`screen_evidence`), or why
        nothing was accepted (``"reason"``); empty for user polygons.
    """

    mask: np.ndarray
    polygon_xy: np.ndarray
    detected: bool = True
    evidence: dict = field(default_factory=dict)


def order_corners(points_xy: np.ndarray) -> np.ndarray:
    """Order four (x, y) points as top-left, top-right, bottom-right, bottom-left."""
    pts = np.asarray(points_xy, np.float64).reshape(4, 2)
    centre = pts.mean(axis=0)
    angles = np.arctan2(pts[:, 1] - centre[1], pts[:, 0] - centre[0])
    pts = pts[np.argsort(angles)]  # counter-clockwise from -pi in image coords = TL, TR, BR, BL order
    start = int(np.argmin(pts.sum(axis=1)))  # top-left has the smallest x + y
    return np.roll(pts, -start, axis=0)


def polygon_mask(shape: tuple[int, int], polygon_xy: np.ndarray) -> np.ndarray:
    """Boolean mask of the pixels whose centres lie inside a polygon (x, y corners)."""
    mask = np.zeros(shape[:2], np.uint8)
    scale = 16  # cv2 fixed-point: sub-pixel corners
    pts = np.round(np.asarray(polygon_xy, np.float64) * scale).astype(np.int32).reshape(-1, 1, 2)
    cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def shrink_polygon(polygon_xy: np.ndarray, fraction: float) -> np.ndarray:
    """Move each corner towards the centroid by ``fraction`` of its distance."""
    pts = np.asarray(polygon_xy, np.float64)
    centre = pts.mean(axis=0)
    return centre + (pts - centre) * (1.0 - 2.0 * fraction)


def _line_intersection(l1: np.ndarray, l2: np.ndarray) -> np.ndarray | None:
    # lines as (vx, vy, x0, y0)
    (vx1, vy1, x1, y1), (vx2, vy2, x2, y2) = l1, l2
    det = vx1 * (-vy2) - vy1 * (-vx2)
    if abs(det) < 1e-9:
        return None
    t = ((x2 - x1) * (-vy2) - (y2 - y1) * (-vx2)) / det
    return np.array([x1 + t * vx1, y1 + t * vy1])


def _sample(image: np.ndarray, points_xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of a float32 image at (..., 2) (x, y) points; NaN outside the frame."""
    pts = np.asarray(points_xy, np.float32)
    flat = pts.reshape(-1, 2)
    n = len(flat)
    # cv2.remap takes maps below 32767 a side: lay the points out as rows of 4096
    cols = max(1, min(n, 4096))
    rows = -(-n // cols)
    grid = np.full((rows * cols, 2), -1.0e6, np.float32)  # padding samples fall outside: NaN
    grid[:n] = flat
    grid = grid.reshape(rows, cols, 2)
    values = cv2.remap(image, grid[..., 0], grid[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                       borderValue=np.nan)
    return values.reshape(-1)[:n].reshape(pts.shape[:-1])


def direct_exposure_level(values: np.ndarray, *, at_foot: bool = False) -> float | None:
    """Attenuation below which pixels are direct exposure (the unattenuated beam), or None.

    The direct-exposure mode is the lowest-attenuation peak of the histogram (128 bins over
    the 0.1-99.9 % range, smoothed over 5) when a valley below half its height separates it
    from the object, the object rises well above the valley again, and at least 20 % of the
    values lie above the valley. Returns the valley's lower bin edge, or with ``at_foot``
    the lower edge of the peak's foot: the first bin after the peak within 3 % of the peak's
    height above the valley (a conservative level: a plateau of thin tissue after the foot
    counts as object).

    The mode must also be narrow beside the object (:func:`_narrow_mode`). Without a flat
    field the open beam keeps the lens's vignetting and may spread as widely as a uniform body:
    then no direct exposure is found and the whole region counts as anatomy (the safe side:
    nothing is left out of the window or the clipping bound).

    Parameters
    ----------
    values : ndarray, float
        Finite attenuation-domain values (high = more attenuation), any shape.
    """
    levels = direct_exposure_levels(values)
    return None if levels is None else levels[1 if at_foot else 0]


def direct_exposure_levels(values: np.ndarray) -> tuple[float, float] | None:
    """Both levels of :func:`direct_exposure_level` from one histogram: ``(valley, foot)``, or None."""
    v = np.asarray(values, np.float32).ravel()
    if v.size < 16:
        return None
    a, b = np.percentile(v, [0.1, 99.9])
    if not b > a:
        return None
    hist, edges = np.histogram(v, bins=128, range=(float(a), float(b)))
    smooth = np.convolve(hist, np.ones(5) / 5, mode="same")
    low_part = smooth[:48]  # direct exposure sits at the low-attenuation end
    peak = int(np.argmax(low_part))
    beyond = smooth[peak:]
    if peak < 40 and beyond.size > 8:
        valley = peak + int(np.argmin(beyond[: max(8, beyond.size // 2)]))
        peak_height = smooth[peak]
        # a real direct-exposure mode: a peak with a clear valley above it and object beyond
        if (smooth[valley] < 0.5 * peak_height and smooth[valley:].max() > 2 * smooth[valley] + 1
                and np.count_nonzero(v >= edges[valley]) > 0.2 * v.size
                and _narrow_mode(v, float(edges[valley]))):
            # Thin soft tissue (the skin line of a limb) spreads as a low plateau from the
            # peak's foot to the object, and the plateau's deepest bin may lie far into it
            floor = smooth[valley] + 0.03 * (peak_height - smooth[valley])
            foot = peak + int(np.argmax(smooth[peak:valley + 1] <= floor))
            return float(edges[valley]), float(edges[foot])
    return None


#: The direct-exposure mode's spread (5-95 %) may be at most this share of the object's.
MAX_DIRECT_SPREAD_RATIO = 0.5


def _narrow_mode(values: np.ndarray, level: float) -> bool:
    """Is the part below ``level`` narrow beside the part above (a level plus noise, not anatomy)?

    The unattenuated beam is one level (the open beam, noise and what is left of the
    illumination pattern on it); the object spreads over its whole attenuation range. Measured
    on the 5 x 5 median of camera frames of real anatomy (the scenario corpus and its dense-area
    family): direct exposure spreads 0.08-0.44 of the object's 5-95 % range (up to 0.9 when
    10-15 % of anatomy mixes into the mode: then it all counts as anatomy, the safe side); a
    "mode" that is the whole anatomy below a dense area (shielding, undetected blades) spreads
    0.57-5.6, and taking it for direct exposure gave the dense area the value-of-interest
    window and showed the anatomy black.
    """
    below, above = values[values < level], values[values >= level]
    if below.size < 8 or above.size < 8:
        return False
    spread_below = float(np.subtract(*np.percentile(below, [95, 5])))
    spread_above = float(np.subtract(*np.percentile(above, [95, 5])))
    return spread_below <= MAX_DIRECT_SPREAD_RATIO * spread_above


def direct_exposure_mask(image: np.ndarray, mask: np.ndarray | None = None, *,
                         at_foot: bool = False) -> np.ndarray | None:
    """Pixels of direct exposure: beam that reached the detector without passing the patient.

    Below :func:`direct_exposure_level` (a narrow low-attenuation mode) AND outside the body's
    outline: connected, through such pixels, to the edge of ``mask`` or of the frame. Low
    pixels enclosed by the body (lung fields, air in the bowel, a lucent lesion) are attenuated
    anatomy, not direct exposure, whatever their level.

    Parameters
    ----------
    image : ndarray, float, (H, W)
        Attenuation-domain values (high = more attenuation); a regular subsample is fine.
    mask : ndarray, bool, (H, W), optional
        The region (screen or collimated field); None = the whole frame.
    at_foot : bool
        Use the conservative level (the foot of the mode, see :func:`direct_exposure_level`).

    Returns
    -------
    ndarray, bool, (H, W) or None
        None when there is no direct-exposure mode.
    """
    masks = direct_exposure_masks(image, mask, at_foot=(at_foot,))
    return None if masks is None else masks[0]


def direct_exposure_masks(image: np.ndarray, mask: np.ndarray | None = None, *,
                          at_foot: tuple[bool, ...] = (True, False)) -> tuple[np.ndarray, ...] | None:
    """:func:`direct_exposure_mask` at several levels from one smoothing and one histogram.

    One mask per entry of ``at_foot`` (in that order), or None when there is no direct-exposure
    mode.
    """
    inside = np.ones(image.shape, bool) if mask is None else mask
    # decided on a 5 x 5 median: the photon noise of a dense, starved area (shielding, blades)
    # would otherwise widen its mode until the whole anatomy looks narrow beside it
    smooth = cv2.medianBlur(np.nan_to_num(np.ascontiguousarray(image, np.float32)), 5)
    levels = direct_exposure_levels(smooth[inside])
    if levels is None:
        return None
    return tuple(_outside_the_body(smooth, inside, levels[1 if foot else 0]) for foot in at_foot)


def _outside_the_body(smooth: np.ndarray, inside: np.ndarray, level: float) -> np.ndarray:
    """Pixels of ``inside`` below ``level`` connected through such pixels to the exterior."""
    low = inside & (smooth < level)
    # the outside of the region and the frame's border seed the exterior; a low pixel is direct
    # exposure when it reaches them through low pixels (8-connected)
    exterior_or_low = np.pad((low | ~inside).astype(np.uint8), 1, constant_values=1)
    _, labels = cv2.connectedComponents(exterior_or_low, connectivity=8)
    return low & (labels[1:-1, 1:-1] == labels[0, 0])


def voi_window(values: np.ndarray, *, low_percentile: float = 0.5, high_percentile: float = 99.5,
               exclude_direct_exposure: bool = True) -> tuple[float, float]:
    """Values-of-interest window of attenuation-like values (high = more attenuation).

    Parameters
    ----------
    values : ndarray, float
        Attenuation-domain values inside the region (any shape; flattened).
    low_percentile, high_percentile : float
        Percentiles of the retained values mapped to 0 and 1.
    exclude_direct_exposure : bool
        Drop the lowest-attenuation mode (the unattenuated beam) when it is a distinct peak
        separated from the object by a histogram valley (:func:`direct_exposure_level`).

    Returns
    -------
    (lo, hi) : tuple of float
        The window; ``hi > lo`` always.

    Raises
    ------
    InputError
        No finite values.
    """
    v = np.asarray(values, np.float32).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        raise InputError("region", "no valid pixels inside the region for the value-of-interest window")
    if v.size > 2_000_000:
        v = v[:: v.size // 1_000_000]
    if exclude_direct_exposure:
        level = direct_exposure_level(v)
        if level is not None:
            v = v[v >= level]
    lo, hi = (float(x) for x in np.percentile(v, [low_percentile, high_percentile]))
    if not hi > lo:
        hi = lo + 1e-6
    return lo, hi


def rectify(image: np.ndarray, polygon_xy: np.ndarray, *, size: tuple[int, int] | None = None) -> np.ndarray:
    """Warp the quadrilateral onto an upright rectangle (perspective correction).

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, C)
    polygon_xy : ndarray, (4, 2)
        Corners (x, y), TL, TR, BR, BL.
    size : (height, width), optional
        Output size in pixels; default the mean lengths of opposite sides.

    Returns
    -------
    ndarray
        ``(height, width[, C])``, same dtype, bilinear interpolation.
    """
    poly = order_corners(polygon_xy)
    if size is None:
        width = 0.5 * (np.hypot(*(poly[1] - poly[0])) + np.hypot(*(poly[2] - poly[3])))
        height = 0.5 * (np.hypot(*(poly[3] - poly[0])) + np.hypot(*(poly[2] - poly[1])))
        size = (max(8, int(round(height))), max(8, int(round(width))))
    oh, ow = size
    dst = np.array([[0, 0], [ow - 1, 0], [ow - 1, oh - 1], [0, oh - 1]], np.float32)
    transform = cv2.getPerspectiveTransform(poly.astype(np.float32), dst)
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] > 4:
        return np.stack([rectify(arr[..., c], poly, size=size) for c in range(arr.shape[2])], axis=-1)
    return cv2.warpPerspective(arr, transform, (ow, oh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
