"""``python -m napari_dslrxr.demo OUTDIR`` (what ``make demo`` runs), on a small frame."""

import json

import numpy as np
import pydicom
import pytest

from napari_dslrxr.core.io import read_image
from napari_dslrxr.demo import main


@pytest.mark.slow
def test_demo_writes_every_output(tmp_path, capsys):
    assert main([str(tmp_path), "--small"]) == 0
    for name in ("radiograph_dslrxr.tif", "radiograph_dslrxr.png", "radiograph_dslrxr.dcm"):
        assert (tmp_path / name).exists()
        side = json.loads((tmp_path / (name + ".json")).read_text())
        assert side["inputs"][0]["path"].endswith("radiograph.tif") and side["timings_s"]
    for name in ("before_after.png", "params.toml", "input/flat.tif", "input/dark.tif"):
        assert (tmp_path / name).exists()
    panel = read_image(tmp_path / "before_after.png").data
    assert panel.shape == (384, 2 * 576 + 8)
    ds = pydicom.dcmread(tmp_path / "radiograph_dslrxr.dcm")
    assert ds.Modality == "DX" and float(ds.PixelSpacing[0]) == 0.2
    out = read_image(tmp_path / "radiograph_dslrxr.tif").data
    assert np.array_equal(ds.pixel_array, out)
    assert "wrote" in capsys.readouterr().out


@pytest.mark.slow
def test_demo_fits_the_frame_blur_and_deblurs_with_it(tmp_path, capsys):
    from napari_dslrxr.core.stages.deconvolution import REG_MAX, REG_MIN
    from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph
    from napari_dslrxr.core.psf import load_psf
    from napari_dslrxr.demo import DEMO_SOURCE_TO_DETECTOR_MM, DEMO_SOURCE_TO_OBJECT_MM

    assert main([str(tmp_path), "--small"]) == 0
    model = load_psf(tmp_path / "psf.json")
    # The edges carry the phantom's Gaussian blur: the fitted kernel must have its width.
    sigma_px = make_dslr_radiograph((64, 64)).truth.blur_sigma_px
    kernel = model.kernel(DEMO_SOURCE_TO_OBJECT_MM, DEMO_SOURCE_TO_DETECTOR_MM).astype(np.float64)
    r = np.arange(kernel.shape[0]) - kernel.shape[0] // 2
    variance = float((kernel.sum(axis=0) * r**2).sum())
    assert abs(np.sqrt(variance) - sigma_px) < 0.1 * sigma_px
    side = json.loads((tmp_path / "radiograph_dslrxr.tif.json").read_text())
    assert side["results"]["deblur"]["method"] == "adaptive"
    reg_used = side["results"]["deblur"]["reg_used"]  # the one auto value the solver used for all channels
    assert isinstance(reg_used, float) and REG_MIN <= reg_used <= REG_MAX
    assert side["results"]["run_options"] == {"source_to_object_mm": DEMO_SOURCE_TO_OBJECT_MM,
                                              "source_to_detector_mm": DEMO_SOURCE_TO_DETECTOR_MM}
    assert any(i["path"].endswith("psf.json") for i in side["inputs"])
