"""Pixel neighbourhoods of the impulse stage: polyphase components, ring medians and
spreads, masked window medians and flat-index helpers."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .params import _FLOAT

#: Replacement / re-test windows (side in px) and the least number of non-pulse pixels each
#: must hold to be used; the first window that qualifies is used.
_REPLACEMENT_WINDOWS_PX = (3, 5, 7, 9)
_REPLACEMENT_MIN_GOOD = (5, 8, 12, 12)
#: Pixels whose windows are gathered and sorted at once (bounded temporaries).
_MEDIAN_CHUNK_PX = 16384

#: Standard deviation of a Gaussian per unit of its interquartile range (1 / 1.349).
IQR_TO_SIGMA = 1.0 / 1.349


@dataclass
class _Component:
    """A polyphase component of a channel (rows r0::step, cols c0::step): its 3x3 median."""

    r0: int
    c0: int
    step: int
    median: np.ndarray


def _detection_components(x: np.ndarray, size_px: int):
    """The components the fast detection median works on: (component, its values) pairs.

    ``size_px`` 3: the whole image and its 3x3 median. 5: the *sparse* 5x5 median over the
    centre and the eight pixels two steps away (rows and columns -2, 0, +2), computed as the
    3x3 median of each of the four polyphase components: a patch of up to 3x3 px around the
    centre holds only one of its nine samples, so the median stays on the background, at the
    cost of one 3x3 median. Both include the centre (cv2.medianBlur), replicated border.
    Yields one component at a time, with a contiguous float32 copy of its values that the
    caller may drop once used (only the medians are kept: memory on 24 Mpx frames).
    """
    import cv2

    step = 1 if size_px == 3 else 2
    for r0 in range(step):
        for c0 in range(step):
            values = np.ascontiguousarray(x[r0::step, c0::step], dtype=_FLOAT)
            yield _Component(r0, c0, step, cv2.medianBlur(values, 3)), values


#: Batcher's odd-even merge sort of 8 values (19 compare-exchanges), used column-wise.
_SORT8_NETWORK = ((0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (1, 2), (5, 6),
                  (0, 4), (3, 7), (1, 5), (2, 6), (1, 4), (3, 6), (2, 4), (3, 5), (3, 4))


def _ring_median_at(x: np.ndarray, rows: np.ndarray, cols: np.ndarray, size_px: int,
                    with_spread: bool = False, channel: int | None = None):
    """Median of the 8 detection samples around each pixel, centre excluded (float64).

    The samples are those of :func:`_detection_components` without the centre: the 8 neighbours
    (``size_px`` 3) or the 8 pixels two steps away (5). Borders are replicated. The median
    of 8 is the mean of the 4th and 5th values, found by a sorting network over the columns.

    ``with_spread``: also return the spread of the 8 samples, (v6 + v7 - v2 - v3) / 2 of the
    sorted values over 1.325, its expected value for 8 Gaussian samples of unit deviation
    (float64): about the noise on a smooth background, far more on edges and corners.

    ``channel``: ``x`` is an (H, W, C) image and the samples are those of this channel.
    """
    step = 1 if size_px == 3 else 2
    dr = np.array([-step, -step, -step, 0, 0, step, step, step])
    dc = np.array([-step, 0, step, -step, step, -step, 0, step])
    flat = _flat_indices(rows, cols, dr, dc, x.shape[:2])
    if channel is None:
        x_flat = np.ascontiguousarray(x).ravel()
        v = [x_flat[flat[:, k]] for k in range(8)]
    else:  # one channel of an interleaved image, gathered in place (a contiguous copy of the
        # whole channel cost more than the gather for the EM sample's 250 000 pixels)
        x_flat = np.ascontiguousarray(x).ravel()
        flat *= x.shape[2]
        flat += channel
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
    vals = np.ascontiguousarray(x).ravel()[flat]
    half = vals.shape[1] // 2
    # Means of point-symmetric pairs (row-major ring: the mirror of k is n - 1 - k): on a
    # linear ramp each equals the centre's value, so only curvature and noise spread them.
    # (Summed in float64 from the gathered values: no float64 copy of the whole ring.)
    pairs = np.add(vals[:, :half], vals[:, ::-1][:, :half], dtype=np.float64)
    pairs *= 0.5
    pairs.sort(axis=1)
    n = half
    return math.sqrt(2.0) * IQR_TO_SIGMA * (pairs[:, (3 * (n - 1)) // 4] - pairs[:, (n - 1) // 4])


def _sorted_unique(indices: np.ndarray, size: int | None = None) -> np.ndarray:
    """Sorted distinct values of an integer array (same result as ``np.unique``).

    numpy 2's hash-based ``np.unique`` took about 15x longer than sort-and-compare on the
    neighbour-index arrays of a 24-megapixel frame. With ``size`` (all values are below
    it) and many values, a bitmap of ``size`` flags is used instead of the sort (half the
    time from a few per cent of ``size`` on).
    """
    if size is not None and indices.size * 32 > size:
        flags = np.zeros(size, bool)
        flags[indices.ravel()] = True
        return np.flatnonzero(flags)
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
                      smallest_px: int = 3, symmetric: bool = False, with_spread: bool = False,
                      spread_about: str = "median", marked_px: np.ndarray | None = None):
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
    deviation for Gaussian noise; larger where the window holds structure, float64), of
    their values (``spread_about="median"``) or of their residuals to their least-squares
    plane (``"plane"``, with ``symmetric`` only: a ramp is not structure there).

    ``marked_px`` (optional): the flat indices of every nonzero pixel of ``excluded``. For a
    floating-point ``x`` (finite, as every channel of the stage is) those pixels of ``x``
    are then set to +inf for the time of the call (and restored), and the windows are read
    from ``x`` alone: the same values, without gathering a window of ``excluded`` too
    (measured: a quarter of the growth's time on 24 Mpx frames dense with pulses).
    """
    x = np.ascontiguousarray(x)
    out = np.full(rows.shape, np.nan)
    spread = np.full(rows.shape, np.nan) if with_spread else None
    x_flat = x.reshape(-1)
    if marked_px is not None and np.issubdtype(x.dtype, np.floating) and x.flags.writeable:
        excluded, saved = None, x_flat[marked_px]
        x_flat[marked_px] = np.inf
    else:
        excluded, saved = np.ascontiguousarray(excluded), None
    try:
        for start in range(0, rows.size, _MEDIAN_CHUNK_PX):  # bounded (N, window) temporaries
            part = slice(start, start + _MEDIAN_CHUNK_PX)
            _masked_median_chunk(x, excluded, rows[part], cols[part], smallest_px, symmetric,
                                 out[part], None if spread is None else spread[part], spread_about == "plane")
    finally:
        if saved is not None:
            x_flat[marked_px] = saved
    return (out, spread) if with_spread else out


