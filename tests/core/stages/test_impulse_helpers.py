"""Fast helpers of the impulse stage give the same sets as their direct definitions."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dslrxr.core.stages.impulse.detection import _NEAR_BIT, _near


@pytest.mark.parametrize("n_others", [3, 40, 2000])  # few: neighbourhood search; many: bitmap
def test_near_is_the_chebyshev_neighbourhood_at_borders_too(n_others):
    rng = np.random.default_rng(n_others)
    h, w, radius = 37, 29, 5
    pixels = np.flatnonzero(rng.random(h * w) < 0.3)
    others = rng.integers(0, h * w, n_others)
    others[:2] = [0, h * w - 1]  # corners: the replicated border must not reach farther
    flags = np.zeros(h * w, np.uint8)
    flags[::7] = 1  # the growth's marks (0 or 1) must be left as they were
    before = flags.copy()
    got = _near(pixels, others, radius, (h, w), flags)
    pr, pc = np.divmod(pixels, w)
    orow, ocol = np.divmod(others, w)
    dist = np.maximum(np.abs(pr[:, None] - orow[None, :]), np.abs(pc[:, None] - ocol[None, :]))
    np.testing.assert_array_equal(got, (dist <= radius).any(axis=1))
    np.testing.assert_array_equal(flags, before)
    assert not (flags & _NEAR_BIT).any()


def test_hsv_planes_are_opencvs_over_several_row_blocks():
    import cv2

    from napari_dslrxr.core.stages.impulse.colour import rgb_to_hsv_counts

    rgb = np.random.default_rng(1).integers(0, 4000, (999, 1234, 3)).astype(np.uint16)  # two blocks
    hue, sat, val = rgb_to_hsv_counts(rgb)
    ref = cv2.cvtColor(rgb.astype(np.float32), cv2.COLOR_RGB2HSV)
    np.testing.assert_array_equal(hue, ref[..., 0] * np.float32(1.0 / 360.0))
    np.testing.assert_array_equal(sat, ref[..., 1])
    np.testing.assert_array_equal(val, ref[..., 2])


def test_ring_median_of_an_interleaved_channel_is_that_of_its_copy():
    from napari_dslrxr.core.stages.impulse.neighbourhoods import _ring_median_at

    rgb = np.random.default_rng(2).integers(0, 4000, (40, 50, 3)).astype(np.uint16)
    rows, cols = np.divmod(np.arange(0, 40 * 50, 7), 50)  # borders included
    for c in range(3):
        for size in (3, 5):
            np.testing.assert_array_equal(_ring_median_at(rgb, rows, cols, size, channel=c),
                                          _ring_median_at(np.ascontiguousarray(rgb[..., c]), rows, cols, size))


@pytest.mark.parametrize("size_px", [3, 5, 7, 9])
def test_window_values_are_the_flat_gather_at_borders_too(size_px):
    from napari_dslrxr.core.stages.impulse.neighbourhoods import _window_flat_indices, _window_values

    x = np.random.default_rng(size_px).normal(size=(23, 31)).astype(np.float32)
    rows, cols = np.divmod(np.arange(23 * 31), 31)
    np.testing.assert_array_equal(_window_values(x, rows, cols, size_px),
                                  x.ravel()[_window_flat_indices(rows, cols, size_px, x.shape)])
    inner = (rows > 5) & (rows < 17) & (cols > 5) & (cols < 25)  # the block-copy path alone
    np.testing.assert_array_equal(_window_values(x, rows[inner], cols[inner], size_px),
                                  x.ravel()[_window_flat_indices(rows[inner], cols[inner], size_px, x.shape)])


@pytest.mark.parametrize("smallest_px, symmetric, spread_about", [(3, False, "median"), (7, True, "median"),
                                                                 (7, True, "plane")])
def test_masked_median_with_marked_pixels_is_that_of_the_mask(smallest_px, symmetric, spread_about):
    from napari_dslrxr.core.stages.impulse.neighbourhoods import _masked_median_at

    rng = np.random.default_rng(smallest_px)
    x = rng.normal(100, 5, (41, 53)).astype(np.float32)
    excluded = (rng.random(x.shape) < 0.35).astype(np.uint8)  # many: every window size is used
    excluded[10:20, 10:20] = 1  # a hole no 3x3-7x7 window around its centre can fill
    rows, cols = np.divmod(np.arange(x.size), x.shape[1])  # borders included
    kwargs = dict(smallest_px=smallest_px, symmetric=symmetric, with_spread=True, spread_about=spread_about)
    before = x.copy()
    ref = _masked_median_at(x, excluded, rows, cols, **kwargs)
    got = _masked_median_at(x, excluded, rows, cols, marked_px=np.flatnonzero(excluded), **kwargs)
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])
    np.testing.assert_array_equal(x, before)  # the marked pixels are restored


@pytest.mark.parametrize("weighted", [False, True])
def test_exact_test_skipping_the_spread_where_it_cannot_matter_gives_the_same_seeds(weighted):
    from napari_dslrxr.core.stages.impulse import ImpulseParams
    from napari_dslrxr.core.stages.impulse.detection import _exact_test
    from napari_dslrxr.core.stages.impulse.noise_model import _NoiseModel

    rng = np.random.default_rng(5)
    x = rng.poisson(1000, (120, 150)).astype(np.float32)
    x[:, 75:] += 3000  # an edge: the spread's floor decides there
    x[rng.integers(0, 120, 300), rng.integers(0, 150, 300)] += rng.uniform(50, 2000, 300).astype(np.float32)
    weight = rng.uniform(0.2, 3.0, x.shape).astype(np.float32) if weighted else None
    model = _NoiseModel(a=1.9, b=4.0, pulse_rate=0.003, pulse_density=1.0 / 6000, polarity=1, var_floor=4.0)
    params = ImpulseParams()
    candidates = np.arange(x.size)
    ref = _exact_test(x, candidates, model, params, False, weight)
    got = _exact_test(x, candidates, model, params, False, weight, float(x.max()) - float(x.min()))
    np.testing.assert_array_equal(got, ref)
    assert 100 < ref.size < x.size // 10
