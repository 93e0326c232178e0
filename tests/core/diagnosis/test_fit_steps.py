"""Steps of the diagnosis's fits that replace a plainer computation by an equal one: the score
test's columns from the current model where the model is affine in a candidate's parameters,
the Levenberg–Marquardt step held at the bounds it would cross, and the line search's exact
offset and gain."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dslrxr.core.diagnosis import acceptance, fitting
from napari_dslrxr.core.diagnosis.fitting import Layout, Problem, _bounded_step
from napari_dslrxr.core.diagnosis.terms import REGISTRATION
from napari_dslrxr.core.simulation.physics_terms import get_term
from napari_dslrxr.core.simulation.simulator import ChainModel

from test_mismatch import make_scene  # noqa: E402 (same directory, on the path under pytest)

SIZE_PX = 64


def _problem(active_names=()):
    scene = make_scene(SIZE_PX)
    grid = scene.grid()
    model = ChainModel(scene.thickness_mm, grid)
    base = scene.base_params()
    terms = list(REGISTRATION) + [get_term(n) for n in active_names]
    layout = Layout.build(base, terms, grid)
    values = {t.name: t.null_params() for t in terms}
    # registration and active terms away from their nulls: the columns are taken through them
    values["registration_shift"].update(shift_x_px=0.13, shift_y_px=-0.07)
    values["registration_affine"].update(scale=4e-4, rotation_rad=-3e-4)
    if "detector_gamma" in active_names:
        values["detector_gamma"]["kappa"] = 0.05
    if "vignetting" in active_names:
        values["vignetting"].update(k1=-0.05, k2=0.01)
    x = layout.pack(base, values)
    rng = np.random.default_rng(5)
    y = model.expected(*layout.unpack(x)) + rng.normal(0.0, 8.0, grid.shape)
    problem = Problem(y, model, np.ones(grid.shape, bool))
    problem.wsqrt = np.full(grid.shape, 1.0 / 8.0)
    return problem, layout, x


def _plain_columns(problem, layout, x, term, grid_point):
    """Forward differences at the probe point (what the score test used before)."""
    base, terms = layout.unpack(x)
    probe = {**acceptance.probe_params(term, problem.model.grid), **grid_point}
    return acceptance.forward_difference_columns(problem, base, terms, term, probe)


@pytest.mark.parametrize("name, active", [
    ("mirror_ghost", ()), ("veiling_glare", ("vignetting",)), ("scatter", ()), ("detector_gamma", ())])
def test_affine_candidates_take_their_columns_from_the_current_model(name, active):
    problem, layout, x = _problem(active)
    term = get_term(name)
    grid_point = term.grid_points()[-1]
    probe = {**acceptance.probe_params(term, problem.model.grid), **grid_point}
    assert acceptance._affine_in_free_params(term, probe, layout.terms)
    fast = acceptance._candidate_columns(problem, layout, x, term, grid_point)
    plain = _plain_columns(problem, layout, x, term, grid_point)
    # equal to rounding: the model is affine in the parameter, so the two differences agree
    np.testing.assert_allclose(fast, plain, rtol=1e-6, atol=1e-9 * np.abs(plain).max())


@pytest.mark.parametrize("name, active", [
    ("veiling_glare", ("detector_gamma",)),  # a non-linear response after the glare: not affine
    ("vignetting", ()),                      # its centre is not a linear parameter
    ("heel_effect", ()), ("lens_distortion", ())])
def test_other_candidates_keep_the_forward_differences(name, active):
    problem, layout, x = _problem(active)
    term = get_term(name)
    grid_point = term.grid_points()[0]
    probe = {**acceptance.probe_params(term, problem.model.grid), **grid_point}
    assert not acceptance._affine_in_free_params(term, probe, layout.terms)
    fast = acceptance._candidate_columns(problem, layout, x, term, grid_point)
    plain = _plain_columns(problem, layout, x, term, grid_point)
    assert np.array_equal(fast, plain)  # the forward differences themselves


def test_the_affine_shortcut_would_be_wrong_through_a_non_linear_response():
    """Why the rule exists: through the camera gamma, the glare's two differences disagree."""
    problem, layout, x = _problem(("detector_gamma",))
    term = get_term("veiling_glare")
    grid_point = {"range_mm": 2.0}
    probe = {**acceptance.probe_params(term, problem.model.grid), **grid_point}
    base, terms = layout.unpack(x)
    f_null = problem.model.expected(base, terms)
    f_probe = problem.model.expected(base, terms + [(term, probe)])
    from_null = ((f_probe - f_null) / probe["eta"] * problem.wsqrt).ravel()
    plain = _plain_columns(problem, layout, x, term, grid_point)[:, 0]
    assert np.abs(from_null - plain).max() > 1e-4 * np.abs(plain).max()


def _linearised_minimum(a, g, x, lower, upper, fixed_at):
    """Minimiser of gᵀs + ½ sᵀAs with the parameters ``fixed_at`` held at their bound."""
    step = np.zeros_like(x)
    for i, bound in fixed_at.items():
        step[i] = bound - x[i]
    free = np.array([i not in fixed_at for i in range(x.size)])
    rhs = -(g[free] + a[np.ix_(free, ~free)] @ step[~free])
    step[free] = np.linalg.solve(a[np.ix_(free, free)], rhs)
    return step


