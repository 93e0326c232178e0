"""The synthetic DSLR frames: deterministic, physically consistent with their truth."""

import numpy as np

from napari_dslrxr.core.simulation.phantom import SCINTILLATOR_RGB_WEIGHTS, make_dslr_radiograph


def test_same_seed_same_frames_other_seed_differs():
    a = make_dslr_radiograph((160, 240), seed=3)
    b = make_dslr_radiograph((160, 240), seed=3)
    c = make_dslr_radiograph((160, 240), seed=4)
    assert np.array_equal(a.raw_rgb, b.raw_rgb) and np.array_equal(a.flat, b.flat)
    assert not np.array_equal(a.raw_rgb, c.raw_rgb)


def test_frames_match_truth_noise_tint_and_pulses():
    frames = make_dslr_radiograph((300, 400), seed=1, pulse_rate=1e-3)
    raw = frames.raw_rgb.astype(np.float64) - frames.black_level
    clean = frames.truth.clean_rgb
    inside = frames.truth.screen_mask & ~frames.truth.pulse_mask.any(axis=2)
    # Poisson + read noise: variance of (raw - clean) ~ gain * clean + read^2 (green channel)
    resid = (raw[..., 1] - clean[..., 1])[inside]
    expected_var = frames.truth.camera_gain_counts_per_photon * clean[..., 1][inside].mean() + 9.0
    assert 0.85 < resid.var() / expected_var < 1.15
    # green tint: channel means follow the scintillator weights
    means = clean[inside].mean(axis=0)
    assert np.allclose(means / means[1], SCINTILLATOR_RGB_WEIGHTS, rtol=1e-3)
    # pulses differ between channels and are bright
    masks = frames.truth.pulse_mask
    assert masks[..., 0].sum() > 0 and not np.array_equal(masks[..., 0], masks[..., 1])
    assert np.median(raw[..., 1][masks[..., 1]] - clean[..., 1][masks[..., 1]]) > 500
    # the screen is bright and the outside dark; the flat has no object
    assert raw[..., 1][frames.truth.screen_mask].mean() > 20 * abs(raw[..., 1][~frames.truth.screen_mask].mean())
    flat = frames.flat.astype(np.float64)[..., 1] - frames.black_level
    assert flat[frames.truth.screen_mask].mean() > 1.5 * raw[..., 1][frames.truth.screen_mask].mean()
