"""Invariants of the whole pipeline over the scenario corpus (camera frames of real anatomy).

60 seeds per run (0-59), each a small frame (180 x 270) with its matching flat. Per
scenario: no anatomy blanked, the anatomy's clipped fraction bounded, bone white (positive
correlation with the true attenuation), the flat-field pattern gone. A scenario that breaks
the clipped-fraction bound must at least have said why (a "no screen found" warning): the
pipeline may not be silently wrong. Held-out seeds (2000-2059, and later sets) run only with
``DSLRXR_HELD_OUT=1`` (before closing an issue, never while tuning). The former held-out set
(1000-1059) was looked at while fixing what it found; it runs with the CI seeds as a second
tuned set when ``DSLRXR_HELD_OUT=1`` too.

Figures of the last full run are printed at the end (``-s`` shows them).
"""

from __future__ import annotations

import os

import numpy as np
import pytest
from scenarios.corpus import (data_dir, evaluate, flat_pattern_left, flat_pattern_resolution, make_scenario,
                              plain_flat_division)

from napari_dslrxr.core.pipeline import process_frame

pytestmark = pytest.mark.realdata

CI_SEEDS = range(0, 60)
HELD_OUT_SEEDS = range(2000, 2060)
#: The first held-out set: its failures were diagnosed and fixed, so it is tuned-on now.
LOOKED_AT_SEEDS = range(1000, 1060)
#: Held out when the direct-exposure rule became spatial and the dense-area family was added:
#: run once before closing, with the dense-area family's own held-out seeds.
SPATIAL_RULE_HELD_OUT_SEEDS = range(5000, 5060)
DENSE_AREA_HELD_OUT_SEEDS = range(5100, 5140)
#: Held out when screen candidates began to need a surround the flat frame saw unexposed (and
#: the flat-pattern metric became a joint fit); 5000-5059 and 5100-5139 were run before as well.
FLAT_SURROUND_HELD_OUT_SEEDS = range(8000, 8060)
FLAT_SURROUND_DENSE_HELD_OUT_SEEDS = range(8100, 8140)
#: Held out when a screen side facing a frame edge the screen runs off became open (developed on
#: 9200-9239; 9400-9519, run first, had four of its frames looked at and is tuned on now).
FRAME_CUT_HELD_OUT_SEEDS = range(9600, 9720)
#: Held out when grown patches whose excess goes on beyond them stopped counting as pulses
#: (developed on 9214, 5002, 6116): run once before closing issue 12.
BROAD_GUARD_HELD_OUT_SEEDS = range(9860, 9960)

#: Bounds per scenario.
MAX_BLANKED = 0.01  # share of the anatomy outside the region (filled, not shown)
MAX_CLIPPED = 0.01  # share of the anatomy at the display's black or white end
MIN_POLARITY_R = 0.3  # correlation of the display with the true attenuation
MAX_FLAT_LEFT = 0.5  # share of the flat-field pattern left (no flat frame: 0.7-1.6)
#: The flat-pattern bound holds where the metric can read the frame: its standard error on the
#: frame's own plain flat-field division (where it should read 0) at most 0.2, so 0.5 is 2.5
#: of them. Above (4 of 258 exposed frames of 0-59, 1000-1059, 2000-2059, 5000-5059,
#: 8000-8059, 9200-9239: a small anatomy on a small screen) the plain division itself read 0.54
#: and 0.80 (seeds 2009, 2015).
MAX_FLAT_LEFT_SE = 0.2
#: Median over the corpus, starved frames aside (0.035 now): a flat corrected three quarters
#: of the way leaves 0.26 (only 2 of 37 scenarios above the per-scenario bound), half-way 0.5.
MAX_MEDIAN_FLAT_LEFT = 0.2


#: The dense-area family (a large dense uniform area beside the anatomy), developed on these
#: seeds. Its screen detection blanked 1-5 % of the anatomy beside the dense area on 4 of them
#: (a dense area as dark as the room cut the "screen") until a candidate's surround had to be
#: unexposed in the flat frame too; every invariant is asserted there now.
DENSE_AREA_SEEDS = range(3000, 3040)


def _run(seed: int, family: str = "corpus") -> tuple[dict, dict, object]:
    scenario = make_scenario(seed, family=family)
    result = process_frame(scenario.raw, flats=[scenario.flat], black_level=scenario.black_level,
                           keep_intermediates=True)
    return evaluate(scenario, result), scenario.info, result


