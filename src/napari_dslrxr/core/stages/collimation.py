"""Collimator blades: the exposed field of a collimated radiograph.

:func:`detect_collimation` finds straight, bright, uniform bands along the frame's sides
(display orientation: the unexposed band is bright) and returns the field between them.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import InputError, ParameterError
from .region import Region, _line_intersection, _sample, polygon_mask


#: Sides of the frame a collimator blade can cover: the Hough angle range's centre (radians,
#: skimage convention x cos(theta) + y sin(theta) = rho with x = column, y = row) and the sign of
#: the outward normal (towards the blade, away from the exposed field).
_BLADE_SIDES = {"left": (0.0, -1.0), "right": (0.0, 1.0), "top": (np.pi / 2, -1.0), "bottom": (np.pi / 2, 1.0)}


#: How far into the field (fraction of the frame's shorter side) a blade's penumbra is followed,
#: and the widest penumbra dropped (the NEMA CR leg's blades: 1.3 and 1.9 %).
_PENUMBRA_REACH = 0.04
_PENUMBRA_MAX = 0.025


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


def _profiles_across(image: np.ndarray, theta: float, rho: float, outward: float,
                     offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Profiles of ``image`` across a line, every few pixels along it: ``(points, normal,
    profiles)``, the (x, y) points on the line, the unit normal towards the blade and the values
    at ``offsets`` (px along that normal) from each point (NaN outside the frame)."""
    h, w = image.shape
    normal = outward * np.array([np.cos(theta), np.sin(theta)])
    points = _line_samples((h, w), theta, rho, step_px=max(2.0, min(h, w) / 400.0))
    return points, normal, _sample(image, points[:, None, :] + offsets[None, :, None] * normal)


def _refine_blade(image: np.ndarray, theta: float, rho: float, outward: float,
                  half_width_px: float) -> tuple[float, float] | None:
    """Move a coarse blade line onto the steepest outward step of the full-resolution image.

    Profiles across the line, every few pixels along it; on each, the sub-pixel position of
    the largest outside-minus-inside derivative; a robust (Huber) line through those points.
    Returns ``(theta, rho)`` or None when too few profiles show the step.
    """
    offsets = np.arange(-half_width_px, half_width_px + 1.0)
    points, normal, profiles = _profiles_across(image, theta, rho, outward, offsets)
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


def _penumbra_px(image: np.ndarray, theta: float, rho: float, outward: float, reach_px: float,
                 settled: float = 0.02) -> float:
    """How far into the field a blade's penumbra reaches from its edge line (px).

    A blade's edge is no step: past its steepest point the exposure keeps rising over tens of
    pixels towards the field's level (a long, faint tail on clinical CR plates), and a
    display's steep curve near the direct beam shows that tail as a grey line beside a black
    shutter. Profiles across the line, every few pixels along it, ``reach_px`` into the field:
    on each, the inward distance from the line at which the profile has come within
    ``settled`` of the blade-to-field step of the field's level (the median of the profile's
    inner half). The median over the profiles whose outside is brighter than their inside by a
    clear step; 0 when too few are.
    """
    h, w = image.shape
    offsets = np.arange(-np.ceil(reach_px), 6.0)  # whole px from the line: inward (negative) to a few onto the blade
    profiles = _profiles_across(image, theta, rho, outward, offsets)[2]
    profiles = profiles[np.all(np.isfinite(profiles), axis=1)]
    if len(profiles) < 8:
        return 0.0
    inner = offsets <= -reach_px / 2
    field_level = np.median(profiles[:, inner], axis=1)
    blade_level = np.median(profiles[:, offsets >= 3.0], axis=1)
    step = blade_level - field_level
    profiles, field_level, step = profiles[step > 0.1], field_level[step > 0.1], step[step > 0.1]
    if len(profiles) < 8:
        return 0.0
    # walking inwards from the line (offset 0, -1, ...): the first pixel at the field's level
    # (anatomy further in, brighter than the field, is not counted)
    from_line = profiles[:, offsets <= 0][:, ::-1]
    settled_px = from_line - field_level[:, None] <= settled * step[:, None]
    reach = np.where(settled_px.any(axis=1), np.argmax(settled_px, axis=1), from_line.shape[1])
    # A penumbra's tail falls ever more gently away from the edge; anatomy lying along the
    # blade is a plateau that ends in a second edge (its skin line): a fall of at least a
    # quarter of the edge's steepest after the fall had nearly stopped (a tenth). Such a
    # profile has no penumbra to drop (its anatomy is never shuttered).
    smooth = cv2.GaussianBlur(from_line.astype(np.float32), (1, 5), 0)  # along the line, as the edge fit
    drop = smooth[:, :-1] - smooth[:, 1:]  # fall per px, going inwards
    at_edge = np.maximum(drop[:, :3].max(axis=1), 1e-12)[:, None]
    gentlest_before = np.minimum.accumulate(np.concatenate([np.full((len(drop), 1), np.inf), drop[:, :-1]], axis=1),
                                            axis=1)
    inside_reach = np.arange(drop.shape[1])[None, :] < reach[:, None]
    second_edge = ((drop > 0.25 * at_edge) & (gentlest_before < 0.1 * at_edge) & inside_reach).any(axis=1)
    reach = np.where(second_edge, 0, reach)
    penumbra = float(np.median(reach))
    # wider than any blade's penumbra: something else lies along the edge; leave it in the field
    return penumbra if penumbra <= _PENUMBRA_MAX * min(h, w) else 0.0


