"""Tests of the imaging-chain simulator and the scene file."""

from __future__ import annotations

import numpy as np
import pytest

from scenes import PHANTOM_SCENE_TOML
from napari_dslrxr.core import io
from napari_dslrxr.core.errors import InputError, ParameterError
from napari_dslrxr.core.simulation.simulator import (ChainModel, effective_attenuation_per_mm, load_scene,
                                                     parse_scene, phantom_thickness_mm, simulate_recording)

SCENE = PHANTOM_SCENE_TOML + """[noise]
poisson_gain_dn = 1.2
read_noise_dn = 6.3
"""


@pytest.fixture
def scene_file(tmp_path):
    io.write_tiff(tmp_path / "thickness.tif", phantom_thickness_mm((64, 64)))
    path = tmp_path / "scene.toml"
    path.write_text(SCENE)
    return path


def test_attenuation_table_matches_nist_at_the_effective_energy():
    # aluminium at 30 keV (E_eff = 0.5 * 60 kVp): mu/rho 1.128 cm2/g * 2.699 g/cm3 = 0.3044 /mm
    assert effective_attenuation_per_mm("aluminium", 60) == pytest.approx(0.30445, rel=1e-4)
    # water at 40 keV: 0.2683 cm2/g -> 0.02683 /mm
    assert effective_attenuation_per_mm("water", 80) == pytest.approx(0.02683, rel=1e-4)
    assert effective_attenuation_per_mm("copper", 60) > 10 * effective_attenuation_per_mm("aluminium", 60)


def test_scene_loads_and_beer_lambert_holds_in_flat_regions(scene_file):
    scene = load_scene(scene_file)
    assert scene.shape == (64, 64)
    assert scene.magnification_minus_one == pytest.approx(0.2)
    expected = ChainModel(scene.thickness_mm, scene.grid()).expected(scene.base_params())
    # open field: offset + gain; inside the wedge step far from edges: offset + gain exp(-mu t)
    assert expected[3, 30] == pytest.approx(scene.offset_dn + scene.gain_dn, rel=1e-4)
    from scipy import ndimage

    t_map = scene.thickness_mm
    flat = (ndimage.maximum_filter(t_map, 11) == ndimage.minimum_filter(t_map, 11)) & (t_map > 0)
    rows, cols = np.nonzero(flat)
    assert rows.size > 10
    predicted = scene.offset_dn + scene.gain_dn * np.exp(-scene.mu_per_mm * t_map[rows, cols])
    np.testing.assert_allclose(expected[rows, cols], predicted, rtol=2e-3)


def test_noise_matches_the_poisson_gaussian_model(scene_file):
    scene = load_scene(scene_file)
    scene.thickness_mm = np.zeros((128, 128))
    y, truth = simulate_recording(scene, seed=3)
    assert y.dtype == np.float32
    expected_var = scene.poisson_gain_dn * scene.gain_dn + scene.read_noise_dn**2
    assert np.var(y - truth["expected"]) == pytest.approx(expected_var, rel=0.03)
    y2, _ = simulate_recording(scene, seed=3)
    assert np.array_equal(y, y2)  # deterministic


def test_pulses_are_sparse_positive_and_flagged(scene_file):
    scene = load_scene(scene_file)
    scene.pulse_rate_per_px = 2e-3
    y, truth = simulate_recording(scene, seed=1)
    mask = truth["pulse_mask"]
    assert 0 < mask.mean() < 0.05
    assert np.median((y - truth["expected"])[mask]) > 5 * scene.read_noise_dn


def test_focal_spot_blur_scales_with_magnification(scene_file):
    scene = load_scene(scene_file)

    def edge_width(sod):
        scene.source_to_object_mm = sod
        scene.focal_spot_sigma_mm = 1.0
        scene.detector_sigma_mm = 0.01
        e = ChainModel(scene.thickness_mm, scene.grid()).expected(scene.base_params())
        return np.abs(np.diff(e[10:15, :].mean(axis=0))).max()

    # steeper edge (larger max gradient) when the object is close to the detector (M - 1 small)
    assert edge_width(1190.0) > 2 * edge_width(800.0)


