"""Same input and parameters, same bytes: every output the ``dslrxr`` commands write, run twice.

Each command runs twice in its own process into the same output path; every output file except
the sidecars (``<file>.json``, which hold timings and dates by design) must be byte-identical.
A time or date inside an output would also change the DICOM UIDs downstream, because they are
seeded by the checksums of the input files (e.g. a ``psf.json`` given to ``dslrxr run``).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from napari_dslrxr.core.io import write_tiff
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph
from napari_dslrxr.core.simulation.simulator import phantom_thickness_mm
from napari_dslrxr.demo import write_edge_radiographs

def _dslrxr(*args) -> None:
    proc = subprocess.run([sys.executable, "-m", "napari_dslrxr.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"dslrxr {' '.join(map(str, args))} exited {proc.returncode}: {proc.stderr}"


def _outputs(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` but the sidecars, by relative path."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not _is_sidecar(p)}


def _is_sidecar(path: Path) -> bool:
    return path.suffix == ".json" and path.with_name(path.name[:-len(".json")]).is_file()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory, phantom_scene_text) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("inputs")
    frames = make_dslr_radiograph((128, 192), seed=1)
    for name, arr in (("radiograph", frames.raw_rgb), ("flat", frames.flat), ("dark", frames.dark)):
        write_tiff(folder / f"{name}.tif", arr)
    edges = write_edge_radiographs(folder, frames.truth.blur_sigma_px, seed=1)
    write_tiff(folder / "thickness.tif", phantom_thickness_mm((64, 64)))
    (folder / "scene.toml").write_text(phantom_scene_text, encoding="utf-8")
    return {"folder": folder, "edges": edges, "scene": folder / "scene.toml"}


@pytest.mark.slow
def test_every_command_writes_the_same_bytes_twice(inputs, tmp_path):
    src = inputs["folder"]
    out = tmp_path / "out"
    out.mkdir()
    commands = [
        ("psf", "fit", inputs["edges"], "-o", out / "psf.json"),
        ("psf", "kernel", out / "psf.json", "--source-to-object-mm", "1150", "--source-to-detector-mm", "1200",
         "-o", out / "kernel.tif", "--max-radius-px", "8"),
        ("run", src / "radiograph.tif", "--flat", src / "flat.tif", "--dark", src / "dark.tif",
         "--psf", out / "psf.json", "--source-to-object-mm", "1150", "--source-to-detector-mm", "1200",
         "--dicom", "--overwrite", "-o", out / "run"),
        ("denoise", src / "radiograph.tif", "-o", out / "denoised.tif", "--mask-out", out / "mask.tif"),
        ("deconvolve", src / "flat.tif", "--kernel", out / "kernel.tif", "--method", "wiener", "--reg", "10",
         "-o", out / "deconvolved.tif"),
        ("simulate", inputs["scene"], "-o", out / "recording.tif", "--seed", "2"),
        ("diagnose", inputs["scene"], out / "recording.tif", "-o", out / "diagnosis", "--max-terms", "1"),
    ]
    for command in commands:
        _dslrxr(*command)
    first = _outputs(out)
    for command in commands:
        _dslrxr(*command)
    second = _outputs(out)
    assert set(first) == set(second)
    expected = {"psf.json", "kernel.tif", "run/radiograph_dslrxr.tif", "run/radiograph_dslrxr.png",
                "run/radiograph_dslrxr.dcm", "denoised.tif", "mask.tif", "deconvolved.tif", "recording.tif",
                "diagnosis/diagnosis.json", "diagnosis/diagnosis_details.json", "diagnosis/report.html",
                "diagnosis/residual_base.tif", "diagnosis/residual_final.tif"}
    assert expected <= set(first), sorted(set(first))
    changed = sorted(name for name in first if first[name] != second[name])
    for name in changed:  # kept beside the second run's file, for a look at what differs
        kept = tmp_path / "first_run" / name
        kept.parent.mkdir(parents=True, exist_ok=True)
        kept.write_bytes(first[name])
    assert not changed, f"outputs that differ between two identical runs: {changed}"
