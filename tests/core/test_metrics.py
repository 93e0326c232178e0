"""PE and GCF against values worked out by hand on small arrays."""

from __future__ import annotations

import math

import numpy as np
import pytest

from napari_dslrxr.core.errors import InputError, ParameterError
from napari_dslrxr.core.metrics import (gcf_by_region, gcf_weights, global_contrast_factor, largest_box,
                                       percentage_error)


def w(i: int) -> float:
    """The paper's weight polynomial, written out again for the hand calculations."""
    return (-0.406385 * i / 9 + 0.334573) * i / 9 + 0.0877526


# --------------------------------------------------------------------------- PE


def test_pe_by_hand():
    x = np.array([[1.0, 2.0], [2.0, 4.0]])        # ||x|| = 5
    y = np.array([[1.0, 2.0], [2.0, 1.0]])        # ||x - y|| = 3
    assert percentage_error(x, y) == pytest.approx(60.0)
    assert percentage_error(x, x) == 0.0
    assert percentage_error(np.array([[3, 4], [0, 0]], np.uint16), np.zeros((2, 2), np.uint16)) == pytest.approx(100.0)


def test_pe_roi_and_mask_select_pixels():
    x = np.array([[3.0, 4.0, 10.0], [0.0, 1.0, 10.0], [5.0, 5.0, 5.0]])
    y = x.copy()
    y[0, 0] = 0.0       # error 3 inside the ROI below
    y[2, 2] = 100.0     # outside it
    # ROI rows 0-1, cols 0-1 holds 3, 4, 0, 1: norm sqrt(26)
    assert percentage_error(x, y, roi=(0, 0, 2, 2)) == pytest.approx(100 * 3 / math.sqrt(26))
    mask = np.zeros((3, 3), bool)
    mask[0, :2] = True  # 3 and 4: norm 5
    assert percentage_error(x, y, mask=mask) == pytest.approx(60.0)
    assert percentage_error(x, y, roi=(0, 1, 2, 3)) == 0.0


def test_pe_errors():
    x = np.ones((4, 4))
    with pytest.raises(InputError):
        percentage_error(x, np.ones((4, 5)))
    with pytest.raises(InputError):
        percentage_error(np.zeros((4, 4)), x)
    with pytest.raises(ParameterError):
        percentage_error(x, x, roi=(0, 0, 5, 4))
    with pytest.raises(InputError):
        percentage_error(x, x, mask=np.zeros((4, 4), bool))
    with pytest.raises(InputError):
        percentage_error(x, np.full((4, 4), np.nan))


# --------------------------------------------------------------------------- GCF


def test_weights_are_the_papers():
    expected = [0.11991, 0.14203, 0.15412, 0.15618, 0.14820, 0.13019, 0.10214, 0.06406, 0.01594]
    assert np.allclose(gcf_weights(), expected, atol=5e-6)
    assert w(1) == pytest.approx(0.1199103, abs=1e-7)


def test_gcf_constant_is_zero():
    for value in (0, 77, 255):
        assert global_contrast_factor(np.full((40, 30), value, np.uint8)) == pytest.approx(0.0, abs=1e-5)


def test_gcf_two_by_two_checker_by_hand():
    # L is 0 or 100; at full resolution every pixel has 2 neighbours, both 100 away: C1 = 100.
    # Every coarser level is a single superpixel: C = 0. GCF = w1 * 100.
    image = np.array([[0, 255], [255, 0]], np.uint8)
    assert global_contrast_factor(image) == pytest.approx(100 * w(1), rel=1e-9)
    # A 4x4 checker: C1 = 100; at 2 px superpixels all are the same mean: C2 = 0.
    checker = (np.indices((4, 4)).sum(0) % 2 * 255).astype(np.uint8)
    assert global_contrast_factor(checker) == pytest.approx(100 * w(1), rel=1e-6)


def test_gcf_vertical_edge_by_hand():
    # 4x4, left half black, right half white (L = 0 | 100).
    # Full resolution: only columns 1 and 2 have contrast: 100 over 4 neighbours (rows 1, 2)
    # or 3 neighbours (rows 0, 3): C1 = 2 * (25 + 25 + 100/3 + 100/3) / 16.
    # 2 px superpixels: [[0, 100], [0, 100]], 2 neighbours each, one 100 away: C2 = 50.
    # Coarser: one superpixel, 0.
    image = np.zeros((4, 4), np.uint8)
    image[:, 2:] = 255
    c1 = 2 * (25 + 25 + 100 / 3 + 100 / 3) / 16
    assert global_contrast_factor(image) == pytest.approx(w(1) * c1 + w(2) * 50, rel=1e-6)
    # Transpose-invariant, and the same for float in [0, 1] and uint16 full scale.
    assert global_contrast_factor(image.T) == pytest.approx(global_contrast_factor(image))
    assert global_contrast_factor(image / 255.0) == pytest.approx(global_contrast_factor(image))
    assert global_contrast_factor(image.astype(np.uint16) * 257) == pytest.approx(global_contrast_factor(image))


