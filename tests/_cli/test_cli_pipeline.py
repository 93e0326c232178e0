"""``dslrxr run`` and ``dslrxr params`` through napari_dslrxr.cli.main."""

import tomllib

import pytest

from napari_dslrxr.cli import main
from napari_dslrxr.core.io import write_tiff
from napari_dslrxr.core.params import PipelineParams, params_from_dict
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("in")
    paths = {}
    for seed in (1, 2):
        frames = make_dslr_radiograph((128, 192), seed=seed)
        paths[f"shot{seed}"] = write_tiff(folder / f"shot{seed}.tif", frames.raw_rgb)
    paths["flat"] = write_tiff(folder / "flat.tif", frames.flat)
    paths["dark"] = write_tiff(folder / "dark.tif", frames.dark)
    bad = folder / "broken.tif"
    bad.write_bytes(b"II*\x00" + b"\x00" * 20)
    paths["bad"] = bad
    return paths


def test_params_default_prints_full_commented_file(capsys):
    assert main(["params", "--default"]) == 0
    text = capsys.readouterr().out
    assert params_from_dict(tomllib.loads(text)) == PipelineParams()
    assert "# strength of subtle-detail enhancement" in text


def test_params_check_reports_unknown_key(tmp_path, capsys):
    cfg = tmp_path / "p.toml"
    cfg.write_text("[contrast]\ndetial_contrast = 0.5\n")
    assert main(["params", "--check", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "did you mean 'detail_contrast'?" in err and err.count("\n") == 1


def test_batch_with_one_bad_file_skip_and_overwrite(tmp_path, inputs, capsys):
    out = tmp_path / "out"
    args = ["run", str(inputs["shot1"]), str(inputs["bad"]), str(inputs["shot2"]), "-o", str(out),
            "--flat", str(inputs["flat"]), "--dark", str(inputs["dark"]), "--dicom"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "broken.tif" in err and "1 of 3 file(s) failed" in err
    for stem in ("shot1", "shot2"):
        for ext in ("tif", "png", "dcm"):
            assert (out / f"{stem}_dslrxr.{ext}").exists() and (out / f"{stem}_dslrxr.{ext}.json").exists()
    assert not (out / "broken_dslrxr.tif").exists()
    before = (out / "shot1_dslrxr.tif").stat().st_mtime_ns
    assert main(args[:2] + args[3:]) == 0  # good files only: finished outputs are skipped
    assert "skipped 2 file(s)" in capsys.readouterr().err
    assert (out / "shot1_dslrxr.tif").stat().st_mtime_ns == before
    assert main(args[:2] + args[3:] + ["--overwrite"]) == 0


def test_jobs_give_identical_outputs(tmp_path, inputs):
    common = [str(inputs["shot1"]), str(inputs["shot2"]), "--flat", str(inputs["flat"]), "--dark",
              str(inputs["dark"]), "--dicom"]
    assert main(["run", *common, "-o", str(tmp_path / "j1"), "--jobs", "1"]) == 0
    assert main(["run", *common, "-o", str(tmp_path / "j2"), "--jobs", "2"]) == 0
    for name in ("shot1_dslrxr.tif", "shot2_dslrxr.png", "shot2_dslrxr.dcm"):
        assert (tmp_path / "j1" / name).read_bytes() == (tmp_path / "j2" / name).read_bytes()


def test_pool_workers_map_the_reference_the_command_prepares_once(tmp_path, inputs, monkeypatch):
    """--jobs 2: the command reads the flats and darks and prepares the reference once; its pool
    workers (forked, so they count their reads in the same file) read none and map it; the
    outputs are those of --jobs 1 and the shared reference folder is gone at the end."""
    import os

    from napari_dslrxr.core import files as core_files

    log = tmp_path / "reads.txt"
    real_load = core_files.load_frames

    def counted(paths):
        with open(log, "a") as f:
            f.write(f"{os.getpid()} {' '.join(map(str, paths))}\n")
        return real_load(paths)

    monkeypatch.setattr(core_files, "load_frames", counted)
    shots = [str(inputs["shot1"]), str(inputs["shot2"])]
    common = [*shots, "--flat", str(inputs["flat"]), "--dark", str(inputs["dark"])]
    assert main(["run", *common, "-o", str(tmp_path / "j2"), "--jobs", "2"]) == 0
    reads = log.read_text().splitlines()
    assert reads == [f"{os.getpid()} {inputs['flat']}", f"{os.getpid()} {inputs['dark']}"]
    assert not [p.name for p in (tmp_path / "j2").iterdir() if p.name.startswith(".")]
    monkeypatch.setattr(core_files, "load_frames", real_load)
    assert main(["run", *common, "-o", str(tmp_path / "seq")]) == 0
    for name in ("shot1_dslrxr.tif", "shot2_dslrxr.png"):
        assert (tmp_path / "j2" / name).read_bytes() == (tmp_path / "seq" / name).read_bytes()


def test_config_and_usage_errors(tmp_path, inputs, capsys):
    cfg = tmp_path / "p.toml"
    cfg.write_text("[contrast]\nbone_contrast = 99.0\n")
    assert main(["run", str(inputs["shot1"]), "-o", str(tmp_path / "o"), "-c", str(cfg)]) == 2
    assert "contrast.bone_contrast" in capsys.readouterr().err
    assert main(["run", str(inputs["shot1"]), "-o", str(tmp_path / "o"), "--psf", str(cfg)]) == 2
    assert "--source-to-object-mm" in capsys.readouterr().err


def test_psf_model_turns_on_deblurring(tmp_path, inputs):
    import json

    from napari_dslrxr.core.psf import PSFModel, save_psf

    psf = save_psf(PSFModel(pixel_pitch_mm=0.1, source_fwhm_x_mm=0.3, source_fwhm_y_mm=0.3,
                            detector_fwhm_core_mm=0.15, detector_fwhm_tail_mm=0.4,
                            detector_weight_core=0.8, shape_power=1.5), tmp_path / "psf.json")
    out = tmp_path / "o"
    assert main(["run", str(inputs["shot1"]), "-o", str(out), "--flat", str(inputs["flat"]),
                 "--psf", str(psf), "--source-to-object-mm", "500", "--source-to-detector-mm", "1000"]) == 0
    side = json.loads((out / "shot1_dslrxr.tif.json").read_text())
    assert side["results"]["deblur"]["method"] == "adaptive"
    assert any(entry["path"].endswith("psf.json") for entry in side["inputs"])
