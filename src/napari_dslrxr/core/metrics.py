"""Image-quality metrics of the pipeline: percentage error (PE) and global contrast factor (GCF).

* PE = 100 * ||x - x_hat||_2 / ||x||_2 over the pixels of a region, with ``x`` the reference
  (noise-free or original) and ``x_hat`` the processed image, both in the same linear units.
  On a pulse-free region a perfect switching filter changes nothing, so PE there measures
  over-filtering.
* GCF: Matkovic, Neumann, Neumann, Psik & Purgathofer, "Global Contrast Factor - a New
  Approach to Image Contrast", Computational Aesthetics 2005, pp. 159-167. Computed on the
  display-referred grey image at nine resolutions (``docs/algorithms/metrics.md``, section
  'Global contrast factor').
"""

from __future__ import annotations

import numpy as np

from .errors import InputError, ParameterError

__all__ = ["percentage_error", "global_contrast_factor", "GCF_SUPERPIXELS_PX", "gcf_weights", "gcf_levels",
           "gcf_by_region", "local_contrast_map"]

#: Superpixel sizes (px) of the nine GCF resolutions (the paper's list for 1024x768 images).
GCF_SUPERPIXELS_PX = (1, 2, 4, 8, 16, 25, 50, 100, 200)
#: Display gamma of the GCF's linearisation.
GCF_GAMMA = 2.2
#: Rec. 709 luma weights used to turn display RGB into grey for the GCF.
REC709_LUMA = (0.2126, 0.7152, 0.0722)


def percentage_error(reference: np.ndarray, estimate: np.ndarray, *,
                     roi: tuple[int, int, int, int] | None = None,
                     mask: np.ndarray | None = None) -> float:
    """Percentage error ``100 * ||reference - estimate|| / ||reference||`` (L2, in %).

    Parameters
    ----------
    reference, estimate : ndarray
        Same shape, ``(H, W)`` or ``(H, W, C)``; any real dtype (computed in float64), same
        linear units.
    roi : tuple of int, optional
        ``(r0, c0, r1, c1)`` in pixels, end exclusive; default the whole image.
    mask : ndarray of bool, optional
        ``(H, W)``: only pixels where it is True count (combined with ``roi``).

    Returns
    -------
    float
        PE in percent.

    Raises
    ------
    InputError
        Shapes differ, values are not finite, or the region is empty or all zero in the
        reference.
    ParameterError
        The ROI is outside the image or empty.
    """
    x = np.asarray(reference)
    y = np.asarray(estimate)
    if x.shape != y.shape:
        raise InputError("estimate", f"shape {y.shape} differs from the reference's {x.shape}")
    if x.ndim not in (2, 3) or x.size == 0:
        raise InputError("reference", f"expected an (H, W) or (H, W, C) image, got shape {x.shape}")
    for name, arr in (("reference", x), ("estimate", y)):
        if arr.dtype.kind not in "uifb":
            raise InputError(name, f"unsupported dtype {arr.dtype}")
    select = np.ones(x.shape[:2], bool)
    if roi is not None:
        r0, c0, r1, c1 = (int(v) for v in roi)
        h, w = x.shape[:2]
        if not (0 <= r0 < r1 <= h and 0 <= c0 < c1 <= w):
            raise ParameterError(f"roi: (r0, c0, r1, c1) = {tuple(roi)} is empty or outside the {h}x{w} image")
        inside = np.zeros_like(select)
        inside[r0:r1, c0:c1] = True
        select &= inside
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != x.shape[:2]:
            raise InputError("mask", f"shape {m.shape} differs from the image's {x.shape[:2]}")
        select &= m.astype(bool)
    if not select.any():
        raise InputError("region", "no pixel selected by the ROI and mask")
    xs = x[select].astype(np.float64)
    ys = y[select].astype(np.float64)
    if not (np.isfinite(xs).all() and np.isfinite(ys).all()):
        raise InputError("image", "NaN or infinite values in the region")
    norm = float(np.linalg.norm(xs))
    if norm == 0.0:
        raise InputError("reference", "is zero everywhere in the region; PE is undefined")
    return 100.0 * float(np.linalg.norm(xs - ys)) / norm


