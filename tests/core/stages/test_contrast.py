"""Multiscale contrast: exact pyramid, monotone in strength, no halo at strong edges (the GCF / CLAHE
comparison on the real chest runs through the ``dslrxr`` process: tests/_cli/test_display_defaults_process.py)."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from napari_dslrxr.core.stages.contrast import ContrastParams, enhance_contrast, laplacian_pyramid, reconstruct_pyramid
from napari_dslrxr.core.params import PipelineParams

_EVAL = Path(__file__).resolve().parents[3] / "benchmarks" / "eval_contrast.py"
_spec = importlib.util.spec_from_file_location("eval_contrast", _EVAL)
eval_contrast = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(eval_contrast)


def test_pyramid_reconstruction_is_exact_for_odd_sizes(rng):
    img = rng.random((257, 190)).astype(np.float32)
    bands = laplacian_pyramid(img.copy(), 6)
    assert len(bands) == 7 and bands[1].shape == (129, 95)
    assert np.abs(reconstruct_pyramid(bands) - img).max() < 1e-5


def test_identity_settings_leave_image_unchanged(rng):
    img = rng.random((128, 160)).astype(np.float32)
    out = enhance_contrast(img, ContrastParams(detail_contrast=0.0, bone_contrast=1.0, edge_sharpness=1.0,
                                                  coarse_edge_gain=1.0))
    assert np.abs(out - img).max() < 1e-5


def test_gcf_grows_with_detail_contrast_and_noise_floor_protects_noise(rng):
    yy, xx = np.mgrid[0:256, 0:256]
    structure = 0.5 + 0.05 * np.sin(xx / 6.0) * (xx < 128) + 0.3 * (yy > 128)
    noisy = (structure + rng.normal(0, 0.01, structure.shape)).astype(np.float32)
    gcfs = [eval_contrast.gcf(np.clip(enhance_contrast(noisy, ContrastParams(detail_contrast=d)), 0, 1))
            for d in (0.0, 0.4, 0.8)]
    assert gcfs[0] < gcfs[1] < gcfs[2]
    flat = np.s_[10:118, 140:250]  # noise only

    def noise(img):  # high-pass residual: the edge's large-scale halo is not noise
        return eval_contrast.highpass_std(img, (flat[0].start, flat[1].start, flat[0].stop, flat[1].stop))

    guarded = enhance_contrast(noisy, ContrastParams(detail_contrast=0.8, noise_floor=3.0))
    unguarded = enhance_contrast(noisy, ContrastParams(detail_contrast=0.8, noise_floor=0.0))
    assert noise(guarded) < 0.75 * noise(unguarded)
    assert noise(guarded) < 1.5 * noise(noisy)


def _halo_fraction(profile):
    """Overshoot above the bright plateau plus undershoot below the dark one, / output step.

    A step edge's input profile is monotone (halo 0); any bright rim or dark band that the
    processing adds shows up as the profile leaving the range of its own far ends.
    """
    p = np.asarray(profile, np.float64)
    step = p[-1] - p[0]
    return ((p.max() - p[-1]) + (p[0] - p.min())) / step


def _step_chain(step_height, dr_params, contrast_params):
    from napari_dslrxr.core.stages.dynamic_range import reduce_dynamic_range

    img = np.full((96, 512), 0.5 - step_height / 2, np.float32)
    img[:, 256:] += np.float32(step_height)  # a strong edge: collimator, skin line, metal
    out = enhance_contrast(reduce_dynamic_range(img, None, dr_params), contrast_params)
    return img, out


@pytest.mark.parametrize(("step_height", "max_halo"), [(0.5, 0.01), (1.0, 0.002), (2.0, 0.001)])
def test_default_output_has_no_halo_at_strong_edges(step_height, max_halo):
    from napari_dslrxr.core.stages.dynamic_range import DynamicRangeParams

    params = PipelineParams()
    img, out = _step_chain(step_height, params.dynamic_range, params.contrast)
    assert _halo_fraction(img.mean(axis=0)) == 0.0
    halo = _halo_fraction(out.mean(axis=0))
    # the earlier defaults (box low-pass DRR, latitude 0.6, power law in every band, no halo guard)
    old = _step_chain(step_height, DynamicRangeParams(latitude=0.6, edge_step=0.0),
                      ContrastParams(detail_contrast=0.5, bone_contrast=2.0, halo_step=0.0, coarse_halo_step=0.0))[1]
    assert _halo_fraction(old.mean(axis=0)) > 0.5
    assert halo < max_halo, halo  # measured 0.0034 (step 0.5), 0.0002 (1.0), 0.00001 (2.0)


# auto = 4 levels here (2 coarse bands). The compression of the step (coarse_edge_gain) scales its
# bands' side lobes down too, a small rim of about 1 % of the step (0.3 % of the display range)
@pytest.mark.parametrize(("levels", "min_gain", "max_halo"), [(0, 1.8, 0.015), (3, 1.3, 0.02)])
def test_coarse_remapping_raises_subtle_steps_and_leaves_strong_ones_without_halo(levels, min_gain, max_halo):
    """The coarse bands' local Laplacian remapping: a weak edge (0.03, below coarse_halo_step)
    gets local contrast, a strong one (0.3, a lung's or an air gap's edge) none and no halo."""
    def chain(height):
        img = np.full((256, 512), 0.5, np.float32)
        img[:, 256:] += np.float32(height)
        return enhance_contrast(img, ContrastParams(levels=levels))

    weak, strong = chain(0.03), chain(0.3)
    near = np.s_[:, 260:268], np.s_[:, 244:252]  # 4-12 px either side of the edge
    assert weak[near[0]].mean() - weak[near[1]].mean() > min_gain * 0.03  # measured 2.06x (auto), 1.47x (3)
    assert strong[near[0]].mean() - strong[near[1]].mean() < 0.3  # compressed (coarse_edge_gain)
    assert _halo_fraction(strong.mean(axis=0)) < max_halo  # measured 0.010 (auto), 0.016 (3)
    # the power-law mapping of the coarse bands (coarse_halo_step 0) keeps a halo beside it
    plain = np.full((256, 512), 0.5, np.float32)
    plain[:, 256:] += np.float32(0.3)
    before = enhance_contrast(plain, ContrastParams(levels=levels, coarse_halo_step=0.0, halo_step=0.0))
    assert _halo_fraction(before.mean(axis=0)) > 0.05


def test_local_laplacian_bands_are_the_plain_pyramid_at_unit_gains(rng):
    from napari_dslrxr.core.stages.contrast import local_laplacian_bands

    img = rng.random((100, 130)).astype(np.float32)
    bands = local_laplacian_bands(img, 3, detail_gain=1.0, edge_gain=1.0, range_sigma=0.1, value_range=(0.0, 1.0))
    plain = laplacian_pyramid(img.copy(), 3)
    assert len(bands) == 4
    assert max(float(np.abs(a - b).max()) for a, b in zip(bands, plain)) < 1e-5


def test_detail_gain_does_not_swing_with_brightness_when_the_range_is_wide():
    """A weak 0.01 step gets about the same gain at every brightness, also when a quarter of
    the frame is far above the display window (8 VOI units): the coarse bands' reference levels
    had then been spaced 4x their remapping's width, and the gain swung 1.2-3.7 with brightness."""
    from napari_dslrxr.core.params import PipelineParams
    from napari_dslrxr.core.stages.contrast import enhance_contrast

    params = PipelineParams().contrast
    h, w = 512, 512
    gains = []
    for base in np.arange(0.30, 0.50, 0.02):
        image = np.full((h, w), base, np.float32)
        image[:, w // 2:] += 0.01
        image[:128] = 0.0
        image[-128:] = 8.0
        out = enhance_contrast(image, params)
        step = out[200:300, w // 2 + 1:w // 2 + 6].mean() - out[200:300, w // 2 - 6:w // 2 - 1].mean()
        gains.append(step / 0.01)
    assert min(gains) > 2.0 and max(gains) / min(gains) < 1.2, gains


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_pixel_is_refused_not_spread_over_the_output(bad):
    from napari_dslrxr.core.errors import InputError

    image = np.random.default_rng(0).uniform(0.2, 0.8, (128, 128)).astype(np.float32)
    image[40, 50] = bad
    with pytest.raises(InputError, match="NaN or infinite"):
        enhance_contrast(image)
