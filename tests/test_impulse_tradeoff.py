"""The trade-off sweep of benchmarks/eval_impulse_tradeoff.py: its Pareto front, its grid, and
that it leaves the detector's module constants as it found them."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import eval_impulse_tradeoff as tradeoff  # noqa: E402


def test_pareto_front_keeps_only_rows_not_beaten_on_recall_and_pe():
    rows = [{"pe_clean_pct": 0.10, "recall": 0.85}, {"pe_clean_pct": 0.12, "recall": 0.84},  # beaten
            {"pe_clean_pct": 0.20, "recall": 0.90}, {"pe_clean_pct": 0.08, "recall": 0.80},
            {"pe_clean_pct": 0.10, "recall": 0.83}]  # same PE, lower recall: beaten
    front = tradeoff.pareto(rows)
    assert [(r["pe_clean_pct"], r["recall"]) for r in front] == [(0.08, 0.80), (0.10, 0.85), (0.20, 0.90)]


def test_the_shipped_settings_are_a_point_of_the_grid():
    from napari_dslrxr.core.stages.impulse import ImpulseParams, detection

    for key, value in tradeoff.DEFAULT.items():
        assert value in tradeoff.GRID[key], key
    params = ImpulseParams()
    assert tradeoff.DEFAULT["min_contrast"] == params.min_contrast
    assert tradeoff.DEFAULT["neighbour_prior"] == params.neighbour_prior
    assert tradeoff.DEFAULT["posterior_threshold"] == params.posterior_threshold
    assert tradeoff.DEFAULT["footprint_sigmas"] == detection._FOOTPRINT_SIGMAS
    assert tradeoff.DEFAULT["strong_rim_prior"] == detection._STRONG_RIM_PRIOR


def test_score_restores_the_module_constants_when_a_frame_fails():
    from napari_dslrxr.core.errors import InputError
    from napari_dslrxr.core.stages.impulse import detection

    before = detection._FOOTPRINT_SIGMAS, detection._STRONG_RIM_PRIOR
    setting = {**tradeoff.DEFAULT, "footprint_sigmas": 4.0, "strong_rim_prior": 0.9}
    with pytest.raises(InputError):  # a 2x2 frame is below the stage's minimum size
        tradeoff.score([SimpleNamespace(dirty=np.zeros((2, 2), np.uint16))], setting)
    assert (detection._FOOTPRINT_SIGMAS, detection._STRONG_RIM_PRIOR) == before
