"""Tests of the SABER blur model and kernel sampler (napari_dslrxr.core.psf)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from napari_dslrxr.core.errors import InputError, ParameterError
from napari_dslrxr.core.psf import (PSFModel, fwhm_to_scale, load_psf, magnification_factor,
                                    sample_exponential_power, save_psf, scale_to_fwhm)


def _moments(kernel):
    """Centroid-free second moments (rows, columns) of a centred kernel, in px^2."""
    k = kernel.astype(np.float64)
    ny, nx = k.shape
    y = np.arange(ny) - ny // 2
    x = np.arange(nx) - nx // 2
    return float((k.sum(axis=1) * y**2).sum()), float((k.sum(axis=0) * x**2).sum())


def _model(**kw):
    base = dict(pixel_pitch_mm=0.01, source_fwhm_x_mm=0.02, source_fwhm_y_mm=0.03,
                detector_fwhm_core_mm=0.02, detector_fwhm_tail_mm=0.2, detector_weight_core=0.9,
                shape_power=1.0)
    base.update(kw)
    return PSFModel(**base)


def test_fwhm_scale_roundtrip_and_half_maximum():
    for p in (1.0, 1.5, 2.0):
        s = fwhm_to_scale(3.0, p)
        assert math.isclose(scale_to_fwhm(s, p), 3.0)
        assert math.isclose(math.exp(-((s * 1.5) ** p)), 0.5)


def test_kernel_is_odd_normalised_float32_centred():
    k = _model().kernel(100.0, 250.0)
    assert k.dtype == np.float32
    assert k.shape[0] % 2 == 1 and k.shape[0] == k.shape[1]
    assert abs(float(k.sum(dtype=np.float64)) - 1.0) < 1e-5
    assert k.min() >= 0
    assert np.unravel_index(np.argmax(k), k.shape) == (k.shape[0] // 2, k.shape[1] // 2)


@pytest.mark.parametrize("fwhm_px", [0.4, 1.0, 3.0, 12.0])
def test_gaussian_is_exactly_area_integrated(fwhm_px):
    # p = 2 is separable: the pixel integral of a Gaussian is a difference of error functions.
    from scipy.special import erf

    radius = int(5 * fwhm_px) + 3
    k = sample_exponential_power(fwhm_px, fwhm_px, 2.0, radius_x_px=radius, radius_y_px=radius)
    sigma = fwhm_px / (2 * math.sqrt(2 * math.log(2)))
    i = np.arange(-radius, radius + 1)
    one_d = 0.5 * (erf((i + 0.5) / (sigma * math.sqrt(2))) - erf((i - 0.5) / (sigma * math.sqrt(2))))
    expected = np.outer(one_d, one_d)
    assert np.abs(k - expected).max() < 5e-3 * expected.max()


def test_exponential_variance_and_anisotropy():
    # 2-D exp(-(s r)) has per-axis variance 3 / s^2; the ellipse scales each axis separately.
    k = sample_exponential_power(4.0, 8.0, 1.0, radius_x_px=60, radius_y_px=120)
    vy, vx = _moments(k)
    sx, sy = fwhm_to_scale(4.0, 1.0), fwhm_to_scale(8.0, 1.0)
    assert vx == pytest.approx(3 / sx**2 + 1 / 12, rel=0.02)
    assert vy == pytest.approx(3 / sy**2 + 1 / 12, rel=0.02)


def test_source_projection_scales_with_magnification_minus_one():
    m = _model()
    assert magnification_factor(100.0, 300.0) == pytest.approx(2.0)
    fx, fy = m.source_fwhm_on_detector_px(100.0, 300.0)
    assert (fx, fy) == pytest.approx((4.0, 6.0))
    # Object on the detector: no source blur, the kernel is the detector kernel.
    np.testing.assert_allclose(m.kernel(300.0, 300.0), m.detector_kernel(), atol=1e-7)
    assert m.source_kernel(300.0, 300.0).shape == (1, 1)
    # Total variance = source variance + detector variance (convolution adds second moments).
    vs = _moments(m.source_kernel(100.0, 300.0))
    vd = _moments(m.detector_kernel())
    vt = _moments(m.kernel(100.0, 300.0))
    assert vt[0] == pytest.approx(vs[0] + vd[0], rel=1e-3)
    assert vt[1] == pytest.approx(vs[1] + vd[1], rel=1e-3)
    assert vt[0] > vt[1]  # rows axis has the wider focal spot


def test_tail_support_not_cropped_but_capped_on_request():
    m = _model(detector_fwhm_tail_mm=1.0)  # 100 px FWHM tail
    k = m.kernel(100.0, 150.0)
    assert k.shape[0] >= 2 * 500 + 1
    capped = m.kernel(100.0, 150.0, max_radius_px=50)
    assert capped.shape == (101, 101)
    assert abs(float(capped.sum(dtype=np.float64)) - 1.0) < 1e-5
    # The tail carries 10 % of the mass; with the full support most of it is kept far out.
    r = np.hypot(*np.meshgrid(np.arange(k.shape[0]) - k.shape[0] // 2, np.arange(k.shape[0]) - k.shape[0] // 2))
    assert 0.05 < float(k[r > 50].sum()) < 0.1


def test_narrow_core_only_is_not_a_point_sample():
    # A 0.5 px exponential: point sampling would put ~100 % in the centre pixel; area integration
    # leaves the neighbours their share (checked against a 2-D quadrature of the continuous PSF).
    m = _model(detector_fwhm_core_mm=0.005, detector_weight_core=1.0)
    k = m.detector_kernel()
    s = fwhm_to_scale(0.5, 1.0)
    t = (np.arange(400) + 0.5) / 400 - 0.5
    centre = np.exp(-s * np.hypot(t[:, None], t[None, :])).mean()
    total = 2 * math.pi / s**2
    assert float(k[k.shape[0] // 2, k.shape[1] // 2]) == pytest.approx(centre / total, rel=2e-3)


def test_parameter_validation():
    with pytest.raises(ParameterError, match="detector_weight_core"):
        _model(detector_weight_core=1.5)
    with pytest.raises(ParameterError, match="source_fwhm_x_mm"):
        _model(source_fwhm_x_mm=float("nan"))
    with pytest.raises(ParameterError, match="pixel_pitch_mm"):
        _model(pixel_pitch_mm=0.0)
    with pytest.raises(ParameterError, match="source_to_detector_mm"):
        _model().kernel(200.0, 100.0)
    with pytest.raises(ParameterError, match="max_radius_px"):
        _model().kernel(100.0, 200.0, max_radius_px=-1)


def test_save_load_roundtrip(tmp_path):
    m = _model(uncertainty={"source_fwhm_x_mm": 0.001}, fit_report={"residual_rms": 0.006, "n_images": 4})
    path = save_psf(m, tmp_path / "psf.json")
    back = load_psf(path)
    assert back == m
    np.testing.assert_array_equal(back.kernel(100.0, 200.0), m.kernel(100.0, 200.0))


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d.pop("detector_fwhm_tail_mm"), "detector_fwhm_tail_mm"),
    (lambda d: d.update(source_fwhm_y_mm="wide"), "source_fwhm_y_mm"),
    (lambda d: d.update(detector_weight_core=2.0), "detector_weight_core"),
    (lambda d: d.update(format="something else"), "not a PSF file"),
    (lambda d: d.update(uncertainty=[1, 2]), "uncertainty"),
])
def test_load_rejects_bad_files_with_one_line_naming_file(tmp_path, mutate, match):
    path = save_psf(_model(), tmp_path / "psf.json")
    record = json.loads(path.read_text())
    mutate(record)
    path.write_text(json.dumps(record))
    with pytest.raises(InputError, match=match) as info:
        load_psf(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_load_rejects_missing_and_non_json(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        load_psf(tmp_path / "absent.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        load_psf(bad)


def _generalised(**kw):
    base = dict(pixel_pitch_mm=0.2, source_fwhm_x_mm=0.0, source_fwhm_y_mm=0.0, detector_fwhm_core_mm=0.0,
                detector_fwhm_tail_mm=0.0, detector_weight_core=1.0, detector_core_mtf_scale_mm=0.6,
                detector_core_mtf_power=1.2, detector_core_mtf_linnik=0.0, source_fitted=False)
    base.update(kw)
    return PSFModel(**base)


def test_generalised_core_holds_the_old_core_shapes():
    # u = 0, q = 2: a Gaussian; u = 2/3, q = 2: SABER's exponential core (transform (1 + (2 pi nu)^2)^-1.5).
    f = np.linspace(0.0, 5.0, 41)
    fwhm = 0.6
    gauss = PSFModel(0.2, 0.0, 0.0, fwhm, 0.0, 1.0, shape_power=2.0)
    same = _generalised(detector_core_mtf_scale_mm=np.pi * fwhm / (2 * np.sqrt(np.log(2))), detector_core_mtf_power=2.0)
    np.testing.assert_allclose(same.detector_mtf(f), gauss.detector_mtf(f), atol=1e-12)
    expo = PSFModel(0.2, 0.0, 0.0, fwhm, 0.0, 1.0, shape_power=1.0)
    u = 2.0 / 3.0
    same = _generalised(detector_core_mtf_scale_mm=2 * np.pi * fwhm / (2 * np.log(2)) / np.sqrt(u),
                        detector_core_mtf_power=2.0, detector_core_mtf_linnik=u)
    np.testing.assert_allclose(same.detector_mtf(f), expo.detector_mtf(f), atol=1e-12)
    # The Fourier-synthesised kernel of the first agrees with the area-integrated Gaussian kernel.
    a, b = gauss.detector_kernel().astype(float), _generalised(
        detector_core_mtf_scale_mm=np.pi * fwhm / (2 * np.sqrt(np.log(2))), detector_core_mtf_power=2.0
    ).detector_kernel().astype(float)
    n = max(a.shape[0], b.shape[0])
    pad = lambda k: np.pad(k, ((n - k.shape[0]) // 2,) * 2)  # noqa: E731
    assert np.abs(pad(a) - pad(b)).max() < 0.005 * a.max()


def test_generalised_kernel_carries_its_mtf():
    model = _generalised()
    kernel = model.kernel(100.0, 100.0).astype(float)
    assert kernel.shape[0] % 2 == 1 and abs(kernel.sum() - 1.0) < 1e-5 and kernel.min() >= 0
    line = kernel.sum(axis=0)
    f_px = np.fft.rfftfreq(line.size)
    dft = np.real(np.fft.rfft(np.fft.ifftshift(line)))
    expected = sum(model.detector_mtf((f_px + k) / 0.2) * np.sinc(f_px + k) for k in range(-6, 7))
    assert np.abs(dft - expected).max() < 0.005


def test_not_fitted_source_and_mtf_core_in_the_file(tmp_path):
    model = _generalised(fit_report={"note": "single object-to-detector ratio"})
    path = save_psf(model, tmp_path / "psf.json")
    record = json.loads(path.read_text())
    assert record["format_version"] == 2 and record["source"] == "not fitted"
    assert record["source_fwhm_x_mm"] is None and record["detector_fwhm_core_mm"] is None
    assert load_psf(path) == model
    text = "\n".join(model.describe())
    assert "focal spot: not fitted (single object-to-detector ratio)" in text and "0 x 0" not in text
    assert "MTF50" in text and "tail: none" in text
    with pytest.raises(ParameterError, match="source widths must be 0"):
        _generalised(source_fwhm_x_mm=0.1)


def test_format_1_files_still_load(tmp_path):
    model = _model()
    record = model.to_dict()
    record["format_version"] = 1
    for key in ("detector_core_mtf_scale_mm", "detector_core_mtf_power", "detector_core_mtf_linnik", "source_fitted"):
        record.pop(key)
    path = tmp_path / "old.json"
    path.write_text(json.dumps(record))
    back = load_psf(path)
    assert not back.core_from_mtf and back.source_fitted
    np.testing.assert_array_equal(back.kernel(100.0, 200.0), model.kernel(100.0, 200.0))


def test_generalised_core_kernel_is_cropped_to_its_energy_and_keeps_its_mtf(monkeypatch):
    """A heavy-tailed core (stretched exponential, q 1.39, scale 7.2 px, as fitted on the NIQA
    edge): the 99.9 % crop shrinks the kernel to well under the 30-scale support, and its 2-D MTF
    stays within 2e / (1 - e) = 0.002 of the kernel cropped at 99.99 %."""
    import napari_dslrxr.core.psf.model as model_module

    model = PSFModel(1.0, 0.0, 0.0, 0.0, 0.0, 1.0, detector_core_mtf_scale_mm=7.22, detector_core_mtf_power=1.39,
                     source_fitted=False)
    cropped = model.detector_kernel().astype(float)
    monkeypatch.setattr(model_module, "CORE_KERNEL_ENERGY", 1.0 - 1e-4)
    wide = model.detector_kernel().astype(float)
    assert cropped.shape[0] < 0.6 * wide.shape[0] and cropped.shape[0] > 100

    def mtf(kernel, n=1024):
        padded = np.zeros((n, n))
        padded[:kernel.shape[0], :kernel.shape[1]] = kernel
        return np.abs(np.fft.rfft2(np.roll(padded, (-(kernel.shape[0] // 2),) * 2, (0, 1))))

    assert np.abs(mtf(cropped) - mtf(wide)).max() < 0.002
