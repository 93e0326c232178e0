"""The exposed screen in a camera frame, found only on strong evidence.

The camera sees the exposed scintillator screen as a bright, possibly keystoned
quadrilateral. :func:`detect_screen` proposes candidates on a downsampled copy (log scale,
Otsu threshold, largest component, convex hull, four corners from a polygon approximation
or the hull's extreme points, each side refined by a robust line fit through the contour)
and accepts one only when :func:`screen_evidence` finds a border of many noise sigmas along
most of its length, falling to the level of a darker surround. Otherwise the whole frame is
the region: a frame that shows only anatomy (the camera framed part of the screen) must not
be blanked to satisfy the shape prior. The accepted quadrilateral is shrunk slightly inward
so the screen's soft rim is excluded (not on sides the frame cut).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from ..errors import ParameterError
from ..robust import MAD_TO_SIGMA
from .region import Region, RegionParams, _line_intersection, _sample, order_corners, polygon_mask, shrink_polygon


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
    sigma = np.median(tiles.transpose(0, 2, 1, 3).reshape(bh, bw, -1), axis=2) * np.float32(MAD_TO_SIGMA)
    # a flat (noise-free) tile must not give infinite contrast: floor at 1e-3 of the median level
    floor = max(1e-3 * float(np.median(small)), 1e-9)
    return cv2.resize(np.maximum(sigma, floor).astype(np.float32), (small.shape[1], small.shape[0]),
                      interpolation=cv2.INTER_NEAREST)


#: Frame edges in the order of their outward directions below.
_FRAME_EDGES = ("left", "top", "right", "bottom")
_EDGE_OUTWARD = np.array([[-1.0, 0.0], [0.0, -1.0], [1.0, 0.0], [0.0, 1.0]])


def _frame_cuts(component: np.ndarray, corners: np.ndarray) -> list[str]:
    """The frame edges beyond which a bright component goes on where its four-corner fit left
    it out: a piece of the component outside the fitted quadrilateral (grown by a pixel), of
    at least 16 px and 0.2 % of the component, that touches the frame edge. A corner that
    merely grazes the edge leaves no such piece; a screen the frame cut at a corner (a
    pentagon, which the fit turns into a quadrilateral with a side across the screen) does."""
    inside = cv2.dilate(polygon_mask(component.shape, corners).astype(np.uint8), np.ones((3, 3), np.uint8))
    left_out = (component.astype(bool) & ~inside.astype(bool)).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(left_out, connectivity=8)
    min_area = max(16.0, 0.002 * np.count_nonzero(component))
    cuts = set()
    for label in range(1, n):
        if stats[label, cv2.CC_STAT_AREA] >= min_area:
            piece = labels == label
            lines = (piece[:, 0], piece[0], piece[:, -1], piece[-1])
            cuts.update(edge for edge, line in zip(_FRAME_EDGES, lines, strict=True) if line.any())
    return [edge for edge in _FRAME_EDGES if edge in cuts]


def _candidate_corners(small: np.ndarray, scaled: np.ndarray, threshold: float) -> tuple[np.ndarray, list[str]] | None:
    """Four corners (small-image x, y) of the largest component above ``threshold`` in ``scaled``,
    and the frame edges that component runs off (:func:`_frame_cuts`)."""
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
    corners = _refine_corners(contour, _four_corners(hull))
    return corners, _frame_cuts(component, corners)


#: Border points averaged for one contrast measurement (px along the border).
_BORDER_RUN_PX = 9


def screen_evidence(small: np.ndarray, noise: np.ndarray, corners: np.ndarray,
                    params: RegionParams, flat_lit: np.ndarray | None = None,
                    frame_cuts: Sequence[str] = ()) -> dict:
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

    A side is open (the frame cut the screen there; :func:`_screen_polygon` takes it to the
    frame's edge) when it lies along a frame edge (median distance under 3 px: no border to
    test, left out of the border test), or when it faces a frame edge the bright component
    it came from runs off (``frame_cuts``, :func:`_frame_cuts`): the screen goes on beyond
    that edge, wherever the fit put the side (a four-corner fit of a screen the frame cut at
    a corner, a pentagon, may put it across the screen inside the frame). A corner merely
    grazing the frame's edge opens nothing.

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
    outward = np.zeros((4, 2))
    for i in range(4):
        a, b = corners[i], corners[(i + 1) % 4]
        length = float(np.hypot(*(b - a)))
        if length < 4:
            continue
        direction = (b - a) / length
        normal = np.array([-direction[1], direction[0]])
        if normal @ (centre - a) < 0:
            normal = -normal  # points into the screen
        outward[i] = -normal
        t = np.arange(0.05 * length, 0.95 * length, 1.0)
        points = a + t[:, None] * direction
        # a side along the frame's edge is open: the frame cut the screen there, no surround to see
        distances = np.stack([points[:, 0], points[:, 1], w - 1 - points[:, 0], h - 1 - points[:, 1]])
        nearest = int(np.argmin(np.median(distances, axis=1)))
        if np.median(distances[nearest]) < 3.0:
            open_sides.append((i, _FRAME_EDGES[nearest]))
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
        run = min(_BORDER_RUN_PX, len(step))  # a side shorter than the run: one average
        step = np.convolve(step, np.ones(run) / run, mode="same")
        step_sigma = np.maximum(sigma, 1e-12) * np.sqrt(2.0 / (run * len(inward_offsets)))
        ratios.append(np.where(valid & to_surround, step / np.where(np.isfinite(step_sigma), step_sigma, np.inf), 0.0))
    for edge in frame_cuts:
        # the side that faces a frame edge the screen runs off is open, wherever the fit put it
        # (its border is still tested: the part of it inside the frame is seen)
        side = int(np.argmax(outward @ _EDGE_OUTWARD[_FRAME_EDGES.index(edge)]))
        if side not in [i for i, _ in open_sides] and outward[side] @ _EDGE_OUTWARD[_FRAME_EDGES.index(edge)] > np.sqrt(0.5):
            open_sides.append((side, edge))
    open_sides.sort()
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
    lit = None
    if flat_lit is not None and surround.any():
        # the open beam reached the surround: what is dark there in the frame is an object in the
        # beam (anatomy, shielding, blades), not the unexposed room beyond a screen's edge
        lit = float(np.mean(flat_lit[surround]))
        evidence["flat_lit_surround"] = round(lit, 4)
    reasons = []
    if coverage < params.min_border_coverage:
        reasons.append(f"border contrast >= {params.min_border_contrast_sigma:g} sigma on only "
                       f"{100 * coverage:.0f} % of its length (needs {100 * params.min_border_coverage:.0f} %)")
    if bright is not None and bright > params.max_bright_surround:
        reasons.append(f"{100 * bright:.1f} % of the surround is as bright as the screen's edge "
                       f"(at most {100 * params.max_bright_surround:.1f} %)")
    if lit is not None and lit > params.max_bright_surround:
        reasons.append(f"the flat frame saw {100 * lit:.1f} % of the surround exposed "
                       f"(at most {100 * params.max_bright_surround:.1f} %)")
    if len(reasons) == 1 and lit is not None and lit > params.max_bright_surround:
        # a strong straight step down to a dark level inside the exposed screen: the edge of a
        # collimated field, or of a dense object; the collimation step tells them apart
        evidence["field_edge"] = True
    evidence["accepted"] = not reasons
    if reasons:
        evidence["reason"] = "; ".join(reasons)
    return evidence


#: A pixel the flat frame lights less than this share of its 99.5th percentile got no X-rays (the
#: screen's rim under vignetting and heel keeps about 0.3, room light stays below 0.05).
_FLAT_EXPOSED_FRACTION = 0.15


def flat_exposed_area(light: np.ndarray) -> np.ndarray | None:
    """Where the open-beam flat frame saw the screen lit, or None when that is (nearly) everywhere.

    The flat's pixels above :data:`_FLAT_EXPOSED_FRACTION` of its 99.5th percentile, opened and
    closed (5 x 5), the largest component with its holes filled and shrunk by 2 px (the screen's
    soft rim, where the flat-field division of little light by little light is noise and the
    room beyond it is lifted to any level, stays out, as the accepted quadrilateral's rim does:
    grown instead, its bright noise took the top of the value-of-interest window beside a
    collimated chest and showed the anatomy at 0.4 of its contrast). None when that area covers more than 95 % of the frame (the camera framed part
    of the screen: the whole frame is the region) or less than 2 % (no usable flat).
    """
    top = float(np.percentile(light, 99.5))
    if not top > 0:
        return None
    lit = (light > _FLAT_EXPOSED_FRACTION * top).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    lit = cv2.morphologyEx(cv2.morphologyEx(lit, cv2.MORPH_OPEN, kernel), cv2.MORPH_CLOSE, kernel)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(lit, connectivity=8)
    if n <= 1:
        return None
    component = (labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
    contours, _ = cv2.findContours(component, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    filled = np.zeros_like(component)
    cv2.drawContours(filled, contours, -1, 1, thickness=cv2.FILLED)
    filled = cv2.erode(filled, kernel)
    share = float(filled.mean())
    return filled.astype(bool) if 0.02 <= share <= 0.95 else None


def _away_from_rim(flat_level: np.ndarray, radius_px: int = 7, share: float = 0.6) -> np.ndarray:
    """Pixels the flat frame lights at least ``share`` of the brightest light within
    ``radius_px`` (both lightly smoothed against its noise): the screen's soft rim, where the
    flat falls off, is left out, also where it meets the frame's edge (the 2 px shrink of
    :func:`flat_exposed_area` does not reach a rim lying along the frame's edge, whose
    lifted values took the top of the value-of-interest window)."""
    smooth = cv2.GaussianBlur(flat_level.astype(np.float32), (0, 0), 1.0)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))
    return smooth >= share * cv2.dilate(smooth, kernel)


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

    exposed: list = [None]  # the flat frame's exposed area (small-image mask), once the flat is read

    def nothing(reason: str, **extra) -> Region:
        evidence = {"accepted": False, **extra, "reason": reason}
        if exposed[0] is None:
            return Region(np.ones((h, w), bool), whole, detected=False, evidence=evidence)
        # no screen border on evidence, but the open-beam flat shows where X-rays reached the
        # screen: nothing outside that area can be anatomy (the flat-field division lifts it to
        # the screen's level, where it would take the value-of-interest window)
        evidence["flat_exposed_fraction"] = round(float(exposed[0].mean()), 4)
        mask = cv2.resize(exposed[0].astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
        return Region(mask, whole, detected=False, evidence=evidence)

    if params.polygon_xy:
        poly = np.asarray(params.polygon_xy, np.float64)
        if poly.shape != (4, 2):
            raise ParameterError(f"region.polygon_xy: expected 4 [x, y] points, got shape {poly.shape}")
        poly = order_corners(poly)
        return Region(polygon_mask((h, w), poly), poly, detected=False, evidence={"source": "user polygon"})
    if not params.enabled:
        return Region(np.ones((h, w), bool), whole, detected=False, evidence={"source": "detection disabled"})
    small, flat_level = _light_seen(arr, illumination, params.analysis_size_px)
    flat_lit = None
    if flat_level is not None:
        exposed[0] = flat_exposed_area(flat_level)
        flat_lit = flat_level > _FLAT_EXPOSED_FRACTION
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
    found = _best_candidate(small, scaled, noise, params, flat_lit)
    if found is None:
        return nothing("no bright area")
    corners, evidence = found
    # pixel-centre coordinates of the small image -> full resolution
    corners = (corners + 0.5) * np.array([w / small.shape[1], h / small.shape[0]]) - 0.5
    corners = order_corners(corners)
    if not evidence["accepted"]:
        evidence.pop("open_side_index")
        return nothing(evidence.pop("reason"), **{k: v for k, v in evidence.items() if k != "accepted"},
                       candidate_xy=corners.round(1).tolist())
    poly = _screen_polygon(corners, evidence, params, (h, w))
    mask = polygon_mask((h, w), poly)
    if evidence["open_sides"] and exposed[0] is not None:
        # a screen the frame cut at a corner is a pentagon, which four corners cannot follow: the
        # polygon may hold a wedge of room and soft rim beside that corner (where the flat-field
        # division lifts the room to any level and takes the value-of-interest window); keep
        # only what the open-beam flat saw lit, away from its rim
        # (holes filled: a dark defect of the flat inside the screen, dust or a marker, is not a
        # rim, which always joins the room or the frame's edge)
        from scipy import ndimage

        lit = ndimage.binary_fill_holes(exposed[0] & _away_from_rim(flat_level))
        mask &= cv2.resize(lit.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    return Region(mask, poly, detected=True, evidence=evidence)


def _light_seen(arr: np.ndarray, illumination: np.ndarray | None,
                analysis_size_px: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The light the camera saw (image x illumination, colour summed), area-downsampled so its
    longest side is about ``analysis_size_px`` (float32), and the area the flat frame shows
    exposed (small-image mask; None without an illumination of the image's shape)."""
    h, w = arr.shape[:2]
    factor = max(1.0, max(h, w) / float(analysis_size_px))
    size = (max(8, round(w / factor)), max(8, round(h / factor)))

    def shrink(a: np.ndarray) -> np.ndarray:
        a = a if a.dtype == np.float32 else a.astype(np.float32)
        # downsample first (area average), then sum the colour channels: no full-size copy
        return cv2.resize(a, size, interpolation=cv2.INTER_AREA) if factor > 1 else a.copy()

    small, flat_level = shrink(arr), None
    if illumination is not None:
        light = shrink(np.asarray(illumination))
        if light.ndim == 2 and small.ndim == 3:
            light = light[..., None]
        if light.shape[:2] == small.shape[:2]:
            small = small * light
            flat_light = light if light.ndim == 2 else light.sum(axis=2)
            top = float(np.percentile(flat_light, 99.5))
            flat_level = flat_light / top if top > 0 else None
    if small.ndim == 3:
        small = small.sum(axis=2)
    return small, flat_level