def _plane_residuals(vals: np.ndarray, bad: np.ndarray, size: int) -> np.ndarray:
    """(N, size^2) residuals of each row-major window's good values (``~bad``) to their
    least-squares plane, sorted, the bad ones +inf (float64). The good set is
    point-symmetric (``symmetric``), so the plane's intercept is the good values' mean and
    its two slopes solve a 2x2 system."""
    dr, dc = _window_offsets(size)
    dr, dc = dr.astype(np.float64), dc.astype(np.float64)
    good = ~bad
    v = np.where(good, vals, 0.0).astype(np.float64)
    mean = v.sum(axis=1) / np.maximum(good.sum(axis=1), 1)
    srr, scc, src = good @ (dr * dr), good @ (dc * dc), good @ (dr * dc)
    svr, svc = v @ dr, v @ dc
    det = srr * scc - src * src
    det = np.where(det > 1e-9, det, np.inf)  # too few pixels for a plane: a constant
    slope_r = (svr * scc - svc * src) / det
    slope_c = (svc * srr - svr * src) / det
    res = vals - (mean[:, None] + slope_r[:, None] * dr + slope_c[:, None] * dc)
    res[bad] = np.inf
    res.sort(axis=1)
    return res


#: Windows from this side on are copied as blocks of a sliding-window view (one block per
#: pixel) rather than gathered pixel by pixel through flat indices: measured on the 280 000
#: ring pixels of a growth round (tinted 1 % frame), 7x7 windows of values and marks in
#: half the time; 3x3 blocks are slower that way, 5x5 about even.
_BLOCK_COPY_FROM_PX = 7


def _window_values(x: np.ndarray, rows: np.ndarray, cols: np.ndarray, size_px: int) -> np.ndarray:
    """(N, size_px^2) row-major windows of the 2-D ``x`` around (rows, cols), border
    replicated (the order of :func:`_window_flat_indices`); a new array."""
    if size_px < _BLOCK_COPY_FROM_PX:
        return x.ravel()[_window_flat_indices(rows, cols, size_px, x.shape)]
    h, w = x.shape
    r = size_px // 2
    blocks = np.lib.stride_tricks.sliding_window_view(x, (size_px, size_px))
    inner = (rows >= r) & (rows < h - r) & (cols >= r) & (cols < w - r)
    if inner.all():
        return blocks[rows - r, cols - r].reshape(rows.size, size_px * size_px)
    out = np.empty((rows.size, size_px * size_px), x.dtype)
    at = np.flatnonzero(inner)
    out[at] = blocks[rows[at] - r, cols[at] - r].reshape(at.size, size_px * size_px)
    at = np.flatnonzero(~inner)
    out[at] = x.ravel()[_window_flat_indices(rows[at], cols[at], size_px, x.shape)]
    return out


