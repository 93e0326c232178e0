"""The small-dense-object evaluation of benchmarks/eval_impulse_hills.py: its frames hold the
hills it says, and its baseline (the hill test off) is the stage before the test."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import eval_impulse_hills as hills  # noqa: E402


def test_bead_frames_hold_thirty_hills_and_the_hill_test_leaves_most_of_them(shared_data, monkeypatch):
    """(The frames' anatomy is a crop of the real CR radiographs.) Measured on seed 12: 274 of
    2470 hill pixels flagged with the hill test, 1482 without."""
    from scipy import ndimage as ndi

    monkeypatch.setenv("DSLRXR_DATA", str(shared_data))
    frame, mask = hills.hill_frame(12, "beads", hills.gen.TINTS["grey"])
    assert frame.dtype == np.uint16 and frame.ndim == 2
    assert ndi.label(mask)[1] == 30
    with_test, _ = hills.flagged(frame, mask, hill_test=True)
    without, _ = hills.flagged(frame, mask, hill_test=False)
    assert without > 0.4 * mask.sum()  # the stage before the hill test flattens many of them
    assert with_test < 0.4 * without
