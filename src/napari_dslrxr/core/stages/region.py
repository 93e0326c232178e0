"""Object region and value-of-interest scaling (stage iii).

The camera sees the exposed scintillator screen as a bright, possibly keystoned
quadrilateral in a dark frame. :func:`detect_screen` finds it on a downsampled copy (log
scale, Otsu threshold, largest component with holes filled, convex hull, four corners from a
polygon approximation or the hull's extreme points), then refines each side by a robust line
fit through the full-contour points between the corners and intersects neighbouring sides.
The quadrilateral is shrunk slightly inward so the screen's soft rim is excluded.

:func:`voi_window` picks the values of interest inside the region: percentiles of the
histogram after excluding the direct-exposure mode (unattenuated beam), the standard CR/DR
"exposure recognition" step that makes the later gains image-independent.

:func:`rectify` optionally warps the quadrilateral onto a rectangle (perspective correction).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import InputError, ParameterError


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
        screen's edge; a brighter surround means the candidate is anatomy, not a screen
        (0 to 0.5).
    detect_collimation : bool
        For display radiographs (CR/DR, :func:`napari_dslrxr.core.pipeline.enhance_radiograph`
        and the contrast widget): find collimator blades with :func:`detect_collimation` and
        use the exposed field as the region. Camera frames ignore it (they use the screen).
    collimation_inset_px : float
        Move each found collimator edge this many pixels into the field (0 to 200), so the
        blade's penumbra (the soft inner side of the edge) counts as outside.
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
        "help": "user override of the screen corners [[x, y], ...] (4 points, px, TL TR BR BL); [] = detect"})
    min_border_contrast_sigma: float = field(default=5.0, metadata={
        "help": "border contrast (screen inside minus surround) that counts as evidence, in pixel-noise sigmas",
        "unit": "sigma", "min": 3.0, "max": 100.0})
    min_border_coverage: float = field(default=0.7, metadata={
        "help": "share of the screen border's length that must show that contrast (else the whole frame is used)",
        "unit": "fraction", "min": 0.3, "max": 1.0})
    max_bright_surround: float = field(default=0.03, metadata={
        "help": "largest share of the surround as bright as the screen's edge (else the whole frame is used)",
        "unit": "fraction", "min": 0.0, "max": 0.5})
    detect_collimation: bool = field(default=True, metadata={
        "help": "display radiographs only: find collimator blades and use the exposed field as the region"})
    collimation_inset_px: float = field(default=10.0, metadata={
        "help": "move each found collimator edge this far into the field (drops the blade's penumbra)",
        "unit": "px", "min": 0.0, "max": 200.0})


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


def _four_corners(hull: np.ndarray) -> np.ndarray:
    """Four corners of a convex hull: polygon approximation, else extreme points."""
    perimeter = cv2.arcLength(hull, True)
    for eps in (0.01, 0.02, 0.03, 0.05):
        approx = cv2.approxPolyDP(hull, eps * perimeter, True)
        if len(approx) == 4:
            return approx.reshape(4, 2).astype(np.float64)
    pts = hull.reshape(-1, 2).astype(np.float64)
    s, d = pts.sum(axis=1), pts[:, 0] - pts[:, 1]
    return np.array([pts[np.argmin(s)], pts[np.argmax(d)], pts[np.argmax(s)], pts[np.argmin(d)]])


def _refine_corners(contour: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Fit a line to the contour points of each side (away from corners); intersect neighbours."""
    pts = contour.reshape(-1, 2).astype(np.float64)
    corners = order_corners(corners)
    lines = []
    for i in range(4):
        a, b = corners[i], corners[(i + 1) % 4]
        ab = b - a
        length = np.hypot(*ab)
        if length < 4:
            return corners
        t = ((pts - a) @ ab) / length**2
        dist = np.abs((pts - a) @ np.array([-ab[1], ab[0]])) / length
        sel = (t > 0.1) & (t < 0.9) & (dist < max(2.0, 0.02 * length))
        if np.count_nonzero(sel) < 5:
            return corners
        lines.append(cv2.fitLine(pts[sel].astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel())
    refined = []
    for i in range(4):
        p = _line_intersection(lines[(i - 1) % 4], lines[i])
        if p is None or np.hypot(*(p - corners[i])) > 0.1 * np.ptp(corners, axis=0).max():
            return corners
        refined.append(p)
    return np.array(refined)


def _noise_map(small: np.ndarray, tile_px: int = 16) -> np.ndarray:
    """Pixel-noise sigma per ``tile_px`` tile (from the finest diagonal Haar band), at ``small``'s size.

    The diagonal detail of 2 x 2 blocks carries the noise and little of a smooth image; the
    median per tile (1.4826 MAD of a zero-mean band) follows signal-dependent (Poisson) noise.
    """
    h, w = (small.shape[0] // 2) * 2, (small.shape[1] // 2) * 2
    d = 0.5 * ((small[0:h:2, 0:w:2] - small[0:h:2, 1:w:2]) - (small[1:h:2, 0:w:2] - small[1:h:2, 1:w:2]))
    np.abs(d, out=d)
    b = max(2, tile_px // 2)
    bh, bw = max(1, d.shape[0] // b), max(1, d.shape[1] // b)
    tiles = d[: bh * b, : bw * b].reshape(bh, min(b, d.shape[0]), bw, min(b, d.shape[1]))
    sigma = np.median(tiles.transpose(0, 2, 1, 3).reshape(bh, bw, -1), axis=2) * np.float32(1.4826)
    # a flat (noise-free) tile must not give infinite contrast: floor at 1e-3 of the median level
    floor = max(1e-3 * float(np.median(small)), 1e-9)
    return cv2.resize(np.maximum(sigma, floor).astype(np.float32), (small.shape[1], small.shape[0]),
                      interpolation=cv2.INTER_NEAREST)


def _candidate_corners(small: np.ndarray, scaled: np.ndarray, threshold: float) -> np.ndarray | None:
    """Four corners (small-image x, y) of the largest component above ``threshold`` in ``scaled``."""
    binary = (scaled > threshold).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, kernel)
    binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, kernel)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    if n <= 1:
        return None
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    component = (labels == largest).astype(np.uint8)
    # The log-scale Otsu split sits low on the blurred screen edge; re-threshold at half way
    # between the unexposed level and the screen rim (the 50 % point of the edge profile).
    ring = component.astype(bool) & ~cv2.erode(component, np.ones((9, 9), np.uint8)).astype(bool)
    outside = ~cv2.dilate(component, np.ones((9, 9), np.uint8)).astype(bool)
    if np.count_nonzero(ring) > 16 and np.count_nonzero(outside) > 16:
        rim_level = float(np.percentile(small[ring], 75))
        edge_level = 0.5 * (rim_level + float(np.median(small[outside])))
        near = cv2.dilate(component, np.ones((9, 9), np.uint8))
        refined = ((small > edge_level) & near.astype(bool)).astype(np.uint8)
        n2, labels2, stats2, _ = cv2.connectedComponentsWithStats(refined, connectivity=8)
        if n2 > 1:
            component = (labels2 == 1 + int(np.argmax(stats2[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
    contours, _ = cv2.findContours(component, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    contour = max(contours, key=cv2.contourArea)
    hull = cv2.convexHull(contour)
    return _refine_corners(contour, _four_corners(hull))


#: Border points averaged for one contrast measurement (px along the border).
_BORDER_RUN_PX = 9


def screen_evidence(small: np.ndarray, noise: np.ndarray, corners: np.ndarray,
                    params: RegionParams) -> dict:
    """How strongly the image supports a screen quadrilateral (all on the analysis copy).

    Along each side of the quadrilateral not lying on the frame's edge, at points every
    pixel, the mean of the image 2-6 px inside minus the mean 2-6 px outside, averaged over
    9 px along the border and divided by that average's noise (from the local pixel-noise
    sigma), is the border contrast. The screen is supported when that contrast
    reaches ``min_border_contrast_sigma`` on at least ``min_border_coverage`` of the border's
    length, and the surround (pixels beyond a margin of 4 px + 3 % of the screen's size) is
    darker: at most ``max_bright_surround`` of it above the level half way between the
    surround's median and the screen's rim. A border point counts only when the image just
    outside it is close to the surround's level (within a quarter of the step), so a step from
    bright to medium (direct exposure beside a limb) is no evidence.

    Returns
    -------
    dict
        ``accepted`` (bool), ``border_coverage``, ``border_contrast_sigma`` (median over the
        border), ``bright_surround``, ``open_sides`` (the frame edges that cut the screen),
        ``open_side_index`` (their sides, 0 = top-left to top-right, clockwise) and, when not
        accepted, ``reason``.
    """
    h, w = small.shape
    corners = order_corners(corners)
    inward_offsets = np.arange(2.0, 7.0)
    centre = corners.mean(axis=0)
    quad = polygon_mask((h, w), corners).astype(np.uint8)
    size = float(np.sqrt(max(quad.sum(), 1)))
    margin = int(round(4 + 0.03 * size))
    kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    surround = ~cv2.dilate(quad, kernel).astype(bool)
    rim = quad.astype(bool) & ~cv2.erode(quad, kernel).astype(bool)
    surround_level = float(np.median(small[surround])) if surround.any() else float(small.min())
    ratios, open_sides, total_points = [], [], 0
    for i in range(4):
        a, b = corners[i], corners[(i + 1) % 4]
        length = float(np.hypot(*(b - a)))
        if length < 4:
            continue
        direction = (b - a) / length
        normal = np.array([-direction[1], direction[0]])
        if normal @ (centre - a) < 0:
            normal = -normal  # points into the screen
        t = np.arange(0.05 * length, 0.95 * length, 1.0)
        points = a + t[:, None] * direction
        # a side along the frame's edge is open: the frame cut the screen there, no surround to see
        distances = np.stack([points[:, 0], points[:, 1], w - 1 - points[:, 0], h - 1 - points[:, 1]])
        nearest = int(np.argmin(np.median(distances, axis=1)))
        if np.median(distances[nearest]) < 3.0:
            open_sides.append((i, ("left", "top", "right", "bottom")[nearest]))
            continue
        inside = _sample(small, points[:, None, :] + inward_offsets[None, :, None] * normal).mean(axis=1)
        outside = _sample(small, points[:, None, :] - inward_offsets[None, :, None] * normal).mean(axis=1)
        sigma = _sample(noise, points)
        valid = np.isfinite(inside) & np.isfinite(outside) & np.isfinite(sigma)
        # the step must go down to the surround's level: a step from bright to medium (direct
        # exposure beside a limb, a lung beside the mediastinum) is anatomy, not a screen's edge
        to_surround = (outside - surround_level) <= 0.25 * (inside - surround_level)
        total_points += len(points)
        # the step averaged over 9 px along the border and 5 px across on each side: its noise is
        # sigma sqrt(2 / 45) for pixel noise sigma
        step = np.where(valid, inside - outside, 0.0)
        step = np.convolve(step, np.ones(_BORDER_RUN_PX) / _BORDER_RUN_PX, mode="same")
        step_sigma = np.maximum(sigma, 1e-12) * np.sqrt(2.0 / (_BORDER_RUN_PX * len(inward_offsets)))
        ratios.append(np.where(valid & to_surround, step / np.where(np.isfinite(step_sigma), step_sigma, np.inf), 0.0))
    evidence: dict = {"open_sides": [edge for _, edge in open_sides], "open_side_index": [i for i, _ in open_sides]}
    if not ratios or total_points < 16:
        evidence.update(accepted=False, border_coverage=0.0, border_contrast_sigma=0.0, bright_surround=None,
                        reason="no side of the candidate lies inside the frame (no border to test)")
        return evidence
    ratio = np.concatenate(ratios)
    coverage = float(np.mean(ratio >= params.min_border_contrast_sigma))
    evidence["border_coverage"] = round(coverage, 3)
    evidence["border_contrast_sigma"] = round(float(np.median(ratio)), 2)
    bright = None
    if np.count_nonzero(surround) >= 16 and np.count_nonzero(rim) >= 16:
        edge_level = 0.5 * (surround_level + float(np.median(small[rim])))
        bright = float(np.mean(small[surround] > edge_level))
    evidence["bright_surround"] = None if bright is None else round(bright, 4)
    reasons = []
    if coverage < params.min_border_coverage:
        reasons.append(f"border contrast >= {params.min_border_contrast_sigma:g} sigma on only "
                       f"{100 * coverage:.0f} % of its length (needs {100 * params.min_border_coverage:.0f} %)")
    if bright is not None and bright > params.max_bright_surround:
        reasons.append(f"{100 * bright:.1f} % of the surround is as bright as the screen's edge "
                       f"(at most {100 * params.max_bright_surround:.1f} %)")
    evidence["accepted"] = not reasons
    if reasons:
        evidence["reason"] = "; ".join(reasons)
    return evidence


def detect_screen(image: np.ndarray, params: RegionParams | None = None, *,
                  illumination: np.ndarray | None = None) -> Region:
    """Find the exposed screen quadrilateral in a (flat-fielded) frame, only on strong evidence.

    A candidate quadrilateral comes from the bright part of a log-scaled, downsampled copy
    (Otsu threshold, largest component, convex hull, four corners refined by line fits). It
    is accepted only when :func:`screen_evidence` finds a border of many noise sigmas along
    most of its length and a darker surround; otherwise the whole frame is the region, so
    anatomy is never blanked to satisfy the shape prior (a camera that framed only part of
    the screen sees no surround at all).

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, 3)
        Linear intensity (counts); colour is summed over channels.
    params : RegionParams, optional
    illumination : ndarray, (H, W[, C]), optional
        The flat-field denominator the image was divided by: the evidence is judged on the
        light the camera saw (image x illumination), where the unexposed surround is dark (the
        flat-field division would lift it towards the screen's level).

    Returns
    -------
    Region
        Mask and corners at full resolution; the whole frame when detection is disabled or
        the evidence is too weak. ``evidence`` records the scores and, if nothing was
        accepted, the reason.

    Raises
    ------
    ParameterError
        A user polygon that is not 4 (x, y) points.
    """
    params = params or RegionParams()
    arr = np.asarray(image)
    h, w = arr.shape[:2]
    whole = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64)

    def nothing(reason: str, **extra) -> Region:
        return Region(np.ones((h, w), bool), whole, detected=False, evidence={"accepted": False, **extra,
                                                                               "reason": reason})

    if params.polygon_xy:
        poly = np.asarray(params.polygon_xy, np.float64)
        if poly.shape != (4, 2):
            raise ParameterError(f"region.polygon_xy: expected 4 [x, y] points, got shape {poly.shape}")
        poly = order_corners(poly)
        return Region(polygon_mask((h, w), poly), poly, detected=False, evidence={"source": "user polygon"})
    if not params.enabled:
        return Region(np.ones((h, w), bool), whole, detected=False, evidence={"source": "detection disabled"})
    factor = max(1.0, max(h, w) / float(params.analysis_size_px))
    size = (max(8, round(w / factor)), max(8, round(h / factor)))

    def shrink(a: np.ndarray) -> np.ndarray:
        a = a if a.dtype == np.float32 else a.astype(np.float32)
        # downsample first (area average), then sum the colour channels: no full-size copy
        return cv2.resize(a, size, interpolation=cv2.INTER_AREA) if factor > 1 else a.copy()

    small = shrink(arr)
    if illumination is not None:
        light = shrink(np.asarray(illumination))
        if light.ndim == 2 and small.ndim == 3:
            light = light[..., None]
        small = small * light if light.shape[:2] == small.shape[:2] else small
    if small.ndim == 3:
        small = small.sum(axis=2)
    noise = _noise_map(small)
    small = cv2.GaussianBlur(small, (0, 0), 1.0)
    top = float(np.percentile(small, 99.5))
    if not top > 0:
        return nothing("the frame holds no light")
    # log scale: attenuated object (dark inside the screen) stays above the unexposed frame
    logged = np.log(np.maximum(small, 0) + 0.005 * top)
    lo, hi = float(logged.min()), float(logged.max())
    if hi - lo < 1e-6:
        return nothing("the frame is uniform")
    scaled = np.round((logged - lo) / (hi - lo) * 255).astype(np.uint8)
    high, _ = cv2.threshold(scaled, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    # Two candidates: the bright class of a log-scale Otsu split, and everything above the
    # dark class of a second split below it (when a large direct-exposure area takes the
    # bright class, the screen is the union of the two brighter classes)
    thresholds = [high]
    darker = scaled[scaled <= high]
    if darker.size > 16 and np.ptp(darker) > 2:
        low, _ = cv2.threshold(darker.reshape(1, -1), 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        if low < high:
            thresholds.append(low)
    best, first = None, None
    for threshold in thresholds:
        corners = _candidate_corners(small, scaled, threshold)
        if corners is None:
            continue
        evidence = screen_evidence(small, noise, corners, params)
        area = cv2.contourArea(order_corners(corners).astype(np.float32))
        if first is None:
            first = (corners, evidence)
        # the lower threshold wins only when it adds a real area (not just the blurred rim)
        if evidence["accepted"] and (best is None or area > 1.1 * best[2]):
            best = (corners, evidence, area)
    if first is None:
        return nothing("no bright area")
    corners, evidence = (best[0], best[1]) if best is not None else first
    # pixel-centre coordinates of the small image -> full resolution
    corners = (corners + 0.5) * np.array([w / small.shape[1], h / small.shape[0]]) - 0.5
    corners = order_corners(corners)
    if not evidence["accepted"]:
        evidence.pop("open_side_index")
        return nothing(evidence.pop("reason"), **{k: v for k, v in evidence.items() if k != "accepted"},
                       candidate_xy=corners.round(1).tolist())
    poly = shrink_polygon(corners, params.shrink_fraction)
    # a side the frame cut has no rim to drop: put it on (or beyond) the frame's edge
    edge_value = {"left": (0, -0.5, min), "top": (1, -0.5, min), "right": (0, w - 0.5, max), "bottom": (1, h - 0.5, max)}
    for index, edge in zip(evidence.pop("open_side_index"), evidence["open_sides"], strict=True):
        axis, value, pick = edge_value[edge]
        for corner in (index, (index + 1) % 4):
            poly[corner, axis] = pick(corners[corner, axis], value)
    return Region(polygon_mask((h, w), poly), poly, detected=True, evidence=evidence)


def direct_exposure_level(values: np.ndarray, *, at_foot: bool = False) -> float | None:
    """Attenuation below which pixels are direct exposure (the unattenuated beam), or None.

    The direct-exposure mode is the lowest-attenuation peak of the histogram (128 bins over
    the 0.1-99.9 % range, smoothed over 5) when a valley below half its height separates it
    from the object, the object rises well above the valley again, and at least 20 % of the
    values lie above the valley. Returns the valley's lower bin edge, or with ``at_foot``
    the lower edge of the peak's foot: the first bin after the peak within 3 % of the peak's
    height above the valley (a conservative level: a plateau of thin tissue after the foot
    counts as object).

    Parameters
    ----------
    values : ndarray, float
        Finite attenuation-domain values (high = more attenuation), any shape.
    """
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
                and np.count_nonzero(v >= edges[valley]) > 0.2 * v.size):
            if not at_foot:
                return float(edges[valley])
            # Thin soft tissue (the skin line of a limb) spreads as a low plateau from the
            # peak's foot to the object, and the plateau's deepest bin may lie far into it
            floor = smooth[valley] + 0.03 * (peak_height - smooth[valley])
            foot = peak + int(np.argmax(smooth[peak:valley + 1] <= floor))
            return float(edges[foot])
    return None


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


#: Sides of the frame a collimator blade can cover: the Hough angle range's centre (radians,
#: skimage convention x cos(theta) + y sin(theta) = rho with x = column, y = row) and the sign of
#: the outward normal (towards the blade, away from the exposed field).
_BLADE_SIDES = {"left": (0.0, -1.0), "right": (0.0, 1.0), "top": (np.pi / 2, -1.0), "bottom": (np.pi / 2, 1.0)}


def _line_samples(shape: tuple[int, int], theta: float, rho: float, step_px: float = 1.0) -> np.ndarray:
    """(x, y) points every ``step_px`` along the line x cos(theta) + y sin(theta) = rho inside a frame."""
    h, w = shape
    c, s = np.cos(theta), np.sin(theta)
    if abs(c) >= abs(s):  # near-vertical: parametrise by row
        y = np.arange(0.0, h - 1.0 + 1e-9, step_px * abs(c))
        x = (rho - y * s) / c
    else:
        x = np.arange(0.0, w - 1.0 + 1e-9, step_px * abs(s))
        y = (rho - x * c) / s
    keep = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    return np.column_stack([x[keep], y[keep]])


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


def _blade_score(small: np.ndarray, grid_xy: tuple[np.ndarray, np.ndarray], theta: float, rho: float,
                 outward: float, min_step: float) -> float:
    """Evidence (0 = none) that a collimator blade lies beyond a line on the normalised small image.

    A blade shades a band between the line and the frame border: the band is brighter than
    the field just inside the line along most of the line's length, and nearly uniform
    compared with the field (no anatomy under the blade).
    """
    h, w = small.shape
    normal = outward * np.array([np.cos(theta), np.sin(theta)])
    points = _line_samples((h, w), theta, rho)
    if len(points) < 0.2 * (h if abs(np.cos(theta)) > abs(np.sin(theta)) else w):
        return 0.0
    offsets = np.arange(2.0, 7.0)
    # samples beyond the frame are NaN: a profile counts only when all of it is inside
    out = _sample(small, points[:, None, :] + offsets[None, :, None] * normal).mean(axis=1)
    inside = _sample(small, points[:, None, :] - offsets[None, :, None] * normal).mean(axis=1)
    step = out - inside
    step = step[np.isfinite(step)]
    if step.size < 8:
        return 0.0
    coverage = float(np.mean(step > min_step))
    xx, yy = grid_xy
    signed = outward * (xx * np.cos(theta) + yy * np.sin(theta) - rho)
    band, field_px = small[signed > 3.0], small[signed < -3.0]
    if band.size < 2 * len(points) or field_px.size < band.size // 4:
        return 0.0
    band_lo, band_mid, band_hi = np.percentile(band, [10, 50, 90])
    field_lo, field_mid, field_hi = np.percentile(field_px, [10, 50, 90])
    uniform = (band_hi - band_lo) < 0.5 * (field_hi - field_lo)
    brighter = band_mid > field_mid + min_step
    if coverage < 0.6 or not uniform or not brighter:
        return 0.0
    return coverage * float(np.median(step))


def _refine_blade(image: np.ndarray, theta: float, rho: float, outward: float,
                  half_width_px: float) -> tuple[float, float] | None:
    """Move a coarse blade line onto the steepest outward step of the full-resolution image.

    Profiles across the line, every few pixels along it; on each, the sub-pixel position of
    the largest outside-minus-inside derivative; a robust (Huber) line through those points.
    Returns ``(theta, rho)`` or None when too few profiles show the step.
    """
    h, w = image.shape
    normal = outward * np.array([np.cos(theta), np.sin(theta)])
    points = _line_samples((h, w), theta, rho, step_px=max(2.0, min(h, w) / 400.0))
    offsets = np.arange(-half_width_px, half_width_px + 1.0)
    profiles = _sample(image, points[:, None, :] + offsets[None, :, None] * normal)
    valid = np.all(np.isfinite(profiles), axis=1)
    if np.count_nonzero(valid) < 8:
        return None
    points = points[valid]
    profiles = cv2.GaussianBlur(profiles[valid].astype(np.float32), (1, 5), 0)  # along the line
    slope = np.diff(profiles, axis=1)  # rises towards the blade (outward)
    best = np.argmax(slope, axis=1)
    strength = slope[np.arange(len(best)), best]
    keep = (strength > 0.25 * np.median(strength)) & (best > 0) & (best < slope.shape[1] - 1)
    if np.count_nonzero(keep) < 8:
        return None
    i = np.arange(len(best))[keep]
    b = best[keep]
    left, mid, right = slope[i, b - 1], slope[i, b], slope[i, b + 1]
    denominator = left - 2 * mid + right
    shift = np.where(np.abs(denominator) > 1e-12, 0.5 * (left - right) / np.where(denominator == 0, 1, denominator), 0)
    # slope index k lies between offsets k and k + 1
    position = offsets[0] + b + 0.5 + np.clip(shift, -0.5, 0.5)
    edge_xy = points[keep] + position[:, None] * normal
    vx, vy, x0, y0 = cv2.fitLine(edge_xy.astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
    new_theta = float(np.arctan2(vx, -vy))  # normal of the direction (vx, vy)
    if np.cos(new_theta - theta) < 0:
        new_theta -= np.pi * np.sign(new_theta - theta)
    return new_theta, float(x0 * np.cos(new_theta) + y0 * np.sin(new_theta))


def detect_collimation(image: np.ndarray, *, analysis_size_px: int = 512, max_tilt_deg: float = 10.0,
                       min_step: float = 0.08, inset_px: float = 0.0) -> Region:
    """Find the exposed field of a collimated radiograph (display orientation, bright = unexposed).

    Collimator blades leave straight-edged bands along the frame's sides where the plate got
    (almost) no radiation: after MONOCHROME1 inversion they are bright and nearly uniform. On a
    copy downsampled to ``analysis_size_px``, normalised to its 0.5-99.5 % range, each side's
    candidate edges are the peaks of a straight-line Hough transform
    (:func:`skimage.transform.hough_line`) of the Canny edges whose gradient points towards
    that side, limited to ``max_tilt_deg`` from the side's axis. A candidate is a blade when
    the band beyond it is brighter than the field just inside along at least 60 % of its
    length (by ``min_step``), brighter than the field's median, and more uniform than the field
    (10-90 % spread below half the field's). The best blade of each side is then moved onto
    the steepest step of the full-resolution image (sub-pixel, robust line fit). The field is
    the intersection of the half-planes inside the found blades; absent blades leave the
    field open to the frame border.

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, 3), any real dtype
        Radiograph in display orientation (higher = brighter = less exposure); colour is
        averaged.
    analysis_size_px : int
        Longest side (px) of the downsampled copy used for the search (64 to 4096).
    max_tilt_deg : float
        Largest blade tilt from the frame's axes searched (degrees, 0 to 30).
    min_step : float
        Smallest brightness step across a blade edge, as a fraction of the image's
        0.5-99.5 % range.
    inset_px : float
        Move each found edge this many pixels into the field (>= 0): 0 keeps the edge at its
        steepest point; a few pixels drop the blade's penumbra.

    Returns
    -------
    Region
        ``mask`` (bool, (H, W)) of the exposed field and ``polygon_xy`` (float64, (4, 2), x, y
        in pixels, TL, TR, BR, BL; corners on an open side lie half a pixel outside the frame
        and may lie further out when a blade is tilted). ``detected`` is False, with an
        all-true mask and the frame's corners, when no blade is found.

    Raises
    ------
    ParameterError
        Out-of-range parameters.
    InputError
        Not a 2-D (or 2-D colour) image.
    """
    from skimage.feature import canny
    from skimage.transform import hough_line, hough_line_peaks

    if not 64 <= analysis_size_px <= 4096:
        raise ParameterError(f"analysis_size_px: must be 64 to 4096, got {analysis_size_px}")
    if not 0 <= max_tilt_deg <= 30:
        raise ParameterError(f"max_tilt_deg: must be 0 to 30 degrees, got {max_tilt_deg}")
    if not 0 < min_step < 1:
        raise ParameterError(f"min_step: must be between 0 and 1, got {min_step}")
    if not inset_px >= 0:
        raise ParameterError(f"inset_px: must be >= 0, got {inset_px}")
    arr = np.asarray(image)
    if arr.ndim == 3:
        arr = arr.mean(axis=2)
    if arr.ndim != 2 or min(arr.shape) < 16:
        raise InputError("image", f"expected a 2-D radiograph at least 16 px a side, got shape {np.shape(image)}")
    h, w = arr.shape
    whole = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64)
    nothing = Region(np.ones((h, w), bool), whole, detected=False)
    full = np.nan_to_num(arr.astype(np.float32, copy=False), nan=0.0, posinf=0.0, neginf=0.0)
    lo, hi = (float(v) for v in np.percentile(full[::4, ::4], [0.5, 99.5]))
    if not hi > lo:
        return nothing
    full = (full - np.float32(lo)) * np.float32(1.0 / (hi - lo))
    factor = max(1.0, max(h, w) / float(analysis_size_px))
    small = cv2.resize(full, (max(16, round(w / factor)), max(16, round(h / factor))),
                       interpolation=cv2.INTER_AREA) if factor > 1 else full.copy()
    sh, sw = small.shape
    scale = np.array([w / sw, h / sh])
    edges = canny(small, sigma=1.5, low_threshold=0.5 * min_step, high_threshold=min_step)
    gy, gx = np.gradient(cv2.GaussianBlur(small, (0, 0), 1.5))
    magnitude = np.hypot(gx, gy) + 1e-12
    tilt = np.deg2rad(max_tilt_deg)
    grid_xy = np.meshgrid(np.arange(sw), np.arange(sh))  # (x, y) pixel indices, once for all candidates
    lines = {}
    for side, (axis_theta, outward) in _BLADE_SIDES.items():
        normal_gradient = (gx if axis_theta == 0 else gy) * outward  # rises towards the blade
        side_edges = edges & (normal_gradient > 0.8 * magnitude)
        if np.count_nonzero(side_edges) < 0.2 * min(sh, sw):
            continue
        thetas = axis_theta + np.linspace(-tilt, tilt, 2 * int(np.ceil(max_tilt_deg * 2)) + 1)
        accumulator, angles, distances = hough_line(side_edges, theta=thetas)
        length = sh if axis_theta == 0 else sw
        _, peak_angles, peak_rhos = hough_line_peaks(accumulator, angles, distances, num_peaks=6,
                                                     threshold=0.2 * length, min_distance=5)
        best = (0.0, None)
        for theta, rho in zip(peak_angles, peak_rhos):
            score = _blade_score(small, grid_xy, float(theta), float(rho), outward, min_step)
            if score > best[0]:
                best = (score, (float(theta), float(rho)))
        if best[1] is None:
            continue
        theta, rho = best[1]
        # small-image pixel centres -> full resolution: p_full = (p_small + 0.5) * scale - 0.5
        nx, ny = np.cos(theta) / scale[0], np.sin(theta) / scale[1]
        norm = np.hypot(nx, ny)
        full_theta = float(np.arctan2(ny, nx))
        full_rho = float((rho + 0.5 * (np.cos(theta) + np.sin(theta))) / norm - 0.5 * (nx + ny) / norm)
        refined = _refine_blade(full, full_theta, full_rho, outward, half_width_px=2.0 * factor + 4.0)
        theta, rho = refined if refined is not None else (full_theta, full_rho)
        lines[side] = (theta, rho - outward * inset_px)
    if not lines:
        return nothing
    border = {"left": (0.0, -0.5), "right": (0.0, w - 0.5), "top": (np.pi / 2, -0.5), "bottom": (np.pi / 2, h - 0.5)}
    as_direction = {}
    for side in _BLADE_SIDES:
        theta, rho = lines.get(side, border[side])
        c, s = np.cos(theta), np.sin(theta)
        as_direction[side] = np.array([-s, c, rho * c, rho * s])  # (vx, vy, x0, y0)
    corners = []
    for first, second in (("left", "top"), ("top", "right"), ("right", "bottom"), ("bottom", "left")):
        point = _line_intersection(as_direction[first], as_direction[second])
        if point is None:
            return nothing
        corners.append(point)
    poly = np.array(corners)
    return Region(polygon_mask((h, w), poly), poly, detected=True)
