"""Helpers of the widgets that need no display: visible region and robust display limits."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from napari_dslrxr._widgets._layers import robust_limits, visible_region


def fake_viewer(centre_rc, zoom, canvas_hw):
    camera = SimpleNamespace(center=(0.0, *centre_rc), zoom=zoom)
    return SimpleNamespace(scene=SimpleNamespace(camera=camera), canvas=SimpleNamespace(size=canvas_hw))


def fake_layer(shape, scale=(1.0, 1.0), translate=(0.0, 0.0)):
    return SimpleNamespace(data=np.zeros(shape), scale=np.asarray(scale), translate=np.asarray(translate))


def test_visible_region_follows_camera_scale_and_translate():
    # 600 x 800 canvas at zoom 4 shows 150 x 200 world units around the centre.
    viewer = fake_viewer((100.0, 300.0), 4.0, (600, 800))
    rows, cols = visible_region(viewer, fake_layer((1000, 1000)))
    assert (rows.start, rows.stop, cols.start, cols.stop) == (25, 176, 200, 401)
    # Pixels of 0.5 world units, image shifted by (10, 20): twice as many pixels, offset.
    rows, cols = visible_region(viewer, fake_layer((1000, 1000), (0.5, 0.5), (10.0, 20.0)))
    assert (rows.start, rows.stop) == (30, 331) and (cols.start, cols.stop) == (360, 761)
    # Margins are added and everything is clipped to the image.
    rows, cols = visible_region(fake_viewer((5.0, 5.0), 1.0, (600, 800)), fake_layer((100, 120)), margin_px=8)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (0, 100, 0, 120)


def test_robust_limits_ignore_outliers():
    data = np.full((100, 100), 10.0)
    data[:50] = 20.0
    data[0, :5] = 1e6  # pulses
    lo, hi = robust_limits(data)
    assert lo == pytest.approx(10.0) and hi == pytest.approx(20.0)
    assert robust_limits(np.zeros((4, 4))) == (0.0, 1.0)


@pytest.mark.gui
def test_colour_layer_of_counts_has_a_thumbnail_scaled_by_its_contrast_limits(make_napari_viewer):
    """napari's own thumbnail of a uint16 colour layer is white; a result layer's follows its
    contrast limits as the canvas does: the left half (at the lower limit) black, the right
    half (at the upper limit) white."""
    from napari_dslrxr._widgets._layers import show_layer

    viewer = make_napari_viewer()
    counts = np.full((64, 64, 3), 1000, np.uint16)
    counts[:, 32:] = 3000
    layer = show_layer(viewer, counts, "cleaned", "image", rgb=True, contrast_limits=(1000.0, 3000.0))
    rgb = layer.thumbnail[..., :3].astype(int)
    assert rgb[:, :15].max() == 0 and rgb[:, 17:].min() == 255
    layer.contrast_limits = (0.0, 6000.0)  # the thumbnail follows (half grey on the right)
    assert 120 <= layer.thumbnail[:, 20, 0].min() <= layer.thumbnail[:, 20, 0].max() <= 135


def test_text_labels_are_revealed_a_few_new_glyphs_per_step_then_whole_at_the_layer_opacity():
    from napari_dslrxr._widgets._layers import reveal_text_steps

    texts = ["before (scene as given)", "after (+ nothing found)"]
    layer = SimpleNamespace(opacity=0.7, visible=False, features=None)
    shown: list[list[str]] = []
    for _ in reveal_text_steps(layer, "what", texts, glyphs_per_step=4):
        assert layer.visible and layer.opacity == 0.0  # drawn, not yet seen
        shown.append(list(layer.features["what"]))
    assert shown[0] == ["", ""]  # the first draw has no text
    drawn: set[str] = set()
    for labels in shown[1:] + [texts]:
        new = set("".join(labels)) - drawn
        assert 0 < len(new) <= 4
        assert all(text.startswith(label) for text, label in zip(texts, labels, strict=True))
        drawn |= new
    assert layer.features == {"what": texts} and layer.opacity == 0.7 and layer.visible
    assert drawn == set("".join(texts))