def _check(seeds, family: str = "corpus", invariants=("blanked", "clipped", "polarity_r", "flat_left")) -> dict:
    if not (data_dir() / "cr_dicom").is_dir():
        pytest.skip(f"real data folder {data_dir()} is absent (set DSLRXR_DATA)")
    rows, problems, starved, unreadable = [], [], [], 0
    for seed in seeds:
        figures, info, result = _run(seed, family)
        rows.append(figures)
        starved.append(info["exposure"] == "starved")
        warned = any(w.startswith(("region: no screen found", "display implausible"))
                     for w in result.results["warnings"])
        where = f"seed {seed} {family} ({info['source']} {info['layout']} {info['exposure']} room {info['room']})"
        readable = figures.get("flat_left_se", 0.0) <= MAX_FLAT_LEFT_SE
        unreadable += not readable
        figures = {key: value for key, value in figures.items() if key in invariants}
        if figures.get("blanked", 0.0) > MAX_BLANKED:
            problems.append(f"{where}: {100 * figures['blanked']:.1f} % of the anatomy blanked")
        if figures["clipped"] > MAX_CLIPPED and not warned:
            problems.append(f"{where}: {100 * figures['clipped']:.1f} % of the anatomy clipped, silently")
        if figures["polarity_r"] < MIN_POLARITY_R:
            problems.append(f"{where}: polarity r = {figures['polarity_r']:.2f}")
        if figures.get("flat_left", 0.0) > MAX_FLAT_LEFT and info["exposure"] != "starved" and readable:
            problems.append(f"{where}: {100 * figures['flat_left']:.0f} % of the flat-field pattern left")
        # the sidecar's own clipped fraction is the pipeline's view of the same thing
        reported = result.results["display"]["clipped_fraction"]
        if not 0.0 <= reported <= MAX_CLIPPED:
            problems.append(f"{where}: the sidecar reports {100 * reported:.1f} % clipped")
    summary = {key: np.array([r[key] for r in rows]) for key in rows[0]}
    print(f"\nscenario corpus, {len(rows)} scenarios:")
    for key, values in summary.items():
        print(f"  {key:10s} median {np.median(values):.4f}  95th {np.percentile(values, 95):.4f}  "
              f"max {values.max():.4f}  min {values.min():.4f}")
    print(f"  clipped > 1 %: {int(np.sum(summary['clipped'] > MAX_CLIPPED))} (each with a warning)")
    print(f"  flat pattern not readable (standard error > {MAX_FLAT_LEFT_SE}): {unreadable}")
    assert not problems, "\n".join(problems)
    summary["starved"] = np.array(starved)
    return summary


def test_corpus_invariants():
    summary = _check(CI_SEEDS)
    # the corpus is varied: more than one scenario per layout/source kind went through
    assert len(summary["blanked"]) >= 50
    # most anatomy is shown unclipped; the rare clipped scenarios were announced
    assert np.mean(summary["clipped"] <= MAX_CLIPPED) >= 0.9
    exposed = summary["flat_left"][~summary["starved"]]
    assert np.median(exposed) <= MAX_MEDIAN_FLAT_LEFT, np.median(exposed)


def test_flat_pattern_metric_catches_a_missing_flat():
    """Without the flat frame the pattern stays (the metric is not blind)."""
    if not (data_dir() / "cr_dicom").is_dir():
        pytest.skip(f"real data folder {data_dir()} is absent (set DSLRXR_DATA)")
    left = []
    for seed in range(0, 8):
        scenario = make_scenario(seed)
        result = process_frame(scenario.raw, black_level=scenario.black_level, keep_intermediates=True)
        left.append(evaluate(scenario, result)["flat_left"])
        assert any(w.startswith("no flat frame given") for w in result.results["warnings"])
    assert np.median(left) > 0.7, left


def test_flat_pattern_metric_is_not_fooled_by_anatomy_that_follows_the_pattern():
    """A chest centred on a small screen correlates with the illumination pattern (r 0.5 on
    these seeds): the same frames lit evenly read (almost) no pattern, and without their flat
    frame they read the whole pattern (about 1). Fitting the truth first read 0.10-0.34 lit
    evenly and 0.75-1.09 uncorrected on them."""
    if not (data_dir() / "cr_dicom").is_dir():
        pytest.skip(f"real data folder {data_dir()} is absent (set DSLRXR_DATA)")
    for seed in (48, 50):
        scenario = make_scenario(seed)
        truth, pattern = scenario.attenuation[scenario.anatomy], -np.log(scenario.flat_pattern[scenario.anatomy])
        assert np.corrcoef(truth, pattern)[0, 1] > 0.5
        even = make_scenario(seed, illumination_pattern=False)
        result = process_frame(even.raw, flats=[even.flat], black_level=even.black_level, keep_intermediates=True)
        assert flat_pattern_left(result.intermediates["attenuation"], scenario) < 0.15
        uncorrected = process_frame(scenario.raw, black_level=scenario.black_level, keep_intermediates=True)
        assert 0.8 < flat_pattern_left(uncorrected.intermediates["attenuation"], scenario) < 1.3


