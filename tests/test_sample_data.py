"""Sample data: generated at run time, deterministic, physically sensible; opens in napari."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dslrxr import _sample_data as samples
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph


def test_dslr_set_is_the_seeded_phantom():
    (dark, dark_kw, _), (flat, flat_kw, _), (radiograph, kw, kind) = samples.make_sample_dslr_set()
    again = make_dslr_radiograph(samples.PHANTOM_SHAPE, seed=samples.PHANTOM_SEED)
    np.testing.assert_array_equal(radiograph, again.raw_rgb)  # generated, same bytes every time
    assert kind == "image" and kw["rgb"] and radiograph.dtype == np.uint16
    assert radiograph.shape == flat.shape == dark.shape == (*samples.PHANTOM_SHAPE, 3)
    assert [k["name"] for k in (dark_kw, flat_kw, kw)] == ["dark", "flat", "DSLR radiograph"]
    # Dark is the black level; the flat's exposed screen is far brighter; pulses are present.
    black = kw["metadata"]["black_level"]
    assert abs(float(dark.mean()) - black) < 2.0
    screen = again.truth.screen_mask
    assert flat[..., 1][screen].mean() > black + 1000
    assert again.truth.pulse_mask.sum() > 50
    assert (radiograph[again.truth.pulse_mask] > again.truth.clean_rgb[again.truth.pulse_mask] + black).mean() > 0.9


@pytest.mark.gui
def test_open_samples_in_napari(make_napari_viewer):
    viewer = make_napari_viewer()
    viewer.open_sample("napari-dslrxr", "dslr_set")
    assert [layer.name for layer in viewer.layers] == ["dark", "flat", "DSLR radiograph"]
    assert viewer.layers["DSLR radiograph"].rgb


def test_edge_samples_have_the_geometry_and_the_blur_they_claim():
    from napari_dslrxr.core.simulation.edge_synthesis import synthesize_edge_image
    from napari_dslrxr.core.psf import PSFModel

    layers = samples.make_sample_edges()
    assert [kw["name"] for _, kw, _ in layers] == ["edge SOD 500 mm", "edge SOD 900 mm"]
    truth = PSFModel(**samples.EDGE_TRUTH)
    for data, kw, kind in layers:
        meta = kw["metadata"]
        assert kind == "image" and data.shape == (128, 256) and meta["psf_truth"] == samples.EDGE_TRUTH
        sod, sdd = meta["source_to_object_mm"], meta["source_to_detector_mm"]
        expected = synthesize_edge_image(truth, sod, sdd, (128, 128), 3.0, low=0.1, high=1.0, supersample=4)
        noise = data[:, :128] / samples.EDGE_BRIGHT_COUNTS - expected
        # Poisson noise only: mean zero, variance = expected / counts.
        assert abs(noise.mean()) < 2e-3
        assert np.var(noise) == pytest.approx(np.mean(expected) / samples.EDGE_BRIGHT_COUNTS, rel=0.1)
    # The nearer object (SOD 500) has the wider focal-spot blur: its edge rises more slowly.
    (near, _, _), (far, _, _) = layers
    rise = [np.abs(np.diff(img[40:90, 40:90].mean(axis=0))).max() for img in (near, far)]
    assert rise[0] < 0.8 * rise[1]


def test_scene_sample_recording_is_the_scene_plus_the_hidden_effect():
    from napari_dslrxr.core.simulation.simulator import parse_scene, simulate_recording

    (thickness, t_kw, _), (recording, r_kw, _) = samples.make_sample_scene()
    meta = r_kw["metadata"]
    assert meta["thickness_layer"] == t_kw["name"] and recording.shape == thickness.shape == samples.SCENE_SHAPE
    scene = parse_scene(meta["scene_table"], thickness=thickness)
    assert scene.effects == {}  # the scene the user believes in has no glare ...
    again, truth = simulate_recording(scene, effects=meta["hidden_effects"], seed=samples.SCENE_SEED)
    np.testing.assert_array_equal(recording, again)  # ... the recording has it
    plain, plain_truth = simulate_recording(scene, seed=samples.SCENE_SEED)
    # Veiling glare adds light under the opaque block: expected level there rises.
    block = thickness > 20
    assert (truth["expected"][block] - plain_truth["expected"][block]).mean() > 5.0
