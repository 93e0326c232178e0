"""Reruns follow parameters: ``dslrxr run`` into a folder with finished outputs skips a file
only when its sidecars record the same input checksums, parameters and version, and says why
it redoes the others."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from napari_dslrxr.cli import main
from napari_dslrxr.core.io import write_tiff
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rerun")
    made = make_dslr_radiograph((128, 192), seed=3)
    other = make_dslr_radiograph((128, 192), seed=4)
    return {"shot": write_tiff(folder / "shot.tif", made.raw_rgb), "flat": write_tiff(folder / "flat.tif", made.flat),
            "dark": write_tiff(folder / "dark.tif", made.dark), "other_raw": other.raw_rgb, "other_flat": other.flat}


def _dslrxr(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "napari_dslrxr.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=180)


@pytest.mark.slow
def test_changing_bone_contrast_in_the_parameter_file_redoes_the_file(tmp_path, frames):
    out, cfg = tmp_path / "out", tmp_path / "p.toml"
    refs = ["--flat", frames["flat"], "--dark", frames["dark"]]
    cfg.write_text("[contrast]\nbone_contrast = 1.0\n")
    first = _dslrxr("run", frames["shot"], *refs, "-o", out, "-c", cfg)
    assert first.returncode == 0, first.stderr
    before = (out / "shot_dslrxr.tif").read_bytes()
    cfg.write_text("[contrast]\nbone_contrast = 1.8\n")
    second = _dslrxr("run", frames["shot"], *refs, "-o", out, "-c", cfg)
    assert second.returncode == 0, second.stderr
    assert "redoing shot.tif: parameters changed: contrast.bone_contrast 1.0 -> 1.8" in second.stderr
    assert "skipped" not in second.stderr
    after = (out / "shot_dslrxr.tif").read_bytes()
    assert after != before
    side = json.loads((out / "shot_dslrxr.tif.json").read_text())
    assert side["parameters"]["contrast"]["bone_contrast"] == 1.8
    # what a fresh run with the new file writes, byte for byte
    assert main(["run", str(frames["shot"]), *map(str, refs), "-o", str(tmp_path / "fresh"), "-c", str(cfg)]) == 0
    assert (tmp_path / "fresh" / "shot_dslrxr.tif").read_bytes() == after
    # same request again, and a change of [batch] only (where it runs, not what it computes): skipped
    cfg.write_text("[contrast]\nbone_contrast = 1.8\n[batch]\njobs = 3\n")
    third = _dslrxr("run", frames["shot"], *refs, "-o", out, "-c", cfg)
    assert third.returncode == 0 and "skipped 1 file(s)" in third.stderr and "redoing" not in third.stderr
    assert (out / "shot_dslrxr.tif").read_bytes() == after


def _tamper_version(out):
    for side in out.glob("*.json"):
        record = json.loads(side.read_text())
        record["version"] = "0.0.1"
        side.write_text(json.dumps(record))


@pytest.mark.parametrize("change,extra,reason", [
    ("version", [], "made by version 0.0.1 (this is "),
    ("input", [], "input frame shot.tif changed (checksum)"),
    ("flat", [], "flat frame flat.tif changed (checksum)"),
    ("no dark", [], "not the same number of flat, dark or PSF files as the last run"),
    ("output replaced", [], "shot_dslrxr.tif differs from the file its sidecar describes"),
    ("sidecar lost", [], "shot_dslrxr.png has no sidecar"),
    ("dicom asked", ["--dicom"], "shot_dslrxr.dcm missing"),
    ("patient", ["--dicom", "--patient-id", "B-2"], "patient fields changed"),
])
def test_any_change_of_inputs_version_or_outputs_redoes_the_file(tmp_path, frames, capsys, change, extra, reason):
    folder = tmp_path / "in"
    folder.mkdir()
    shot, flat, dark = (folder / "shot.tif", folder / "flat.tif", folder / "dark.tif")
    for name, path in (("shot", shot), ("flat", flat), ("dark", dark)):
        path.write_bytes(frames[name].read_bytes())
    out = tmp_path / "out"
    refs = ["--flat", str(flat), "--dark", str(dark)]
    first_extra = ["--dicom", "--patient-id", "A-1"] if change == "patient" else []
    assert main(["run", str(shot), *refs, "-o", str(out), *first_extra]) == 0
    assert main(["run", str(shot), *refs, "-o", str(out), *first_extra]) == 0  # unchanged: skipped
    assert "skipped 1 file(s)" in capsys.readouterr().err
    if change == "version":
        _tamper_version(out)
    elif change == "input":
        write_tiff(shot, frames["other_raw"])
    elif change == "flat":
        write_tiff(flat, frames["other_flat"])
    elif change == "no dark":
        refs = refs[:2]
    elif change == "output replaced":  # as a later run killed between image and sidecar leaves it
        (out / "shot_dslrxr.tif").write_bytes((out / "shot_dslrxr.tif").read_bytes()[:-2] + b"\x00\x01")
    elif change == "sidecar lost":
        (out / "shot_dslrxr.png.json").unlink()
    assert main(["run", str(shot), *refs, "-o", str(out), *extra]) == 0
    err = capsys.readouterr().err
    assert f"redoing shot.tif: {reason}" in err and "skipped" not in err
    # the redone outputs are exactly a fresh run's
    assert main(["run", str(shot), *refs, "-o", str(tmp_path / "fresh"), *extra]) == 0
    for path in (tmp_path / "fresh").iterdir():
        if path.suffix != ".json":
            assert (out / path.name).read_bytes() == path.read_bytes(), path.name
    assert main(["run", str(shot), *refs, "-o", str(out), *extra]) == 0
    assert "skipped 1 file(s)" in capsys.readouterr().err  # and now it is done


def test_overwrite_redoes_finished_files(tmp_path, frames, capsys):
    out = tmp_path / "out"
    assert main(["run", str(frames["shot"]), "-o", str(out)]) == 0
    mtime = (out / "shot_dslrxr.tif").stat().st_mtime_ns
    assert main(["run", str(frames["shot"]), "-o", str(out), "--overwrite"]) == 0
    err = capsys.readouterr().err
    assert "skipped" not in err and "[1/1] " in err
    assert (out / "shot_dslrxr.tif").stat().st_mtime_ns != mtime
