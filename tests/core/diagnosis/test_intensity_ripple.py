"""The intensity-ripple test of the final residual (an ADC ripple: periodic in the recorded DN).

A ripple of the recorded value acts after the noise, so only its noise-smoothed mean
``A exp(-2π²σ²/P²) sin(2πμ/P)`` shows against the expected intensity ``μ``; 48 quantile bins of
``μ`` average a ripple whose period is about a bin width (the held-out ADC ripple of the
diagnosis study at SNR ~40 was reported as nothing missing).
"""

from __future__ import annotations

import numpy as np
import pytest

from napari_dslrxr.core.diagnosis.structure import N_TESTS, _intensity_ripple_test, structure_tests

SHAPE = (192, 192)
OFFSET_DN = 200.0
LEVEL = 1e-3 / N_TESTS


def _scene():
    """Expected intensity from 205 to 3205 DN (quadratic, so dark pixels are many) and the
    Poisson-Gaussian noise σ of the study's camera (1.2 DN²/DN, read noise 6.3 DN)."""
    rows, cols = np.mgrid[0:SHAPE[0], 0:SHAPE[1]]
    u = (cols + 0.5 * rows) / (1.5 * SHAPE[1])
    expected_dn = OFFSET_DN + 5.0 + 3000.0 * u**2
    sd_dn = np.sqrt(1.2 * (expected_dn - OFFSET_DN) + 6.3**2)
    return expected_dn, sd_dn


def _run(z, expected_dn, sd_dn):
    zero = np.zeros(SHAPE)
    mask = np.ones(SHAPE, bool)
    return structure_tests(z, mask, float(np.sum(z**2)), float(z.size), expected_dn, zero, zero, 32, 1,
                           noise_sd_dn=sd_dn)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_adc_ripple_of_the_noisy_value_is_found_with_its_period(seed):
    expected_dn, sd_dn = _scene()
    rng = np.random.default_rng(seed)
    analog_dn = expected_dn + sd_dn * rng.standard_normal(SHAPE)
    period_dn = 97.0
    # 2 DN: a third of the read noise, attenuated to 1 % of itself in the open field (σ 60 DN)
    recorded_dn = analog_dn + 2.0 * np.sin(2 * np.pi * analog_dn / period_dn)
    z = (recorded_dn - expected_dn) / sd_dn
    out = _run(z, expected_dn, sd_dn)
    ripple = out["tests"]["intensity_ripple"]
    assert ripple["p"] < LEVEL, ripple
    assert abs(ripple["period_dn"] - period_dn) < 0.1 * period_dn, ripple
    assert "intensity_ripple" in out["failed"]
    assert any(s.startswith("intensity ripple (period ~") for s in out["signatures"]), out["signatures"]


def test_white_noise_with_a_smooth_intensity_trend_is_not_a_ripple():
    # a residual non-linearity (0.3 σ over the span) is the binned intensity test's business
    expected_dn, sd_dn = _scene()
    trend = 0.3 * np.cos(np.pi * (expected_dn - expected_dn.min()) / np.ptp(expected_dn))
    ps = []
    for seed in range(30):
        z = np.random.default_rng(100 + seed).standard_normal(SHAPE) + trend
        out = _run(z, expected_dn, sd_dn)
        assert "intensity_ripple" not in out["failed"]
        ps.append(out["tests"]["intensity_ripple"]["p"])
    # the Bonferroni bound over the (oversampled) trial periods is conservative, not blind:
    # p-values of the maximum sit at or above uniform
    assert np.mean(np.array(ps) < 0.1) <= 0.2


def test_ripple_statistic_is_chi2_with_two_degrees_of_freedom_per_period():
    # each period's statistic is χ²(2) for white unit-variance z; the maximum over n periods
    expected_dn, sd_dn = _scene()
    stats, counts = [], []
    for seed in range(40):
        z = np.random.default_rng(500 + seed).standard_normal(SHAPE)
        p, stat, _, n = _intensity_ripple_test(z.ravel(), expected_dn.ravel(), sd_dn.ravel())
        stats.append(stat)
        counts.append(n)
    # is then below 2 ln(n / 0.01) in (nearly) every null, and above the median of a single
    # χ²(2) (2 ln 2) in every one: neither anti-conservative nor blind
    assert np.mean(np.array(stats) > 2 * np.log(np.array(counts) / 0.01)) <= 0.05
    assert min(stats) > 2 * np.log(2.0)


def test_constant_intensity_has_no_ripple_test():
    z = np.random.default_rng(4).standard_normal(SHAPE)
    p, stat, period, n = _intensity_ripple_test(z.ravel(), np.full(z.size, 1000.0), None)
    assert (p, n) == (1.0, 0)


def test_phase_profile_shows_the_ripple_and_stays_flat_on_noise():
    # the report's evidence: the residual folded on the intensity's phase at the found period
    from napari_dslrxr.core.diagnosis.structure import ripple_phase_profile

    expected_dn, sd_dn = _scene()
    rng = np.random.default_rng(1)
    analog_dn = expected_dn + sd_dn * rng.standard_normal(SHAPE)
    recorded_dn = analog_dn + 2.0 * np.sin(2 * np.pi * analog_dn / 97.0)
    rippled = ripple_phase_profile(((recorded_dn - expected_dn) / sd_dn).ravel(), expected_dn.ravel(),
                                   sd_dn.ravel(), 1, 97.0)
    noise = [ripple_phase_profile(np.random.default_rng(700 + seed).standard_normal(SHAPE).ravel(),
                                  expected_dn.ravel(), sd_dn.ravel(), 1, 97.0) for seed in range(10)]
    # Σ bin_z² is χ²(16) under the null: 39.3 is its 0.1 % point
    assert len(rippled["bin_z"]) == 16 and np.sum(np.square(rippled["bin_z"])) > 39.3, rippled["bin_z"]
    assert all(np.sum(np.square(n["bin_z"])) < 39.3 for n in noise)
    # the folded means follow a sine of the phase: positive near a quarter, negative near three
    phase, mean_z = np.array(rippled["centre"]), np.array(rippled["mean_z"])
    assert np.corrcoef(mean_z, np.sin(2 * np.pi * phase))[0, 1] > 0.8