def _masked_median_chunk(x, excluded, rows, cols, smallest_px, symmetric, out, spread, about_plane=False):
    """:func:`_masked_median_at` for one chunk of pixels, written into ``out`` and ``spread``
    (``x`` and ``excluded``: 2-D, C-contiguous; ``excluded`` None: the excluded pixels of
    ``x`` are +inf)."""
    with_spread = spread is not None
    todo = np.arange(rows.size)
    for size, min_good in zip(_REPLACEMENT_WINDOWS_PX, _REPLACEMENT_MIN_GOOD, strict=True):
        if todo.size == 0:
            break
        if size < smallest_px:
            continue
        vals = _window_values(x, rows[todo], cols[todo], size).astype(_FLOAT, copy=False)
        if excluded is None:
            bad = vals == np.inf
        else:
            bad = _window_values(excluded, rows[todo], cols[todo], size) != 0
        if symmetric:
            bad |= bad[:, ::-1]  # row-major window: the mirror of offset k is offset n - 1 - k
        good_count = size * size - np.count_nonzero(bad, axis=1)
        about = _plane_residuals(vals, bad, size) if with_spread and about_plane else None
        vals[bad] = np.inf
        vals.sort(axis=1)
        enough = good_count >= (min_good if size != _REPLACEMENT_WINDOWS_PX[-1] else 1)
        idx = np.nonzero(enough)[0]
        if idx.size:
            n = good_count[idx]
            lo = vals[idx, (n - 1) // 2]
            hi = vals[idx, n // 2]
            out[todo[idx]] = 0.5 * (lo.astype(np.float64) + hi)
            if with_spread:
                sorted_for_spread = vals if about is None else about
                q1 = sorted_for_spread[idx, (n - 1) // 4]
                q3 = sorted_for_spread[idx, (3 * (n - 1)) // 4]
                spread[todo[idx]] = IQR_TO_SIGMA * (q3.astype(np.float64) - q1)
        todo = todo[~enough]


class _FullMap:
    """A per-pixel float32 map of a channel, filled component by component.

    The fast detection works on polyphase components; ``part`` is the (strided, writable)
    view of one component's pixels, so each component writes its block in place, and reads
    at full-image flat indices are plain gathers (the neighbour indices the texture guard
    builds anyway serve both the channel and this map).
    """

    def __init__(self, shape, step: int):
        self._height, self.width = shape
        self.step = step
        self.data = np.zeros(shape, _FLOAT)
        self.flat = self.data.reshape(-1)

    def part(self, comp: "_Component") -> np.ndarray:
        """The (writable) view of one component's pixels, shaped like its median."""
        return self.data[comp.r0::self.step, comp.c0::self.step]

    def at(self, flat: np.ndarray) -> np.ndarray:
        return self.flat[flat]

    def around(self, rows: np.ndarray, cols: np.ndarray, dr: np.ndarray, dc: np.ndarray) -> np.ndarray:
        """Values at (rows + dr, cols + dc), shape (N, K), borders replicated."""
        return self.flat[_flat_indices(rows, cols, dr, dc, (self._height, self.width))]


def _component_values_at(components: list[_Component], rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The fast detection median at full-image (rows, cols) (same shape; border replicated)."""
    step = components[0].step
    shape = np.broadcast(rows, cols).shape
    h = sum(comp.median.shape[0] for comp in components if comp.c0 == 0)
    w = sum(comp.median.shape[1] for comp in components if comp.r0 == 0)
    rows = np.clip(rows, 0, h - 1).ravel()
    cols = np.clip(cols, 0, w - 1).ravel()
    phase = (rows % step) * step + (cols % step)  # components are in row-major phase order
    out = np.empty(rows.size, _FLOAT)
    for k, comp in enumerate(components):
        sel = np.flatnonzero(phase == k)
        out[sel] = comp.median.ravel()[(rows[sel] // step) * comp.median.shape[1] + cols[sel] // step]
    return out.reshape(shape)


def _subsample_indices(n: int, count: int) -> np.ndarray:
    """A regular (deterministic) subsample of ``count`` flat indices out of ``n``."""
    if n <= count:
        return np.arange(n)
    step = n / count
    return (np.arange(count) * step).astype(np.int64)
