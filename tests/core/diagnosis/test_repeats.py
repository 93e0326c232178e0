"""Cleaning repeated frames of a plate edge: spots replaced, everything else left as recorded."""

import numpy as np
import pytest

from napari_dslrxr.core.diagnosis.repeats import clean_repeats
from napari_dslrxr.core.errors import InputError


def test_clean_repeats_replaces_only_the_spot_by_the_temporal_median():
    rng = np.random.default_rng(3)
    frames = rng.normal(1000.0, 5.0, (5, 32, 40))
    frames[2, 7, 11] += 500.0  # a direct hit on one frame
    cleaned = clean_repeats(frames)
    assert cleaned[2, 7, 11] == np.median(frames[:, 7, 11])
    changed = cleaned != frames
    changed[2, 7, 11] = False
    assert not changed.any()


def test_clean_repeats_needs_three_frames():
    with pytest.raises(InputError, match="at least 3"):
        clean_repeats(np.zeros((2, 8, 8)))