def test_bounded_step_solves_again_with_the_crossed_bound_held():
    rng = np.random.default_rng(2)
    jac = rng.normal(size=(200, 4))
    jac[:, 1] += 0.9 * jac[:, 0]  # correlated: the others must take up what the clipped one cannot
    r = rng.normal(size=200)
    a, g = jac.T @ jac, jac.T @ r
    x = np.array([0.01, 0.3, -0.2, 0.5])
    unconstrained = np.linalg.solve(a, -g)
    lower, upper = np.full(4, -np.inf), np.full(4, np.inf)
    j = int(np.argmax(np.abs(unconstrained)))
    # a bound the unconstrained step crosses, half-way along it
    if unconstrained[j] < 0:
        lower[j] = x[j] + 0.5 * unconstrained[j]
        bound = lower[j]
    else:
        upper[j] = x[j] + 0.5 * unconstrained[j]
        bound = upper[j]
    step = _bounded_step(a, g, x, lower, upper, np.ones(4, bool), 0.0, np.diag(a))
    expected = _linearised_minimum(a, g, x, lower, upper, {j: bound})
    np.testing.assert_allclose(step, expected, rtol=1e-10, atol=1e-12)
    assert np.all(x + step >= lower - 1e-15) and np.all(x + step <= upper + 1e-15)
    # the plain clip of the unconstrained step predicts less gain than the re-solved step
    def predicted(s):
        return -(2.0 * g @ s + s @ a @ s)
    clipped = np.clip(x + unconstrained, lower, upper) - x
    assert predicted(step) > predicted(clipped)
    # inside the bounds it is the plain damped step
    lam = 0.3
    inside = _bounded_step(a, g, x, np.full(4, -np.inf), np.full(4, np.inf), np.ones(4, bool), lam, np.diag(a))
    np.testing.assert_allclose(inside, np.linalg.solve(a + lam * np.diag(np.diag(a)), -g), rtol=1e-12)


def test_line_search_offset_and_gain_are_the_least_squares_solution():
    problem, layout, x = _problem()
    start = x.copy()
    start[layout.index("base", "offset_dn")] += 40.0
    start[layout.index("base", "gain_dn")] *= 0.97
    refit, chi2 = acceptance._with_linear_refit(problem, layout, start)
    r = problem.whitened(layout, refit)
    assert chi2 == pytest.approx(float(r @ r), rel=1e-9)
    # χ² is minimal in offset and gain: small moves either way only raise it
    for name in ("offset_dn", "gain_dn"):
        j = layout.index("base", name)
        for h in (-1e-3, 1e-3):
            moved = refit.copy()
            moved[j] += h * max(abs(refit[j]), 1.0)
            rm = problem.whitened(layout, moved)
            assert float(rm @ rm) > chi2
    # and it recovers the values the recording was made with (noise 8 DN over 64² pixels)
    assert refit[layout.index("base", "offset_dn")] == pytest.approx(x[layout.index("base", "offset_dn")], abs=2.0)
    assert refit[layout.index("base", "gain_dn")] == pytest.approx(x[layout.index("base", "gain_dn")], rel=2e-3)


def test_a_fits_final_jacobian_is_computed_when_read_and_equals_the_direct_one():
    problem, layout, x = _problem()
    start = x.copy()
    start[layout.index("base", "detector_sigma_mm")] *= 1.1
    counted = []
    jacobian = problem.jacobian

    def counting(*args, **kwargs):
        counted.append(1)
        return jacobian(*args, **kwargs)

    problem.jacobian = counting
    x_fit, _, jac = problem.fit(layout, start)
    before = len(counted)
    value = fitting.resolved(jac)
    assert isinstance(jac, fitting.DeferredJacobian) and len(counted) == before + 1
    assert fitting.resolved(jac) is value and len(counted) == before + 1  # computed once
    np.testing.assert_array_equal(value, jacobian(layout, x_fit))
    # read after the weights changed, it would be another Jacobian: refused
    _, _, stale = problem.fit(layout, start)
    problem.wsqrt = problem.wsqrt * 2.0
    with pytest.raises(RuntimeError, match="wsqrt"):
        fitting.resolved(stale)


def test_levenberg_marquardt_stops_where_no_step_gains_on_the_previous_jacobian():
    """A linear problem: the damped first step (λ = 1e-3) leaves a little to gain, the second
    reaches the minimum, and the fit ends there without computing the Jacobian at that point
    (the test on the previous one is exact for a linear model); it is computed when read."""
    rng = np.random.default_rng(8)
    design = rng.normal(size=(500, 3))
    target = design @ np.array([1.0, -2.0, 0.5]) + rng.normal(0.0, 0.1, 500)
    calls = []

    def jac(x, r):
        calls.append(1)
        return design

    x, chi2, j = fitting.levenberg_marquardt(lambda x: design @ x - target, jac, np.zeros(3),
                                             np.full(3, -np.inf), np.full(3, np.inf), 40)
    best, *_ = np.linalg.lstsq(design, target, rcond=None)
    np.testing.assert_allclose(x, best, rtol=1e-6, atol=1e-6)
    assert isinstance(j, fitting.DeferredJacobian) and len(calls) == 2
    assert np.array_equal(fitting.resolved(j), design) and len(calls) == 3
