"""Tests of the declarative physics-term library."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dslrxr.core.errors import ParameterError
from napari_dslrxr.core.simulation.physics_terms import LIBRARY, STAGES, get_term, validate_params
from napari_dslrxr.core.simulation.simulator import ChainModel, phantom_thickness_mm, parse_scene

REQUIRED = {"heel_effect", "inverse_square", "vignetting", "veiling_glare", "mirror_ghost", "scatter",
            "beam_hardening", "detector_gamma", "lens_distortion", "focal_spot_shape"}


@pytest.fixture(scope="module")
def model_and_base():
    scene = parse_scene({"geometry": {"source_to_detector_mm": 1200, "source_to_object_mm": 1000,
                                      "pixel_pitch_mm": 0.1},
                         "object": {"material": "aluminium"}, "source": {"kvp": 60}},
                        thickness=phantom_thickness_mm((64, 64)))
    return ChainModel(scene.thickness_mm, scene.grid()), scene.base_params()


def test_library_has_the_required_terms_with_complete_declarations():
    assert REQUIRED <= {t.name for t in LIBRARY}
    for term in LIBRARY:
        assert term.stage in STAGES
        assert term.main in term.param_names
        assert term.physics and term.covariate and term.separating
        for spec in term.params:
            lo, hi = spec.prior
            assert lo <= spec.null <= hi and lo <= spec.probe <= hi, (term.name, spec.name)
            assert spec.step > 0


def test_null_params_leave_the_image_unchanged_and_probe_changes_it(model_and_base):
    model, base = model_and_base
    reference = model.expected(base)
    for term in LIBRARY:
        null = term.null_params()
        np.testing.assert_allclose(model.expected(base, [(term, null)]), reference, rtol=0, atol=1e-9,
                                   err_msg=term.name)
        probe = term.probe_params()
        probe.update(term.grid_points()[0])
        assert np.abs(model.expected(base, [(term, probe)]) - reference).max() > 0.5, term.name


def test_glare_conserves_light_and_spreads_it_past_edges(model_and_base):
    model, base = model_and_base
    glare = get_term("veiling_glare")
    no = model.expected(base) - base["offset_dn"]
    yes = model.expected(base, [(glare, {"eta": 0.1, "range_mm": 0.5})]) - base["offset_dn"]
    # The opaque block (rows ~38-54, cols ~46-55) receives light from the bright surroundings.
    assert yes[45, 50] > no[45, 50] + 0.02 * base["gain_dn"]
    # Centre of open field loses light (it went into the tail).
    assert yes[5, 60] < no[5, 60]
    # ...and the total is kept (MTF 1 at f = 0): eta = 0.1 moves ~1 % of the light, while a
    # non-conserving glare would change the sum by ~10 %; the rest is light leaving the frame.
    assert yes.sum() == pytest.approx(no.sum(), rel=2e-3)


def test_heel_is_a_monotone_ramp_along_its_axis(model_and_base):
    model, base = model_and_base
    heel = get_term("heel_effect")
    ratio = (model.expected(base, [(heel, {"h1": 0.1, "h2": 0.0, "angle_deg": 0.0})]) - base["offset_dn"]) \
        / (model.expected(base) - base["offset_dn"])
    row = ratio[3]
    assert np.all(np.diff(row) > 0)
    np.testing.assert_allclose(row[40] / row[20], np.exp(0.1 * (20 / 32)), rtol=1e-4)


def test_validate_params_errors_are_one_line():
    with pytest.raises(ParameterError, match="did you mean 'veiling_glare'"):
        get_term("veiling_glar")
    with pytest.raises(ParameterError, match="outside its range"):
        validate_params(get_term("veiling_glare"), {"eta": 2.0})
    with pytest.raises(ParameterError, match="unknown parameter"):
        validate_params(get_term("veiling_glare"), {"width": 2.0})


def test_periodic_angle_wraps():
    spec = get_term("focal_spot_shape").spec("axis_deg")
    assert spec.wrap(177.5) == pytest.approx(-2.5)
    assert spec.wrap(-92.0) == pytest.approx(88.0)
