"""``python -m napari_dslrxr.demo OUTDIR`` (what ``make demo`` runs), on a small frame."""

import json

import numpy as np
import pydicom

from napari_dslrxr.core.io import read_image
from napari_dslrxr.demo import main


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
