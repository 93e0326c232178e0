"""The recall-ceiling references of benchmarks/eval_impulse_recall_ceiling.py pick the right threshold."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import eval_impulse_recall_ceiling as ceiling  # noqa: E402


def test_lowest_threshold_is_the_first_step_with_the_target_precision():
    rng = np.random.default_rng(0)
    z = rng.normal(size=(400, 400))
    near = np.zeros(z.shape, bool)
    near[:20, :20] = True
    z[:20, :20] += 6.0  # 400 pulse pixels 6 sigma up
    t = ceiling.lowest_threshold(z, near)
    for threshold, should_pass in ((t, True), (t - 0.05, False)):
        flag = z >= threshold
        precision = np.count_nonzero(flag & near) / np.count_nonzero(flag)
        assert bool(precision >= ceiling.PRECISION) is should_pass, (threshold, precision)
    # 159 600 noise pixels; 21 false ones (precision 0.95 with ~380 hits) lie near 3.5 sigma
    assert 3.0 < t < 4.0


def test_lowest_threshold_without_pulses_is_infinite():
    z = np.random.default_rng(1).normal(size=(100, 100))
    assert ceiling.lowest_threshold(z, np.zeros(z.shape, bool)) == float("inf")


def test_sparse_ring_is_the_eight_pixels_two_steps_away():
    fp = ceiling._sparse_ring()
    assert fp.sum() == 8 and not fp[2, 2] and fp[0, 0] and fp[2, 0] and not fp[1, 1]


def test_threshold_at_the_pe_target_is_the_first_step_meeting_precision_and_pe():
    from scipy import ndimage as ndi

    rng = np.random.default_rng(2)
    z = rng.normal(size=(400, 400, 1))
    z[:40, :40] += 6.0  # 1600 pulse pixels 6 sigma up: precision allows about 80 false ones
    near = np.zeros(z.shape[:2], bool)
    near[:40, :40] = True
    far = ~ndi.binary_dilation(near, iterations=2)
    expected = np.full(z.shape, 1000.0)
    dirty = expected + 30.0 * z  # sigma 30 counts
    t = ceiling.lowest_threshold_at_pe(z, near, dirty, expected, far)

    def meets(threshold):
        flag_c = z >= threshold
        flag = flag_c.any(axis=2)
        precise = np.count_nonzero(flag & near) >= ceiling.PRECISION * np.count_nonzero(flag)
        pe = ceiling.pe_clean_pct(dirty, np.where(flag_c, expected, dirty), far)
        return precise and pe <= ceiling.PE_TARGET_PCT

    assert meets(t) and not meets(t - 0.05)
    # the PE bound, not the precision, sets it here: ~75 false pixels of 3.3 sigma and more
    # cost about 0.2 % of the frame
    assert t > ceiling.lowest_threshold(z[..., 0], near) + 0.2
