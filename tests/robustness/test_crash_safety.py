"""Crash safety and determinism of a batch: kill it, check what is left, rerun, compare bytes.

``dslrxr run`` is started in its own process and SIGKILLed after new outputs appear, several
times over. After every kill each file under a final name must be complete (a readable
image whose sidecar checksum matches it) and the inputs unchanged; a rerun without
``--overwrite`` then finishes the batch, and the result is byte-identical to an uninterrupted
run, to a second run and to a run with ``--jobs 2``.
"""

from __future__ import annotations

import builtins
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from napari_dslrxr import cli
from napari_dslrxr.core import io

N_FILES = 8
KILL_ROUNDS = 3
RUN_TIMEOUT_S = 120


@pytest.fixture(scope="module")
def batch(tmp_path_factory) -> Path:
    """N_FILES small synthetic radiographs (uint16 TIFF) in a read-only folder."""
    folder = tmp_path_factory.mktemp("batch")
    rng = np.random.default_rng(11)
    y, x = np.mgrid[0:192, 0:256]
    for i in range(N_FILES):
        body = 30000 - 12000 * np.exp(-(((x - 128 - 4 * i) / 50.0) ** 2 + ((y - 96) / 40.0) ** 2))
        image = rng.poisson(np.clip(body, 1, None) / 4.0) * 4 + 200
        tifffile.imwrite(folder / f"frame_{i:02d}.tif", np.clip(image, 0, 65535).astype(np.uint16))
    for p in folder.iterdir():
        p.chmod(0o444)
    return folder


def _checksums(folder: Path) -> dict[str, str]:
    return {p.name: io.file_sha256(p) for p in sorted(folder.iterdir()) if p.is_file()}


def _final_files(out: Path) -> list[Path]:
    return sorted(p for p in out.iterdir() if not p.name.startswith("."))


def assert_nothing_partial(out: Path) -> None:
    """Every file under a final name is complete and, if it has a sidecar, matches it."""
    for path in _final_files(out):
        if path.suffix == ".tif":
            with tifffile.TiffFile(path) as tif:
                assert tif.asarray().shape[:2] == (192, 256), path
        elif path.suffix == ".png":
            assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is not None, path
        elif path.suffix == ".dcm":
            import pydicom

            assert pydicom.dcmread(path).pixel_array.shape == (192, 256), path
        elif path.suffix == ".json":
            record = json.loads(path.read_text())
            described = path.with_name(record["output"]["path"])
            assert described.exists(), f"{path} describes a missing output"
            assert io.file_sha256(described) == record["output"]["sha256"], f"{path} does not match its output"
        else:
            raise AssertionError(f"unexpected file {path}")


def _start(batch: Path, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "napari_dslrxr.cli", "run", str(batch), "-o", str(out), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)


@pytest.mark.slow
def test_killed_batch_leaves_nothing_partial_and_a_rerun_completes(batch, tmp_path):
    inputs_before = _checksums(batch)
    out = tmp_path / "out"
    rng = np.random.default_rng(5)
    kills = 0
    for _ in range(KILL_ROUNDS):
        done_before = len(_final_files(out)) if out.exists() else 0
        proc = _start(batch, out)
        deadline = time.monotonic() + RUN_TIMEOUT_S
        while proc.poll() is None and time.monotonic() < deadline:
            if out.exists() and len(_final_files(out)) > done_before:
                time.sleep(float(rng.uniform(0.0, 0.3)))  # land anywhere in the next file
                break
            time.sleep(0.005)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)  # the process group this test started
            kills += 1
        proc.communicate(timeout=RUN_TIMEOUT_S)
        assert_nothing_partial(out)
        assert _checksums(batch) == inputs_before
    assert kills >= 1, "the batch finished before it could be killed; make it longer"
    proc = _start(batch, out)
    _, err = proc.communicate(timeout=RUN_TIMEOUT_S)
    assert proc.returncode == 0, err.decode()
    assert_nothing_partial(out)
    names = {p.name for p in _final_files(out)}
    images = [f"frame_{i:02d}_dslrxr{ext}" for i in range(N_FILES) for ext in (".tif", ".png")]
    assert set(images) <= names, sorted(set(images) - names)
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")], "temporary files left behind"
    assert _checksums(batch) == inputs_before
    # The interrupted-and-resumed batch equals an uninterrupted one, byte for byte.
    reference = tmp_path / "reference"
    assert cli.main(["run", str(batch), "-o", str(reference)]) == 0
    assert _image_bytes(out) == _image_bytes(reference)
    missing_sidecars = [name for name in images if name + ".json" not in names]
    assert not missing_sidecars, f"rerun left outputs without sidecars: {missing_sidecars}"