def test_gcf_by_region_splits_the_vertical_edge_by_hand():
    # The 4x4 edge above (C1 from columns 1 and 2, C2 = 50 from the two 2 px columns).
    image = np.zeros((4, 4), np.uint8)
    image[:, 2:] = 255
    c1 = 2 * (25 + 25 + 100 / 3 + 100 / 3) / 16
    left = np.zeros((4, 4), bool)
    left[:, :2] = True
    parts = gcf_by_region(image, left)  # columns: inside, outside, border
    # column 1 is inside, column 2 outside: half of C1 each; the 2 px superpixels likewise;
    # the single coarser superpixel is half in the mask: border, with no contrast
    assert parts[0] == pytest.approx([w(1) * c1 / 2, w(1) * c1 / 2, 0.0], rel=1e-9)
    assert parts[1] == pytest.approx([w(2) * 25, w(2) * 25, 0.0], rel=1e-6)
    assert np.all(parts[2:] == 0.0)
    three = np.zeros((4, 4), bool)
    three[:, :3] = True
    parts = gcf_by_region(image, three)
    # both contrasted columns inside; the right 2 px superpixels straddle the outline
    assert parts[0] == pytest.approx([w(1) * c1, 0.0, 0.0], rel=1e-9)
    assert parts[1] == pytest.approx([w(2) * 25, 0.0, w(2) * 25], rel=1e-6)
    assert parts.sum() == pytest.approx(global_contrast_factor(image), rel=1e-9)


def test_gcf_by_region_sums_to_the_gcf_and_swaps_with_the_mask(rng):
    image = rng.random((230, 310)) ** 2
    mask = np.zeros(image.shape, bool)
    mask[40:170, 60:250] = True
    parts = gcf_by_region(image, mask)
    assert parts.sum() == pytest.approx(global_contrast_factor(image), rel=1e-9)
    assert np.allclose(gcf_by_region(image, ~mask), parts[:, [1, 0, 2]], rtol=1e-9, atol=1e-12)
    with pytest.raises(InputError, match="mask"):
        gcf_by_region(image, mask[1:])


def test_gcf_grey_gamma_by_hand():
    # One pixel step between k = 0 and k = 128 on a 1x2 image: L = 100 sqrt((128/255)^2.2).
    image = np.array([[0, 128]], np.uint8)
    step = 100 * math.sqrt((128 / 255) ** 2.2)
    assert global_contrast_factor(image) == pytest.approx(w(1) * step, rel=1e-9)


def test_gcf_rgb_uses_rec709_luma():
    rgb = np.zeros((1, 2, 3), np.uint8)
    rgb[0, 1] = (0, 255, 0)  # luma 0.7152 * 255
    grey = np.array([[0.0, 0.7152]])
    assert global_contrast_factor(rgb) == pytest.approx(global_contrast_factor(grey), rel=1e-9)


def test_gcf_grows_with_contrast_and_matches_the_documented_checkerboard(rng):
    base = rng.integers(0, 256, (96, 128)).astype(np.float64)
    values = [global_contrast_factor(np.clip(a * (base - 127) + 127, 0, 255).astype(np.uint8))
              for a in (0.25, 0.5, 0.75, 1.0)]
    assert all(a < b for a, b in zip(values, values[1:], strict=False))
    # docs/algorithms/metrics.md, section 'Checks': a 64x64 checkerboard of grey levels 127 and 128 gives 0.048; by
    # hand, C1 = 100 ((128/255)^1.1 - (127/255)^1.1) and the coarser levels are flat except
    # for the 25 px level (64 px into 3 superpixels of 21.3 px do not average exactly).
    checker = (127 + np.indices((64, 64)).sum(0) % 2).astype(np.uint8)
    c1 = 100 * ((128 / 255) ** 1.1 - (127 / 255) ** 1.1)
    assert global_contrast_factor(checker) == pytest.approx(0.048, abs=0.001)
    assert global_contrast_factor(checker) == pytest.approx(w(1) * c1, rel=1e-3)


def test_gcf_errors():
    with pytest.raises(InputError):
        global_contrast_factor(np.full((8, 8), 1.5))
    with pytest.raises(InputError):
        global_contrast_factor(np.zeros((8, 8, 2)))
    with pytest.raises(InputError):
        global_contrast_factor(np.zeros((8, 8), np.int64))


def _largest_box_area_brute_force(mask: np.ndarray) -> int:
    """Every box tried: the largest all-True area (independent of the histogram scan)."""
    best = 0
    h, w = mask.shape
    for r0 in range(h):
        for r1 in range(r0 + 1, h + 1):
            for c0 in range(w):
                for c1 in range(c0 + 1, w + 1):
                    if (r1 - r0) * (c1 - c0) > best and mask[r0:r1, c0:c1].all():
                        best = (r1 - r0) * (c1 - c0)
    return best


def test_largest_box_matches_brute_force(rng):
    for _ in range(20):
        mask = rng.random((7, 9)) < 0.75
        rows, cols = largest_box(mask)
        area = (rows.stop - rows.start) * (cols.stop - cols.start)
        assert mask[rows, cols].all()
        assert area == _largest_box_area_brute_force(mask)


def test_largest_box_step_and_margin():
    mask = np.zeros((100, 120), bool)
    mask[10:90, 20:60] = True  # a tall box
    mask[40:50, 0:120] = True  # a wide thin one, smaller
    assert largest_box(mask) == (slice(10, 90), slice(20, 60))
    assert largest_box(mask, step=2, margin_px=4) == (slice(14, 86), slice(24, 56))
    assert largest_box(np.zeros((5, 5), bool)) == (slice(0, 0), slice(0, 0))
