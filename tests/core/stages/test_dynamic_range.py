"""Dynamic-range reduction: large-area range shrinks, detail kept; no leakage from outside."""

import numpy as np
import pytest

from napari_dslrxr.core.stages.dynamic_range import (DynamicRangeParams, edge_aware_lowpass, masked_lowpass, reduce_dynamic_range,
                                              sigmoid_lut)


def test_latitude_compresses_large_areas_and_keeps_detail():
    yy, xx = np.mgrid[0:300, 0:300].astype(np.float32)
    background = 0.8 * (xx > 150)  # two large areas (thin / thick part)
    detail = 0.05 * (np.sin(xx / 2.0) > 0)  # fine structure
    img = background + detail
    for edge_step in (0.0, 0.3):  # plain blur; edge-aware low-pass (detail well below its edge step)
        out = reduce_dynamic_range(img, None, DynamicRangeParams(latitude=0.5, detail_gain=1.2, kernel_fraction=0.1,
                                                                 edge_step=edge_step))
        _check_compressed_and_detail_kept(img, out)


def _check_compressed_and_detail_kept(img, out):
    left, right = np.s_[100:200, 20:120], np.s_[100:200, 180:280]
    assert abs(out[right].mean() - out[left].mean()) < 0.6 * abs(img[right].mean() - img[left].mean())
    assert out[left].std() >= 1.15 * img[left].std()  # detail gain 1.2 on fine structure


def test_edge_aware_lowpass_compresses_a_strong_step_without_halo():
    img = np.full((120, 400), 0.1, np.float32)
    img[:, 200:] = 1.3  # collimator-like step, 6x the default edge step
    params = DynamicRangeParams(latitude=0.6)
    out = reduce_dynamic_range(img, None, params).mean(axis=0)
    box = reduce_dynamic_range(img, None, DynamicRangeParams(latitude=0.6, edge_step=0.0)).mean(axis=0)

    def halo(p):  # overshoot + undershoot beyond the far plateaus, relative to the output step
        return ((p.max() - p[-1]) + (p[0] - p.min())) / (p[-1] - p[0])

    assert halo(box) > 0.3  # the plain blur's halo (unsharp-mask overshoot); measured 0.59
    assert halo(out) < 0.03  # measured 0.016
    assert abs((out[-1] - out[0]) - 0.6 * 1.2) < 0.03  # the step itself is compressed by latitude


def test_edge_aware_lowpass_ignores_outside_pixels():
    img = np.full((200, 200), 0.3, np.float32)
    img[:, :50] = 5.0
    mask = np.zeros(img.shape, bool)
    mask[:, 50:] = True
    low = edge_aware_lowpass(img, mask, 20.0, 0.1)
    assert np.abs(low[:, 50:60] - 0.3).max() < 1e-3


def test_masked_lowpass_ignores_outside_pixels():
    img = np.full((200, 200), 0.3, np.float32)
    img[:, :50] = 5.0  # bright collimator outside the mask
    mask = np.zeros(img.shape, bool)
    mask[:, 50:] = True
    low = masked_lowpass(img, mask, 41)
    assert np.abs(low[:, 50:60] - 0.3).max() < 1e-3


def test_sigmoid_maps_voi_ends_and_is_monotone():
    x = np.linspace(-0.5, 1.5, 101, dtype=np.float32)
    y = sigmoid_lut(x)
    assert np.all(np.diff(y) >= 0) and y.min() >= 0 and y.max() <= 1
    ends = sigmoid_lut(np.array([0.0, 1.0], np.float32))
    assert np.allclose(ends, [0.02, 0.98], atol=1e-5)


def test_foot_lift_is_a_toe_that_keeps_the_order():
    """Display 0 goes to the floor, the curve is untouched from 4 x floor up, and stays increasing."""
    from napari_dslrxr.core.stages.dynamic_range import FOOT_TOE_SPAN, lift_anatomy_foot

    y = np.linspace(0.0, 1.0, 1001, dtype=np.float32)
    lifted = y.copy()
    lift_anatomy_foot(lifted, np.ones_like(y), 0.12)
    assert lifted[0] == pytest.approx(0.12, abs=1e-6)
    above = y >= FOOT_TOE_SPAN * 0.12
    assert np.array_equal(lifted[above], y[above])
    slope = np.diff(lifted) / np.diff(y)
    assert slope.min() >= 1 - 2 / FOOT_TOE_SPAN - 1e-3  # at least half the curve's: nothing flattened
    # where the weight is 0 (direct exposure) or the floor is 0, nothing changes
    kept = y.copy()
    lift_anatomy_foot(kept, np.zeros_like(y), 0.12)
    lift_anatomy_foot(kept, np.ones_like(y), 0.0)
    assert np.array_equal(kept, y)