def test_scene_errors_are_one_line(tmp_path, scene_file):
    bad = tmp_path / "bad.toml"
    bad.write_text(SCENE.replace("aluminium", "aluminum_foil"))
    with pytest.raises(ParameterError, match="unknown material"):
        load_scene(bad)
    bad.write_text(SCENE.replace("pixel_pitch_mm = 0.1\n", ""))
    with pytest.raises(ParameterError, match=r"\[geometry\] is missing pixel_pitch_mm"):
        load_scene(bad)
    bad.write_text(SCENE.replace("thickness.tif", "nope.tif"))
    with pytest.raises(InputError, match="not found"):
        load_scene(bad)
    bad.write_text(SCENE + "[effects.glare]\neta = 0.1\n")
    with pytest.raises(ParameterError, match="unknown effect"):
        load_scene(bad)
    bad.write_text("[geometry\n")
    with pytest.raises(InputError, match="not valid TOML"):
        load_scene(bad)


def test_scene_effects(tmp_path, scene_file):
    path = tmp_path / "fx.toml"
    path.write_text(SCENE + "[effects.veiling_glare]\neta = 0.05\nrange_mm = 0.5\n")
    scene = load_scene(path)
    assert scene.effects["veiling_glare"]["eta"] == 0.05


def test_wrong_thickness_shape_rejected():
    with pytest.raises(InputError, match="2-D"):
        parse_scene({"geometry": {"source_to_detector_mm": 1, "source_to_object_mm": 1, "pixel_pitch_mm": 1},
                     "object": {"material": "water"}, "source": {"kvp": 60}}, thickness=np.zeros((4, 4, 3)))


def test_cfa_option_applies_rggb_plane_gains(scene_file):
    scene = load_scene(scene_file)
    scene.thickness_mm = np.zeros((64, 64))
    scene.cfa = True
    y, truth = simulate_recording(scene, seed=2)
    signal = truth["expected"] - scene.offset_dn
    assert signal[0::2, 0::2].mean() == pytest.approx(0.15 * signal[0::2, 1::2].mean(), rel=1e-6)
    assert signal[1::2, 1::2].mean() == pytest.approx(0.10 * signal[1::2, 0::2].mean(), rel=1e-6)


def _direct_binned_model(thickness, grid, pre_blur_px, base, terms=()):
    """The model at one parameter point on a fresh ChainModel: its first transmission is always
    computed directly on the fine grid (no series)."""
    return ChainModel(thickness, grid, pre_blur_px).expected(base, list(terms))


@pytest.mark.parametrize("relative_change", [1e-7, 0.01, -0.2, 0.45, 1.0])
def test_binned_model_series_in_mu_equals_the_direct_transmission(relative_change):
    # A binned fit evaluates many attenuations: after the first, the coarse transmission and the
    # scatter source come from a series in mu. They must equal the direct fine-grid blur and
    # block average at every mu (near and far from the series' centre, where a new one is made).
    from napari_dslrxr.core.simulation.physics_terms import ChainGrid, get_term

    rng = np.random.default_rng(7)
    thickness = phantom_thickness_mm((96, 96)) + rng.uniform(0.0, 2.0, (96, 96))  # no two pixels alike
    grid = ChainGrid((24, 24), 4, 0.2, 0.2, 1200.0)
    base = {"offset_dn": 100.0, "gain_dn": 3000.0, "mu_per_mm": 0.08, "detector_sigma_mm": 0.3,
            "focal_spot_sigma_mm": 0.1}
    scatter = [(get_term("scatter"), {"amplitude": 0.3, "sigma_mm": 2.0})]
    model = ChainModel(thickness, grid, 0.6)
    model.expected(base, scatter)  # the first mu: direct
    moved = {**base, "mu_per_mm": base["mu_per_mm"] * (1.0 + relative_change)}
    for point in (moved, base, moved):  # the series, there and back
        through_series = model.expected(point, scatter)
        direct = _direct_binned_model(thickness, grid, 0.6, point, scatter)
        assert model._expansion is not None  # the series made this one, not the direct path
        np.testing.assert_allclose(through_series, direct, rtol=1e-12, atol=0.0)