def _image_bytes(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in _final_files(out) if p.suffix in (".tif", ".png", ".dcm")}


def _sidecars_without_timings(out: Path) -> dict[str, dict]:
    records = {}
    for p in _final_files(out):
        if p.suffix == ".json":
            record = json.loads(p.read_text())
            record.pop("timings_s", None)
            records[p.name] = record
    return records


def test_same_batch_gives_identical_bytes_across_runs_and_job_counts(batch, tmp_path, capsys):
    runs = {}
    for name, jobs in (("first", "1"), ("second", "1"), ("parallel", "2")):
        out = tmp_path / name
        code = cli.main(["run", str(batch), "-o", str(out), "--jobs", jobs, "--dicom",
                         "--patient-id", "TEST-0001"])
        assert code == 0, capsys.readouterr().err
        runs[name] = out
    first = _image_bytes(runs["first"])
    assert len(first) == 3 * N_FILES  # TIFF, PNG and DICOM per input
    assert _image_bytes(runs["second"]) == first
    assert _image_bytes(runs["parallel"]) == first
    # Sidecars agree on everything but the wall-clock timings: parameters, versions, checksums.
    assert _sidecars_without_timings(runs["second"]) == _sidecars_without_timings(runs["first"])
    assert _sidecars_without_timings(runs["parallel"]) == _sidecars_without_timings(runs["first"])