def gcf_weights() -> np.ndarray:
    """The nine GCF weights ``w_i = (-0.406385 i/9 + 0.334573) i/9 + 0.0877526``, i = 1..9."""
    t = np.arange(1, 10) / 9.0
    return (-0.406385 * t + 0.334573) * t + 0.0877526


def _display_grey(image: np.ndarray) -> np.ndarray:
    """Display grey level k in [0, 255], float64, from uint8/uint16/float, grey or RGB."""
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[-1] in (3, 4):
        arr = arr[..., :3]
    elif arr.ndim != 2:
        raise InputError("image", f"expected (H, W) or (H, W, 3), got shape {arr.shape}")
    if arr.size == 0:
        raise InputError("image", "empty image")
    if arr.dtype == np.uint8:
        k = arr.astype(np.float64)
    elif arr.dtype == np.uint16:
        k = arr.astype(np.float64) * (255.0 / 65535.0)
    elif arr.dtype.kind == "f":
        if not np.isfinite(arr).all():
            raise InputError("image", "NaN or infinite values")
        if arr.min() < 0.0 or arr.max() > 1.0:
            raise InputError("image", f"float display image must lie in [0, 1], got [{arr.min():.4g}, {arr.max():.4g}]")
        k = arr.astype(np.float64) * 255.0
    else:
        raise InputError("image", f"unsupported dtype {arr.dtype} (use uint8, uint16 or float in [0, 1])")
    if k.ndim == 3:
        k = k @ np.asarray(REC709_LUMA)
    return k


def local_contrast_map(perceptual: np.ndarray) -> np.ndarray:
    """Per pixel, the mean |L(p) - L(q)| over the existing 4-neighbours q of p (float64)."""
    h, w = perceptual.shape
    total = np.zeros((h, w))
    count = np.zeros((h, w))
    if w > 1:
        dh = np.abs(np.diff(perceptual, axis=1))
        total[:, :-1] += dh
        total[:, 1:] += dh
        count[:, :-1] += 1
        count[:, 1:] += 1
    if h > 1:
        dv = np.abs(np.diff(perceptual, axis=0))
        total[:-1, :] += dv
        total[1:, :] += dv
        count[:-1, :] += 1
        count[1:, :] += 1
    return np.divide(total, count, out=np.zeros_like(total), where=count > 0)