def detect_collimation(image: np.ndarray, *, analysis_size_px: int = 512, max_tilt_deg: float = 10.0,
                       min_step: float = 0.08, inset_px: float = 0.0, drop_penumbra: bool = False) -> Region:
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
    drop_penumbra : bool
        Move each edge further in where the blade's penumbra reaches further: to where the
        image has come within 2 % of the blade-to-field step of the field's level (median over
        profiles along the edge, followed up to 4 % of the frame's shorter side into the field;
        a profile with a second steep edge inside, anatomy along the blade, counts as none, and
        a median above 2.5 % of the shorter side is not taken for a penumbra).
        For a display with a black shutter outside the field, where the faint tail of a soft
        blade edge otherwise shows as a grey line.

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
    grid_xy = np.meshgrid(np.arange(sw), np.arange(sh))  # (x, y) pixel indices, once for all candidates
    lines = {}
    for side, (axis_theta, outward) in _BLADE_SIDES.items():
        normal_gradient = (gx if axis_theta == 0 else gy) * outward  # rises towards the blade
        found = _best_blade(small, edges & (normal_gradient > 0.8 * magnitude), grid_xy, axis_theta, outward,
                            max_tilt_deg, min_step)
        if found is None:
            continue
        full_theta, full_rho = _to_full_resolution(*found, scale)
        refined = _refine_blade(full, full_theta, full_rho, outward, half_width_px=2.0 * factor + 4.0)
        theta, rho = refined if refined is not None else (full_theta, full_rho)
        inset = inset_px
        if drop_penumbra:
            inset = max(inset, _penumbra_px(full, theta, rho, outward, reach_px=_PENUMBRA_REACH * min(h, w)))
        lines[side] = (theta, rho - outward * inset)
    poly = _field_polygon(lines, (h, w)) if lines else None
    return nothing if poly is None else Region(polygon_mask((h, w), poly), poly, detected=True)


def _best_blade(small: np.ndarray, side_edges: np.ndarray, grid_xy, axis_theta: float, outward: int,
                max_tilt_deg: float, min_step: float) -> tuple[float, float] | None:
    """The best-scoring blade line ``(theta, rho)`` of one side on the small copy, or None: the
    peaks of a Hough transform of the side's edges within ``max_tilt_deg`` of its axis, each
    scored by :func:`_blade_score`."""
    from skimage.transform import hough_line, hough_line_peaks

    sh, sw = small.shape
    if np.count_nonzero(side_edges) < 0.2 * min(sh, sw):
        return None
    tilt = np.deg2rad(max_tilt_deg)
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
    return best[1]


def _to_full_resolution(theta: float, rho: float, scale: np.ndarray) -> tuple[float, float]:
    """A line of the small copy on the full-resolution grid: p_full = (p_small + 0.5) * scale - 0.5."""
    nx, ny = np.cos(theta) / scale[0], np.sin(theta) / scale[1]
    norm = np.hypot(nx, ny)
    full_theta = float(np.arctan2(ny, nx))
    full_rho = float((rho + 0.5 * (np.cos(theta) + np.sin(theta))) / norm - 0.5 * (nx + ny) / norm)
    return full_theta, full_rho


def _field_polygon(lines: dict, shape: tuple[int, int]) -> np.ndarray | None:
    """The field's corners (TL, TR, BR, BL): the found blade lines, the frame's border on the
    sides without a blade; None when two sides do not meet."""
    h, w = shape
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
            return None
        corners.append(point)
    return np.array(corners)
