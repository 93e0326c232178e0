"""Privacy: outputs carry no personal metadata from the input; DICOM patient fields only from the user.

The inputs are built WITH a camera serial number, an owner name and a GPS position (DNG tags
and XMP) or with patient, operator and device fields (DICOM); every byte of every output,
sidecars included, is scanned for those strings.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydicom
import tifffile
from robustness.synthetic_files import PRIVATE_STRINGS, write_dicom, write_dng

from napari_dslrxr import cli

#: TIFF tags that would carry personal or device-identifying data.
_PERSONAL_TIFF_TAGS = {315: "Artist", 33432: "Copyright", 34665: "ExifIFD", 34853: "GPSIFD", 50735: "CameraSerialNumber",
                       42033: "BodySerialNumber", 42032: "CameraOwnerName", 700: "XMP", 37500: "MakerNote"}


def _private_dng(folder: Path, rng) -> Path:
    y, x = np.mgrid[0:192, 0:256]
    signal = 1500 + 800 * np.sin(x / 25.0) * np.cos(y / 35.0) + rng.normal(0, 20, (192, 256))
    path = write_dng(folder / "private.dng", np.clip(64 + signal, 0, 4095).astype(np.uint16), private=True)
    data = path.read_bytes()
    assert all(s.encode() in data for s in PRIVATE_STRINGS.values())  # the test input does carry them
    return path


def _private_dicom(folder: Path, rng) -> Path:
    y, x = np.mgrid[0:192, 0:256]
    pixels = (2000 + 1000 * np.sin(x / 25.0) + rng.normal(0, 20, (192, 256))).astype(np.uint16)
    path = write_dicom(folder / "patient.dcm", pixels, photometric="MONOCHROME1", bits_stored=12, private=True)
    assert PRIVATE_STRINGS["serial"].encode() in path.read_bytes()
    return path


def assert_no_private_strings(out: Path) -> int:
    """Scan every output file (images and sidecars); return how many files were scanned."""
    files = [p for p in sorted(out.rglob("*")) if p.is_file()]
    for path in files:
        data = path.read_bytes().lower()
        for what, text in PRIVATE_STRINGS.items():
            for needle in {text, text.replace(" ", "^"), text.split()[-1] if " " in text else text}:
                assert needle.lower().encode() not in data, f"{path.name} carries the {what} ({needle!r})"
    for path in files:
        if path.suffix == ".tif":
            with tifffile.TiffFile(path) as tif:
                found = {_PERSONAL_TIFF_TAGS[t.code] for page in tif.pages for t in page.tags
                         if t.code in _PERSONAL_TIFF_TAGS}
            assert not found, f"{path.name} has tags {found}"
    return len(files)


def test_run_outputs_of_a_private_dng_carry_no_personal_metadata(tmp_path, rng, capsys):
    src = _private_dng(tmp_path, rng)
    out = tmp_path / "out"
    assert cli.main(["run", str(src), "-o", str(out), "--dicom"]) == 0, capsys.readouterr().err
    assert assert_no_private_strings(out) >= 6  # TIFF, PNG, DICOM and their sidecars
    (dcm,) = out.glob("*.dcm")
    ds = pydicom.dcmread(dcm)
    for keyword in ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "OperatorsName",
                    "DeviceSerialNumber", "InstitutionName", "InstitutionAddress"):
        assert str(ds.get(keyword, "") or "") == "", keyword


def test_dicom_patient_fields_come_only_from_the_user(tmp_path, rng, capsys):
    src = _private_dicom(tmp_path, rng)
    out = tmp_path / "out"
    code = cli.main(["run", str(src), "-o", str(out), "--dicom", "--patient-name", "Test^Given",
                     "--patient-id", "USER-42"])
    assert code == 0, capsys.readouterr().err
    assert_no_private_strings(out)  # nothing of the input DICOM's patient, operator or device
    (dcm,) = out.glob("*.dcm")
    ds = pydicom.dcmread(dcm)
    assert str(ds.PatientName) == "Test^Given" and ds.PatientID == "USER-42"
    assert str(ds.get("PatientBirthDate", "")) == "" and str(ds.get("PatientSex", "")) == ""


def test_denoise_output_of_a_private_dng_carries_no_personal_metadata(tmp_path, rng, capsys):
    src = _private_dng(tmp_path, rng)
    out = tmp_path / "out"
    out.mkdir()
    code = cli.main(["denoise", str(src), "-o", str(out / "clean.tif"), "--mask-out", str(out / "mask.tif")])
    assert code == 0, capsys.readouterr().err
    assert assert_no_private_strings(out) >= 2
