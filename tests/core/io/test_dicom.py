"""DICOM DX output: tags, pixel round trip, deterministic UIDs, no unsupplied personal data."""

import numpy as np
import pydicom
import pytest

from napari_dslrxr.core.io.dicom import DX_FOR_PRESENTATION, write_dicom_dx
from napari_dslrxr.core.errors import OutputError


def test_dx_reads_back_with_right_tags_and_pixels(tmp_path, rng):
    image = rng.integers(0, 65536, (40, 56), dtype=np.uint16)
    path = write_dicom_dx(tmp_path / "x.dcm", image, uid_seed="abc", pixel_spacing_mm=0.15,
                          patient={"PatientName": "Doe^Jane", "PatientID": "P1"})
    ds = pydicom.dcmread(path)
    assert ds.Modality == "DX" and ds.PhotometricInterpretation == "MONOCHROME2"
    assert ds.SOPClassUID == DX_FOR_PRESENTATION == ds.file_meta.MediaStorageSOPClassUID
    assert ds.PresentationIntentType == "FOR PRESENTATION"
    assert [float(v) for v in ds.ImagerPixelSpacing] == [0.15, 0.15] == [float(v) for v in ds.PixelSpacing]
    assert float(ds.WindowCenter) == 32768 and float(ds.WindowWidth) == 65536
    assert ds.BitsStored == 16 and ds.PixelRepresentation == 0
    assert str(ds.PatientName) == "Doe^Jane" and ds.PatientID == "P1"
    assert np.array_equal(ds.pixel_array, image)
    for uid in (ds.SOPInstanceUID, ds.StudyInstanceUID, ds.SeriesInstanceUID):
        assert uid.startswith("2.25.") and len(uid) <= 64
    assert len({ds.SOPInstanceUID, ds.StudyInstanceUID, ds.SeriesInstanceUID}) == 3
    assert "DeviceSerialNumber" not in ds and "StudyDate" in ds and ds.StudyDate == ""


def test_same_seed_same_bytes_other_seed_other_uids(tmp_path):
    image = np.arange(64 * 64, dtype=np.uint16).reshape(64, 64)
    a = write_dicom_dx(tmp_path / "a.dcm", image, uid_seed="s1")
    b = write_dicom_dx(tmp_path / "b.dcm", image, uid_seed="s1")
    c = write_dicom_dx(tmp_path / "c.dcm", image, uid_seed="s2")
    assert a.read_bytes() == b.read_bytes()
    assert pydicom.dcmread(c).SOPInstanceUID != pydicom.dcmread(a).SOPInstanceUID
    ds = pydicom.dcmread(a)
    assert str(ds.PatientName) == "" and "PixelSpacing" not in ds


def test_bad_inputs_refused(tmp_path):
    with pytest.raises(OutputError, match="uint16"):
        write_dicom_dx(tmp_path / "x.dcm", np.zeros((8, 8), np.float32), uid_seed="s")
    with pytest.raises(OutputError, match="unknown patient field"):
        write_dicom_dx(tmp_path / "x.dcm", np.zeros((8, 8), np.uint16), uid_seed="s", patient={"Address": "x"})