def gcf_levels(image: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """The GCF's nine resolutions: ``(superpixel size, perceptual luminance L)`` each.

    ``L = 100 sqrt(l)`` of the linear image ``l = (k/255)^2.2`` averaged (area interpolation)
    to ``round(W/s) x round(H/s)``, at least 1 x 1; ``image`` as :func:`global_contrast_factor`
    takes it.
    """
    import cv2

    linear = (_display_grey(image) / 255.0) ** GCF_GAMMA
    h, w = linear.shape
    levels = []
    for size in GCF_SUPERPIXELS_PX:
        if size == 1:
            level = linear
        else:
            new_w, new_h = max(1, round(w / size)), max(1, round(h / size))
            level = cv2.resize(linear, (new_w, new_h), interpolation=cv2.INTER_AREA)
        levels.append((size, 100.0 * np.sqrt(np.maximum(level, 0.0))))
    return levels


def global_contrast_factor(image: np.ndarray) -> float:
    """Global contrast factor (Matkovic et al. 2005) of a display image.

    Steps: display grey ``k`` in [0, 255] -> linear ``l = (k/255)^2.2`` -> at each of the
    nine resolutions (superpixels of 1, 2, 4, 8, 16, 25, 50, 100, 200 px; the image is
    averaged in linear ``l`` with area interpolation to round(W/s) x round(H/s), at least
    1x1) perceptual luminance ``L = 100 sqrt(l)`` -> local contrast of each pixel = mean
    absolute difference of ``L`` to its existing 4-neighbours -> ``C_i`` = mean local
    contrast -> ``GCF = sum_i w_i C_i``.

    Parameters
    ----------
    image : ndarray
        Display-referred (gamma-encoded, as shown on screen) grey ``(H, W)`` or RGB
        ``(H, W, 3)``. uint8 is used as 0-255 directly; uint16 is scaled by 255/65535;
        float must lie in [0, 1] and is scaled by 255. RGB is turned into grey by Rec. 709
        luma on the display values, ``k = 0.2126 R + 0.7152 G + 0.0722 B``.

    Returns
    -------
    float
        GCF (dimensionless; about 1-10 for natural images, 0 for a constant image).
    """
    contrasts = [local_contrast_map(level).mean() for _, level in gcf_levels(image)]
    return float(np.dot(gcf_weights(), contrasts))


def gcf_by_region(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Where an image's GCF comes from: its terms ``w_i C_i`` split between two regions.

    At each of the nine resolutions the local contrast of every superpixel goes to ``inside``
    (its pixels all in ``mask``: at least 99 % of its area), ``outside`` (at most 1 %) or
    ``border`` (the rest: superpixels straddling the mask's outline, such as a skin line
    against direct exposure). Each share is the superpixels' summed local contrast over the
    level's pixel count, weighted, so the array sums to :func:`global_contrast_factor`.

    Parameters
    ----------
    image : ndarray
        Display image, as :func:`global_contrast_factor` takes it.
    mask : ndarray of bool, (H, W)

    Returns
    -------
    ndarray, (9, 3)
        Rows: the resolutions of :data:`GCF_SUPERPIXELS_PX`; columns: inside, outside, border.
    """
    import cv2

    inside = np.asarray(mask, np.float32)
    if inside.shape != np.asarray(image).shape[:2]:
        raise InputError("mask", f"shape {inside.shape} differs from the image's {np.asarray(image).shape[:2]}")
    parts = np.zeros((len(GCF_SUPERPIXELS_PX), 3))
    for row, ((_, level), weight) in enumerate(zip(gcf_levels(image), gcf_weights())):
        share = inside if level.shape == inside.shape else cv2.resize(
            inside, (level.shape[1], level.shape[0]), interpolation=cv2.INTER_AREA)
        local = local_contrast_map(level)
        for col, select in enumerate((share >= 0.99, share <= 0.01, (share > 0.01) & (share < 0.99))):
            parts[row, col] = weight * local[select].sum() / local.size
    return parts


def largest_box(mask: np.ndarray, *, step: int = 1, margin_px: int = 0) -> tuple[slice, slice]:
    """Largest axis-aligned box holding only ``True`` pixels of ``mask``, as ``(rows, cols)`` slices.

    Where a score such as the GCF is to be taken over the anatomy alone (no direct exposure,
    no collimator band). The classic largest rectangle in a histogram, row by row, on the
    ``step`` px grid; the box is shrunk by ``margin_px`` on each side. An empty mask gives an
    empty box.
    """
    grid = np.asarray(mask, bool)[::step, ::step]
    heights = np.zeros(grid.shape[1] + 1, np.int64)  # the trailing 0 empties the stack at each row's end
    best = (0, 0, 0, 0, 0)  # area, first row, last row + 1, first col, last col + 1
    for row in range(grid.shape[0]):
        heights[:-1] = np.where(grid[row], heights[:-1] + 1, 0)
        stack: list[int] = []
        for col, height in enumerate(heights.tolist()):
            while stack and heights[stack[-1]] >= height:
                top = int(heights[stack.pop()])
                start = stack[-1] + 1 if stack else 0
                if top * (col - start) > best[0]:
                    best = (top * (col - start), row + 1 - top, row + 1, start, col)
            stack.append(col)
    _, r0, r1, c0, c1 = best
    rows = slice(r0 * step + margin_px, max(r0 * step + margin_px, r1 * step - margin_px))
    cols = slice(c0 * step + margin_px, max(c0 * step + margin_px, c1 * step - margin_px))
    return rows, cols
