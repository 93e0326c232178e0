"""Screen detection on rotated / keystoned quadrilaterals; VOI window."""

import cv2
import numpy as np
import pytest

from napari_dslrxr.core.errors import ParameterError
from napari_dslrxr.core.region import RegionParams, detect_screen, order_corners, rectify, voi_window


def _quad_frame(rng, shape, corners):
    h, w = shape
    mask = np.zeros(shape, np.uint8)
    cv2.fillPoly(mask, [np.round(corners * 16).astype(np.int32)], 1, shift=4)
    truth = mask.astype(bool)
    bright = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), 1.5) * 3000.0
    # some dark "object" inside the screen (attenuating), not touching the edge
    yy, xx = np.mgrid[0:h, 0:w]
    centre = corners.mean(axis=0)
    blob = ((xx - centre[0]) ** 2 / (0.2 * w) ** 2 + (yy - centre[1]) ** 2 / (0.2 * h) ** 2) < 1
    bright[blob] *= 0.2
    noisy = rng.poisson(np.maximum(bright, 0) + 20.0).astype(np.float32) + rng.normal(0, 5, shape)
    return noisy.astype(np.float32), truth


@pytest.mark.parametrize("shape,rotation,keystone", [((400, 600), 3.0, 0.15), ((512, 512), -8.0, 0.25),
                                                     ((360, 480), 15.0, 0.05), ((300, 500), 0.0, 0.3)])
def test_corner_error_and_iou(rng, shape, rotation, keystone):
    h, w = shape
    half_w, half_h = 0.38 * w, 0.38 * h
    corners = np.array([[-half_w * (1 - keystone), -half_h], [half_w * (1 - keystone), -half_h],
                        [half_w, half_h], [-half_w, half_h]])
    a = np.deg2rad(rotation)
    corners = corners @ np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]]) + [w / 2, h / 2]
    frame, truth = _quad_frame(rng, shape, corners)
    region = detect_screen(frame, RegionParams(shrink_fraction=0.0))
    diagonal = np.hypot(h, w)
    error = np.hypot(*(region.polygon_xy - order_corners(corners)).T).max()
    iou = (region.mask & truth).sum() / (region.mask | truth).sum()
    assert error < 0.005 * diagonal, error
    assert iou > 0.98, iou
    # a naive bounding box of the thresholded image is much worse on keystoned screens
    ys, xs = np.nonzero(frame > 1500)
    box = np.zeros(shape, bool)
    box[ys.min():ys.max() + 1, xs.min():xs.max() + 1] = True
    assert (box & truth).sum() / (box | truth).sum() < iou


def test_user_polygon_overrides_detection(rng):
    frame = rng.normal(100, 5, (100, 120)).astype(np.float32)
    poly = [[10, 10], [100, 12], [98, 90], [12, 88]]
    region = detect_screen(frame, RegionParams(polygon_xy=poly))
    assert not region.detected and np.allclose(region.polygon_xy, poly)
    assert region.mask[50, 50] and not region.mask[5, 5]
    with pytest.raises(ParameterError, match="4"):
        detect_screen(frame, RegionParams(polygon_xy=[[0, 0], [1, 1]]))


def test_voi_excludes_direct_exposure(rng):
    obj = rng.normal(0.6, 0.1, 60000)
    direct = rng.normal(0.05, 0.01, 40000)  # large unattenuated background mode
    lo, hi = voi_window(np.concatenate([obj, direct]))
    assert lo > 0.25  # window starts at the object, not the background
    lo2, _ = voi_window(np.concatenate([obj, direct]), exclude_direct_exposure=False)
    assert lo2 < 0.1


def test_rectify_restores_rectangle():
    img = np.zeros((200, 300), np.float32)
    quad = np.array([[60, 40], [240, 50], [260, 170], [40, 160]], np.float64)
    cv2.fillPoly(img, [quad.astype(np.int32)], 1.0)
    out = rectify(img, quad)
    assert out[2:-2, 2:-2].min() > 0.9