@pytest.mark.parametrize("seed, main_v_px", [(9214, 76), (5002, 524), (6116, 350)])
def test_smooth_anatomy_blobs_are_not_taken_for_pulses(seed, main_v_px):
    """Frames where the V pass replaced smooth lung blobs (6-8 px across, 10-16 noise sigmas,
    blurred by the screen) as if they were pulses, and so left the flat-field invariant above
    its bound (main: flat pattern left 0.57 / 0.55 / 0.53, V pixels replaced 76 / 524 / 350;
    with the broad-patch guard 0.07 / 0.40 / 0.11 and 12 / 333 / 112).
    The corpus holds no pulses, so every replaced pixel is a false alarm."""
    if not (data_dir() / "cr_dicom").is_dir():
        pytest.skip(f"real data folder {data_dir()} is absent (set DSLRXR_DATA)")
    scenario = make_scenario(seed)
    result = process_frame(scenario.raw, flats=[scenario.flat], black_level=scenario.black_level,
                           keep_intermediates=True)
    figures = evaluate(scenario, result)
    assert figures["flat_left"] <= MAX_FLAT_LEFT, figures
    assert result.results["impulse"]["pulse_pixels"]["V"] <= 0.8 * main_v_px, result.results["impulse"]


def test_dense_area_family():
    """A dense area beside the anatomy: the anatomy is shown (not taken for direct exposure)
    and not blanked (the dense area is not the room around a screen)."""
    summary = _check(DENSE_AREA_SEEDS, "dense_area")
    assert len(summary["clipped"]) == 40


@pytest.mark.skipif(os.environ.get("DSLRXR_HELD_OUT") != "1", reason="held-out seeds: set DSLRXR_HELD_OUT=1")
def test_corpus_held_out_seeds():
    _check(HELD_OUT_SEEDS)


@pytest.mark.skipif(os.environ.get("DSLRXR_HELD_OUT") != "1", reason="looked-at seeds: set DSLRXR_HELD_OUT=1")
def test_corpus_looked_at_seeds():
    _check(LOOKED_AT_SEEDS)


@pytest.mark.skipif(os.environ.get("DSLRXR_HELD_OUT") != "1", reason="held-out seeds: set DSLRXR_HELD_OUT=1")
def test_corpus_spatial_rule_held_out_seeds():
    _check(SPATIAL_RULE_HELD_OUT_SEEDS)


#: Further seed sets run only with ``DSLRXR_HELD_OUT=1`` (held out, then run once before closing).
HELD_OUT_SETS = {"dense_area_spatial_rule": (DENSE_AREA_HELD_OUT_SEEDS, "dense_area"),
                 "corpus_flat_surround": (FLAT_SURROUND_HELD_OUT_SEEDS, "corpus"),
                 "dense_area_flat_surround": (FLAT_SURROUND_DENSE_HELD_OUT_SEEDS, "dense_area"),
                 "corpus_frame_cut": (FRAME_CUT_HELD_OUT_SEEDS, "corpus"),
                 "corpus_broad_guard": (BROAD_GUARD_HELD_OUT_SEEDS, "corpus")}


@pytest.mark.skipif(os.environ.get("DSLRXR_HELD_OUT") != "1", reason="held-out seeds: set DSLRXR_HELD_OUT=1")
@pytest.mark.parametrize("name", list(HELD_OUT_SETS))
def test_held_out_sets(name):
    seeds, family = HELD_OUT_SETS[name]
    _check(seeds, family)


def test_flat_pattern_metric_knows_where_it_cannot_read():
    """On a small anatomy on a small screen the metric reads a pattern even on the frame's own
    plain flat-field division (0.5-0.8 on held-out seeds 2009 and 2015, where the pipeline's
    stage gives the same): its standard error there is above the bound, so those frames are
    not judged on it; on every exposed CI frame it is well below, so none is let off."""
    if not (data_dir() / "cr_dicom").is_dir():
        pytest.skip(f"real data folder {data_dir()} is absent (set DSLRXR_DATA)")
    for seed in (2009, 2015):
        scenario = make_scenario(seed)
        assert flat_pattern_left(plain_flat_division(scenario), scenario) > MAX_FLAT_LEFT
        assert flat_pattern_resolution(scenario) > MAX_FLAT_LEFT_SE
    for seed in range(0, 60, 3):
        scenario = make_scenario(seed)
        if scenario.info["exposure"] != "starved":
            assert flat_pattern_resolution(scenario) < 0.7 * MAX_FLAT_LEFT_SE, seed
