"""Sidecars: what they record, that it is enough to check a reproduction, and that odd values survive."""

from __future__ import annotations

import enum
import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from napari_dslrxr import __version__
from napari_dslrxr.core import io
from napari_dslrxr.core.io import provenance
from napari_dslrxr.core.errors import InputError, OutputError


@dataclass
class _Params:
    sigma_px: float = 1.5
    passes: tuple = (3, 1, 1)
    space: str = "hsv"


class _Space(enum.Enum):
    GREY = "grey"


def _stage(image: np.ndarray, params: _Params) -> np.ndarray:
    """A stand-in stage: deterministic in its input and parameters."""
    return (image.astype(np.float32) * params.sigma_px + sum(params.passes)).astype(np.float32)


def test_sidecar_records_version_parameters_inputs_output_and_environment(tmp_path, rng):
    src = io.write_tiff(tmp_path / "in.tif", rng.integers(0, 4000, (16, 16)).astype(np.uint16))
    params = _Params()
    out = io.write_tiff(tmp_path / "out.tif", _stage(io.read_image(src).data, params), inputs=[src])
    side = provenance.write_sidecar(out, stage="denoise", parameters=params, inputs=[src],
                                    timings_s={"denoise": 0.123456}, results={"gain": np.float32(2.5)})
    assert side == tmp_path / "out.tif.json"
    record = json.loads(side.read_text())
    assert record["version"] == __version__ and record["stage"] == "denoise"
    assert record["parameters"] == {"sigma_px": 1.5, "passes": [3, 1, 1], "space": "hsv"}
    assert record["inputs"] == [{"path": str(src), "bytes": src.stat().st_size, "sha256": io.file_sha256(src)}]
    assert record["output"] == {"path": "out.tif", "sha256": io.file_sha256(out)}
    assert record["results"] == {"gain": 2.5} and record["timings_s"] == {"denoise": 0.1235}
    for lib in ("python", "numpy", "tifffile", "rawpy", "libraw"):
        assert record["environment"][lib]


def test_sidecar_is_enough_to_verify_a_reproduction(tmp_path, rng):
    """Re-running from what the sidecar records gives the recorded output checksum."""
    src = io.write_tiff(tmp_path / "in.tif", rng.integers(0, 4000, (16, 16)).astype(np.uint16))
    out = io.write_tiff(tmp_path / "out.tif", _stage(io.read_image(src).data, _Params(sigma_px=0.5)))
    provenance.write_sidecar(out, stage="x", parameters=_Params(sigma_px=0.5), inputs=[src])
    record = json.loads(provenance.sidecar_path(out).read_text())
    (rec_input,) = record["inputs"]
    assert io.file_sha256(rec_input["path"]) == rec_input["sha256"]
    params = _Params(**{**record["parameters"], "passes": tuple(record["parameters"]["passes"])})
    again = io.write_tiff(tmp_path / "again.tif", _stage(io.read_image(rec_input["path"]).data, params))
    assert io.file_sha256(again) == record["output"]["sha256"]
    # A different parameter gives a different checksum, so the check can fail.
    other = io.write_tiff(tmp_path / "other.tif", _stage(io.read_image(src).data, _Params()))
    assert io.file_sha256(other) != record["output"]["sha256"]


def test_sidecars_of_identical_runs_differ_only_in_timings(tmp_path, rng):
    src = io.write_tiff(tmp_path / "in.tif", rng.integers(0, 4000, (16, 16)).astype(np.uint16))
    records = []
    for i, seconds in enumerate((0.5, 0.7)):
        out = io.write_tiff(tmp_path / f"out{i}.tif",
                            _stage(io.read_image(src).data, _Params()))
        provenance.write_sidecar(out, stage="x", parameters=_Params(), inputs=[src], timings_s={"x": seconds})
        record = json.loads(provenance.sidecar_path(out).read_text())
        record["output"].pop("path")
        record.pop("timings_s")
        records.append(record)
    assert records[0] == records[1]


def test_to_jsonable_handles_numpy_nonfinite_enums_sets_and_paths():
    value = {"a": np.float64("nan"), "b": np.array([1.0, np.inf]), "c": _Space.GREY, "d": {3, 1},
             "e": Path("x/y.tif"), 4: np.int64(7), "f": (np.bool_(True), None), "g": math.inf,
             "h": object.__new__(_Opaque)}
    got = provenance.to_jsonable(value)
    assert got == {"a": None, "b": [1.0, None], "c": "grey", "d": [1, 3], "e": "x/y.tif", "4": 7,
                   "f": [True, None], "g": None, "h": "opaque"}
    json.dumps(got, allow_nan=False)  # would raise on a NaN left behind


class _Opaque:
    def __str__(self) -> str:
        return "opaque"


def test_missing_input_or_output_is_a_one_line_error(tmp_path):
    out = io.write_tiff(tmp_path / "out.tif", np.zeros((8, 8), np.uint8))
    with pytest.raises(InputError, match="gone.tif: cannot checksum input"):
        provenance.write_sidecar(out, stage="x", parameters={}, inputs=[tmp_path / "gone.tif"])
    with pytest.raises(OutputError, match="cannot checksum the output"):
        provenance.write_sidecar(tmp_path / "never.tif", stage="x", parameters={})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.tif"]


def _age(path: Path, seconds: float) -> None:
    old = path.stat().st_mtime - seconds
    os.utime(path, (old, old))


def test_a_settled_input_is_hashed_once_per_process(tmp_path, monkeypatch):
    from napari_dslrxr.core.io import writers

    path = tmp_path / "flat.bin"
    path.write_bytes(b"a" * 5000)
    _age(path, 60)
    # ctime cannot be set back: wait until the change time is settled too
    monkeypatch.setattr(writers, "_SETTLED_NS", 0)
    first = writers.file_sha256(path)
    opened = []
    real_open = open
    monkeypatch.setattr(writers, "open", lambda *a, **k: opened.append(a) or real_open(*a, **k), raising=False)
    assert writers.file_sha256(path) == first == hashlib.sha256(b"a" * 5000).hexdigest()
    assert opened == []


def test_a_changed_input_is_hashed_again_even_with_its_size_and_mtime_restored(tmp_path, monkeypatch):
    from napari_dslrxr.core.io import writers

    monkeypatch.setattr(writers, "_SETTLED_NS", 0)
    path = tmp_path / "dark.bin"
    path.write_bytes(b"a" * 5000)
    _age(path, 60)
    mtime = path.stat().st_mtime_ns
    assert writers.file_sha256(path) == hashlib.sha256(b"a" * 5000).hexdigest()
    with open(path, "r+b") as fh:  # same size, same inode
        fh.write(b"b")
    os.utime(path, ns=(mtime, mtime))
    assert writers.file_sha256(path) == hashlib.sha256(b"b" + b"a" * 4999).hexdigest()


def test_a_file_rewritten_within_the_time_stamp_step_is_never_stale(tmp_path):
    from napari_dslrxr.core.io import writers

    path = tmp_path / "input.bin"
    for content in (b"x" * 100, b"y" * 100, b"z" * 100):  # same size, same coarse time stamp
        with open(path, "r+b" if path.exists() else "wb") as fh:
            fh.write(content)
        assert writers.file_sha256(path) == hashlib.sha256(content).hexdigest()