def test_inputs_are_opened_read_only(batch, tmp_path, monkeypatch):
    """Every open() of an input file during a run asks for reading only."""
    inputs = {str(p.resolve()) for p in batch.iterdir()}
    modes: list[tuple[str, str]] = []
    real_open, real_os_open = builtins.open, os.open

    def spy_open(file, mode="r", *args, **kwargs):
        if isinstance(file, (str, os.PathLike)) and str(Path(file).resolve()) in inputs:
            modes.append((str(file), mode))
        return real_open(file, mode, *args, **kwargs)

    def spy_os_open(file, flags, *args, **kwargs):
        if isinstance(file, (str, os.PathLike)) and str(Path(file).resolve()) in inputs:
            modes.append((str(file), "w" if flags & (os.O_WRONLY | os.O_RDWR | os.O_TRUNC) else "r"))
        return real_os_open(file, flags, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", spy_open)
    monkeypatch.setattr(os, "open", spy_os_open)
    before = _checksums(batch)
    assert cli.main(["run", str(batch), "-o", str(tmp_path / "o")]) == 0
    monkeypatch.undo()
    assert modes, "the spy saw no input being opened"
    assert all(set(mode) <= set("rbt") for _, mode in modes), modes
    assert _checksums(batch) == before


def test_sidecar_records_enough_to_reproduce_the_output(batch, tmp_path, capsys):
    """Rebuild the parameter file from a sidecar alone, rerun, and get the recorded checksum."""
    from napari_dslrxr.core import params

    config = tmp_path / "custom.toml"
    custom = params.params_to_dict(params.PipelineParams())
    custom["impulse"]["passes_grey"] = 2
    custom["dynamic_range"]["latitude"] = 0.5
    params.save_params(params.params_from_dict(custom), config)
    src = batch / "frame_00.tif"
    assert cli.main(["run", str(src), "-o", str(tmp_path / "a"), "-c", str(config)]) == 0, capsys.readouterr().err
    record = json.loads((tmp_path / "a" / "frame_00_dslrxr.tif.json").read_text())
    assert record["inputs"][0]["sha256"] == io.file_sha256(src)
    assert record["version"] and record["environment"]["numpy"]
    rebuilt = tmp_path / "rebuilt.toml"
    params.save_params(params.params_from_dict(record["parameters"]), rebuilt)
    assert cli.main(["run", str(src), "-o", str(tmp_path / "b"), "-c", str(rebuilt)]) == 0
    assert io.file_sha256(tmp_path / "b" / "frame_00_dslrxr.tif") == record["output"]["sha256"]
    # The defaults give another image, so the check above can fail.
    assert cli.main(["run", str(src), "-o", str(tmp_path / "c")]) == 0
    assert io.file_sha256(tmp_path / "c" / "frame_00_dslrxr.tif") != record["output"]["sha256"]


def test_sidecar_records_the_psf_geometry_of_a_deblurred_output(batch, tmp_path, capsys):
    """With --psf the output depends on the two distances: the sidecar must hold them."""
    from napari_dslrxr.core import psf

    model = psf.PSFModel(pixel_pitch_mm=0.1, source_fwhm_x_mm=0.3, source_fwhm_y_mm=0.3,
                         detector_fwhm_core_mm=0.12, detector_fwhm_tail_mm=0.6, detector_weight_core=0.8)
    psf_path = psf.save_psf(model, tmp_path / "psf.json")
    code = cli.main(["run", str(batch / "frame_01.tif"), "-o", str(tmp_path / "o"), "--psf", str(psf_path),
                     "--source-to-object-mm", "900", "--source-to-detector-mm", "1000"])
    assert code == 0, capsys.readouterr().err
    record = json.loads((tmp_path / "o" / "frame_01_dslrxr.tif.json").read_text())
    assert io.file_sha256(psf_path) in [i["sha256"] for i in record["inputs"]]  # a checksummed input
    numbers = set(_numbers(record["parameters"])) | set(_numbers(record["results"]))
    assert {900.0, 1000.0} <= numbers, "the sidecar does not record the deblurring geometry"


def _numbers(value):
    """Every number inside a JSON value."""
    if isinstance(value, dict):
        for v in value.values():
            yield from _numbers(v)
    elif isinstance(value, list):
        for v in value:
            yield from _numbers(v)
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        yield float(value)


def test_rerun_completes_a_batch_killed_between_an_image_and_its_sidecar(batch, tmp_path, capsys):
    """The kill test's random timing hits this state only sometimes; build it on purpose."""
    out = tmp_path / "out"
    assert cli.main(["run", str(batch / "frame_02.tif"), "-o", str(out)]) == 0
    sidecar = out / "frame_02_dslrxr.png.json"
    sidecar.unlink()  # what a SIGKILL after the PNG's rename and before its sidecar leaves
    assert cli.main(["run", str(batch / "frame_02.tif"), "-o", str(out)]) == 0
    capsys.readouterr()
    assert sidecar.exists(), "the rerun skipped an input whose sidecar was missing"
    assert_nothing_partial(out)


def test_denoise_gives_identical_bytes_on_every_run(batch, tmp_path, capsys):
    outputs = []
    for run in ("a", "b"):
        (tmp_path / run).mkdir()
        code = cli.main(["denoise", str(batch / "frame_03.tif"), "-o", str(tmp_path / run / "clean.tif"),
                         "--mask-out", str(tmp_path / run / "mask.tif")])
        assert code == 0, capsys.readouterr().err
        outputs.append({p.name: p.read_bytes() for p in (tmp_path / run).glob("*.tif")})
    assert set(outputs[0]) == {"clean.tif", "mask.tif"} and outputs[0] == outputs[1]
