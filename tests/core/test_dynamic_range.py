"""Dynamic-range reduction: large-area range shrinks, detail kept; no leakage from outside."""

import numpy as np

from napari_dslrxr.core.dynamic_range import DynamicRangeParams, masked_lowpass, reduce_dynamic_range, sigmoid_lut


def test_latitude_compresses_large_areas_and_keeps_detail():
    yy, xx = np.mgrid[0:300, 0:300].astype(np.float32)
    background = 0.8 * (xx > 150)  # two large areas (thin / thick part)
    detail = 0.05 * (np.sin(xx / 2.0) > 0)  # fine structure
    img = background + detail
    out = reduce_dynamic_range(img, None, DynamicRangeParams(latitude=0.5, detail_gain=1.2, kernel_fraction=0.1))
    left, right = np.s_[100:200, 20:120], np.s_[100:200, 180:280]
    assert abs(out[right].mean() - out[left].mean()) < 0.6 * abs(img[right].mean() - img[left].mean())
    assert out[left].std() >= 1.15 * img[left].std()  # detail gain 1.2 on fine structure


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
