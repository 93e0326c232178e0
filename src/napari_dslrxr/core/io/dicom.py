"""DICOM Digital X-Ray (DX) output: a display-ready radiograph that PACS and viewers accept.

The file is a DX Image, SOP class *Digital X-Ray Image Storage - For Presentation*
(1.2.840.10008.5.1.4.1.1.1.1), MONOCHROME2, 16 bits, explicit VR little endian. UIDs are
derived from a caller-supplied seed (the input checksums and parameters), so a rerun writes
the same bytes. No camera serial number, owner, date or other personal metadata is written;
patient fields come only from what the user supplies (empty otherwise, as DICOM type 2
allows).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from ..errors import OutputError

DX_FOR_PRESENTATION = "1.2.840.10008.5.1.4.1.1.1.1"

#: Patient/study fields a user may supply (anything else is refused).
ALLOWED_PATIENT_FIELDS = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyID",
                          "AccessionNumber", "StudyDescription", "BodyPartExamined", "ViewPosition")


def deterministic_uid(seed: str, role: str) -> str:
    """A ``2.25.<int>`` UID derived from ``seed`` and ``role`` (same inputs -> same UID).

    The integer is the first 128 bits of SHA-256(seed, role): the UUID-derived form of
    PS3.5 B.2 (at most 44 characters), without randomness.
    """
    import hashlib

    digest = hashlib.sha256(f"{seed}|{role}".encode()).hexdigest()
    return f"2.25.{int(digest[:32], 16)}"


def write_dicom_dx(path: str | os.PathLike, image: np.ndarray, *, uid_seed: str,
                   pixel_spacing_mm: float | tuple[float, float] | None = None,
                   window: tuple[float, float] | None = None, patient: Mapping[str, str] | None = None,
                   series_description: str = "", inputs: Iterable[str | os.PathLike] = (),
                   linear: bool = False, attributes: Mapping[str, str] | None = None) -> Path:
    """Write a uint16 grey radiograph as a DICOM DX (For Presentation) file.

    Parameters
    ----------
    path : path-like
        Output file (written atomically; never an input).
    image : ndarray, uint16, (H, W)
        Display-ready values (MONOCHROME2: higher = brighter).
    uid_seed : str
        Seed of the Study, Series and SOP Instance UIDs (e.g. input checksums + parameters).
    pixel_spacing_mm : float or (row, col), optional
        Pixel pitch at the detector (mm); written as ImagerPixelSpacing and PixelSpacing.
    window : (centre, width), optional
        VOI window; default the full 16-bit range.
    patient : mapping, optional
        User-supplied fields from :data:`ALLOWED_PATIENT_FIELDS`.
    series_description : str
    inputs : iterable of path-like
        Files the output must not overwrite.
    linear : bool
        The values are linear in light (camera counts): PixelIntensityRelationship ``LIN``
        instead of ``LOG``, so a reader takes the file for a camera frame, not a display
        radiograph.
    attributes : mapping, optional
        Further attributes by keyword (e.g. ``ExposureIndex``), as their DICOM strings.

    Returns
    -------
    Path

    Raises
    ------
    OutputError
        Wrong image dtype/shape or an unknown patient field.
    """
    from .writers import atomic_write

    arr = np.ascontiguousarray(image)
    if arr.dtype != np.uint16 or arr.ndim != 2:
        raise OutputError(f"{path}: DICOM DX needs a 2-D uint16 image, got {arr.dtype} {arr.shape}")
    patient = dict(patient or {})
    unknown = sorted(set(patient) - set(ALLOWED_PATIENT_FIELDS))
    if unknown:
        raise OutputError(f"{path}: unknown patient field(s) {', '.join(unknown)} "
                          f"(allowed: {', '.join(ALLOWED_PATIENT_FIELDS)})")
    ds = _dx_identity(uid_seed)
    _set_patient_and_study(ds, patient, series_description)
    _set_image(ds, arr, window=window, pixel_spacing_mm=pixel_spacing_mm, linear=linear)
    for keyword, value in (attributes or {}).items():  # pydicom writes elements in tag order
        setattr(ds, keyword, value)

    def _write(tmp: str) -> None:
        ds.save_as(tmp, enforce_file_format=True)

    return atomic_write(Path(path), _write, inputs=inputs)


def _dx_identity(uid_seed: str):
    """A DX For Presentation dataset with its file meta and UIDs, all derived from ``uid_seed``."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, PYDICOM_IMPLEMENTATION_UID

    sop_uid = deterministic_uid(uid_seed, "sop")
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = DX_FOR_PRESENTATION
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = DX_FOR_PRESENTATION
    ds.SOPInstanceUID = sop_uid
    ds.StudyInstanceUID = deterministic_uid(uid_seed, "study")
    ds.SeriesInstanceUID = deterministic_uid(uid_seed, "series")
    ds.FrameOfReferenceUID = deterministic_uid(uid_seed, "frame")
    ds.Modality = "DX"
    ds.ImageType = ["DERIVED", "PRIMARY"]
    ds.PresentationIntentType = "FOR PRESENTATION"
    return ds


def _set_patient_and_study(ds, patient: dict, series_description: str) -> None:
    """Patient, study and series attributes: type 2 ones present, empty unless the user supplied
    them (no dates or times: the file is reproducible)."""
    ds.PatientName = patient.get("PatientName", "")
    ds.PatientID = patient.get("PatientID", "")
    ds.PatientBirthDate = patient.get("PatientBirthDate", "")
    ds.PatientSex = patient.get("PatientSex", "")
    ds.StudyDate = ""
    ds.StudyTime = ""
    ds.ContentDate = ""
    ds.ContentTime = ""
    ds.ReferringPhysicianName = ""
    ds.StudyID = patient.get("StudyID", "")
    ds.AccessionNumber = patient.get("AccessionNumber", "")
    if "StudyDescription" in patient:
        ds.StudyDescription = patient["StudyDescription"]
    ds.BodyPartExamined = patient.get("BodyPartExamined", "")
    ds.ViewPosition = patient.get("ViewPosition", "")
    ds.SeriesNumber = 1
    ds.InstanceNumber = 1
    ds.PatientOrientation = ""
    ds.Manufacturer = "napari-dslrxr"
    ds.SeriesDescription = series_description
    ds.DetectorType = "SCINTILLATOR"
    ds.BurnedInAnnotation = "NO"
    ds.LossyImageCompression = "00"


def _set_image(ds, arr: np.ndarray, *, window: tuple[float, float] | None,
               pixel_spacing_mm: float | tuple[float, float] | None, linear: bool) -> None:
    """The image module: 16-bit MONOCHROME2 pixels, intensity relationship, VOI window, spacing."""
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = int(arr.shape[0]), int(arr.shape[1])
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0
    ds.PixelIntensityRelationship = "LIN" if linear else "LOG"
    ds.PixelIntensityRelationshipSign = 1
    ds.RescaleIntercept = 0
    ds.RescaleSlope = 1
    ds.RescaleType = "US"
    centre, width = window if window is not None else (32768.0, 65536.0)
    ds.WindowCenter = f"{centre:g}"
    ds.WindowWidth = f"{width:g}"
    if pixel_spacing_mm:
        sp = (pixel_spacing_mm, pixel_spacing_mm) if np.isscalar(pixel_spacing_mm) else pixel_spacing_mm
        spacing = [f"{float(sp[0]):.6g}", f"{float(sp[1]):.6g}"]
        ds.ImagerPixelSpacing = spacing
        ds.PixelSpacing = spacing
    ds.PixelData = arr.astype("<u2").tobytes()
