"""Faster computations in the diagnosis that must give the same numbers, to the bit, as the
plain ones they replace (``np.median``, ``np.gradient``, a fresh model evaluation)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dslrxr.core.diagnosis import noise
from napari_dslrxr.core.diagnosis.fitting import Layout, Problem, tall_product
from napari_dslrxr.core.simulation.physics_terms import image_gradient
from napari_dslrxr.core.simulation.simulator import ChainModel

from test_mismatch import make_scene  # noqa: E402 (same directory, on the path under pytest)


def _arrays():
    rng = np.random.default_rng(3)
    for n in (50, 51, 19_999, 20_000, 20_001, 150_000, 150_001):
        yield f"normal {n}", rng.normal(0.0, 3.0, n)
    yield "heavy tails", rng.standard_cauchy(100_001)
    yield "integer ties", rng.integers(-3, 4, 80_000).astype(float)
    yield "constant", np.full(40_000, 2.5)
    yield "sorted", np.sort(rng.normal(size=60_000))
    yield "reversed", np.sort(rng.normal(size=60_001))[::-1].copy()
    # the strided sample sees only the large values: the bracket misses, the full partition runs
    trap = rng.normal(size=100_000)
    trap[:: 100_000 // noise._SELECT_SAMPLE] = 1e6
    yield "unrepresentative sample", trap
    yield "float32", rng.normal(size=50_000).astype(np.float32)


@pytest.mark.parametrize("label, values", list(_arrays()), ids=lambda v: v if isinstance(v, str) else "")
def test_selected_median_is_numpy_median_to_the_bit(label, values):
    expected = np.median(values)
    got = noise._median(values)
    assert got.dtype == expected.dtype and got == expected, label
    # and so is the clipped half mean square built on it (robust sigma from two medians)
    mad = np.median(np.abs(values - np.median(values)))
    assert noise._median(np.abs(values - noise._median(values))) == mad


@pytest.mark.parametrize("shape", [(2, 2), (3, 5), (64, 48), (257, 129)])
def test_image_gradient_is_numpy_gradient_to_the_bit(shape):
    image = np.random.default_rng(4).normal(0.0, 100.0, shape).cumsum(axis=1)
    for ours, numpys in zip(image_gradient(image), np.gradient(image)):
        assert np.array_equal(ours, numpys)


def test_problem_keeps_read_only_expected_images_equal_to_fresh_evaluations():
    scene = make_scene(64)
    grid = scene.grid()
    model = ChainModel(scene.thickness_mm, grid)
    problem = Problem(np.zeros(grid.shape), model, np.ones(grid.shape, bool))
    base = scene.base_params()
    layout = Layout.build(base, [], grid)
    x = layout.pack(base, {})
    first = problem.expected(layout, x)
    assert not first.flags.writeable
    x2 = x.copy()
    x2[layout.index("base", "mu_per_mm")] *= 1.01
    other = problem.expected(layout, x2)
    assert problem.expected(layout, x) is first  # a refit from the same point: not recomputed
    fresh = ChainModel(scene.thickness_mm, grid)
    assert np.array_equal(first, fresh.expected(*layout.unpack(x)))
    assert np.array_equal(other, fresh.expected(*layout.unpack(x2)))


@pytest.mark.parametrize("rows,inner,cols", [(512 * 512, 14, 2), (20001, 3, 5), (7, 4, 1)])
def test_tall_product_is_matmul_to_the_bit(rows, inner, cols):
    rng = np.random.default_rng(rows)
    tall = np.linalg.qr(rng.normal(size=(rows, inner)))[0]  # C-ordered like the projections' bases
    small = rng.normal(size=(inner, cols))
    out = tall_product(tall, small)
    assert out.shape == (rows, cols) and np.array_equal(out, tall @ small)
    # and a block boundary is not skipped or repeated: a product that would notice it
    assert np.array_equal(tall_product(np.arange(rows, dtype=float)[:, None], np.ones((1, 1)))[:, 0],
                          np.arange(rows, dtype=float))