def _best_candidate(small: np.ndarray, scaled: np.ndarray, noise: np.ndarray,
                    params: RegionParams, flat_lit: np.ndarray | None = None) -> tuple[np.ndarray, dict] | None:
    """Corners (small image's pixels) and evidence of the best screen candidate, or None.

    Two candidates: the bright class of a log-scale Otsu split, and everything above the dark
    class of a second split below it (when a large direct-exposure area takes the bright class,
    the screen is the union of the two brighter classes). The first accepted one wins, unless
    the lower threshold adds a real area; with none accepted, the first candidate and why (the
    first that is a field's edge inside the exposed screen, when one is).
    """
    high, _ = cv2.threshold(scaled, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    thresholds = [high]
    darker = scaled[scaled <= high]
    if darker.size > 16 and np.ptp(darker) > 2:
        low, _ = cv2.threshold(darker.reshape(1, -1), 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        if low < high:
            thresholds.append(low)
    best, first = None, None
    for threshold in thresholds:
        candidate = _candidate_corners(small, scaled, threshold)
        if candidate is None:
            continue
        corners, frame_cuts = candidate
        evidence = screen_evidence(small, noise, corners, params, flat_lit, frame_cuts)
        area = cv2.contourArea(order_corners(corners).astype(np.float32))
        if first is None or (evidence.get("field_edge") and not first[1].get("field_edge")):
            first = (corners, evidence)  # a field's edge is the better account of a refusal
        # the lower threshold wins when it adds a real area (not just the blurred rim), or when
        # the flat saw less of its surround lit and no side the frame cut closes: lit surround
        # beside an accepted candidate is exposed screen beyond a side the fit put across it
        # (dense anatomy at the screen's edge as dark as the room), which blanks that anatomy
        if evidence["accepted"] and (best is None or area > 1.1 * best[2]
                                     or (_flat_lit_share(evidence) < _flat_lit_share(best[1])
                                         and set(best[1]["open_sides"]) <= set(evidence["open_sides"]))):
            best = (corners, evidence, area)
    if first is None:
        return None
    return (best[0], best[1]) if best is not None else first


def _flat_lit_share(evidence: dict) -> float:
    """Share of a candidate's surround the flat frame saw lit (0 without a flat)."""
    return evidence.get("flat_lit_surround") or 0.0


def _screen_polygon(corners: np.ndarray, evidence: dict, params: RegionParams, shape: tuple[int, int]) -> np.ndarray:
    """The accepted screen's corners shrunk inside its rim, except on the sides the frame cut,
    which go on (or beyond) the frame's edge. Takes ``open_side_index`` out of ``evidence``.

    An open side's corner moves along the other side that meets there (when that one is a
    seen border) until it reaches the frame's edge, so the seen border keeps its line: moved
    straight out to the edge instead, a corner inside the frame turned that border and cut a
    wedge of the screen off (or added one of the room). Where both sides at a corner are open,
    the corner goes to the frame's corner (or stays beyond it)."""
    h, w = shape
    poly = shrink_polygon(corners, params.shrink_fraction)
    shrunk = poly.copy()
    edge_value = {"left": (0, -0.5, min), "top": (1, -0.5, min), "right": (0, w - 0.5, max), "bottom": (1, h - 0.5, max)}
    open_edge = dict(zip(evidence.pop("open_side_index"), evidence["open_sides"], strict=True))
    for index, edge in open_edge.items():
        axis, value, pick = edge_value[edge]
        for corner, other in ((index, (index - 1) % 4), ((index + 1) % 4, (index + 1) % 4)):
            if pick(corners[corner, axis], value) == corners[corner, axis]:
                poly[corner, axis] = corners[corner, axis]  # on or beyond the frame's edge: not shrunk
                continue
            # the other side at this corner runs from ``far`` through the corner
            far = shrunk[(corner + 1) % 4] if other == corner else shrunk[other]
            step = shrunk[corner] - far
            if other not in open_edge and abs(step[axis]) > 1e-6 * max(h, w):
                reach = shrunk[corner] + step * (value - shrunk[corner, axis]) / step[axis]
                if np.hypot(*(reach - shrunk[corner])) < max(h, w):
                    poly[corner] = reach
                    continue
            poly[corner, axis] = pick(corners[corner, axis], value)
    return poly
