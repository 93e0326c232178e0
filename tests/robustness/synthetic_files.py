"""Small synthetic files for the I/O and robustness tests: DNG (pidng), DICOM (pydicom), TIFF, PNG.

Every maker writes into a folder the test owns (``tmp_path``) and returns the path; sizes are
tiny so hundreds of files can be fuzzed within the CI budget.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: Bayer cells as pidng's CFAPattern codes (0 red, 1 green, 2 blue), row-major over the 2x2 cell.
CFA_CODES = {"RGGB": [0, 1, 1, 2], "GRBG": [1, 0, 2, 1], "GBRG": [1, 2, 0, 1], "BGGR": [2, 1, 1, 0]}

#: Personal metadata written into the "private" DNG; outputs must never contain these strings.
PRIVATE_STRINGS = {
    "serial": "SN-8675309-PRIVATE",
    "owner": "Jane Q. Private-Owner",
    "gps": "51.5007N-0.1246W-GPSPRIVATE",
}


def write_dng(path: Path, mosaic: np.ndarray, *, pattern: str = "RGGB", black_counts: int = 64,
              white_counts: int = 4095, bits: int = 16, neutral=(1.0, 1.0, 1.0),
              private: bool = False, declared_size: tuple[int, int] | None = None) -> Path:
    """Write a Bayer mosaic (uint16 counts) as an uncompressed DNG.

    ``private`` adds a camera serial number, an owner name (Artist, CameraOwnerName) and a
    GPS position (in XMP) from :data:`PRIVATE_STRINGS`. ``declared_size`` (height, width)
    overrides the size written in the header without changing the pixel data (for tests
    of the size limit).
    """
    from pidng.core import RAW2DNG
    from pidng.defs import CalibrationIlluminant, DNGVersion, Orientation, PhotometricInterpretation
    from pidng.dng import DNGTags, Tag, Type

    height, width = mosaic.shape if declared_size is None else declared_size
    tags = DNGTags()
    ratio = [[int(round(v * 1000)), 1000] for v in neutral]
    for key, value in [
        (Tag.ImageWidth, width), (Tag.ImageLength, height),
        (Tag.TileWidth, mosaic.shape[1]), (Tag.TileLength, mosaic.shape[0]),
        (Tag.Orientation, Orientation.Horizontal),
        (Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array),
        (Tag.SamplesPerPixel, 1), (Tag.BitsPerSample, bits), (Tag.CFARepeatPatternDim, [2, 2]),
        (Tag.CFAPattern, CFA_CODES[pattern]), (Tag.BlackLevel, [black_counts]),
        (Tag.WhiteLevel, [white_counts]),
        (Tag.ColorMatrix1, [[1, 1], [0, 1], [0, 1], [0, 1], [1, 1], [0, 1], [0, 1], [0, 1], [1, 1]]),
        (Tag.CalibrationIlluminant1, CalibrationIlluminant.D65), (Tag.AsShotNeutral, ratio),
        (Tag.Make, "Canon"), (Tag.Model, "EOS 350D DIGITAL"),
        (Tag.DNGVersion, DNGVersion.V1_4), (Tag.DNGBackwardVersion, DNGVersion.V1_2),
    ]:
        tags.set(key, value)
    if private:
        xmp = ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/'
               '22-rdf-syntax-ns#"><rdf:Description xmlns:exif="http://ns.adobe.com/exif/1.0/" '
               f'exif:GPSLatitude="{PRIVATE_STRINGS["gps"]}"/></rdf:RDF></x:xmpmeta>')
        tags.set(Tag.CameraSerialNumber, PRIVATE_STRINGS["serial"])
        tags.set(Tag.EXIFPhotoBodySerialNumber, PRIVATE_STRINGS["serial"])
        tags.set(Tag.Artist, PRIVATE_STRINGS["owner"])
        tags.set((42032, Type.Ascii), PRIVATE_STRINGS["owner"])  # CameraOwnerName
        tags.set(Tag.XMP_Metadata, list(xmp.encode("ascii")))
    writer = RAW2DNG()
    writer.options(tags, path="", compress=False)
    written = writer.convert(np.ascontiguousarray(mosaic, dtype=np.uint16), filename=str(Path(path).with_suffix("")))
    if Path(written) != Path(path):
        Path(written).rename(path)
    return Path(path)


def write_dicom(path: Path, pixels: np.ndarray, *, photometric: str = "MONOCHROME1",
                bits_stored: int = 12, rows_cols: tuple[int, int] | None = None,
                pixel_spacing_mm: float | tuple[float, float] | None = 0.1, private: bool = False) -> Path:
    """Write a minimal single-frame CR DICOM (explicit VR little endian) of uint16 pixels.

    ``pixel_spacing_mm`` is one value or (row, column) spacing in mm, None for none;
    ``rows_cols`` overrides the Rows/Columns written in the header (for size-limit tests);
    ``private`` fills patient, operator and device-serial fields from :data:`PRIVATE_STRINGS`.
    """
    import pydicom
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.1"  # CR image storage
    meta.MediaStorageSOPInstanceUID = generate_uid(entropy_srcs=[str(path)])
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = FileDataset(str(path), {}, file_meta=meta, preamble=b"\0" * 128)
    ds.SOPClassUID = meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = "CR"
    rows, cols = pixels.shape[:2] if rows_cols is None else rows_cols
    ds.Rows, ds.Columns = rows, cols
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = photometric
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, bits_stored, bits_stored - 1
    ds.PixelRepresentation = 0
    if pixel_spacing_mm is not None:
        ds.ImagerPixelSpacing = list(np.broadcast_to(np.asarray(pixel_spacing_mm, float), 2))
    if private:
        ds.PatientName = PRIVATE_STRINGS["owner"].replace(" ", "^")
        ds.PatientID = PRIVATE_STRINGS["serial"]
        ds.OperatorsName = PRIVATE_STRINGS["owner"]
        ds.DeviceSerialNumber = PRIVATE_STRINGS["serial"]
        ds.InstitutionAddress = PRIVATE_STRINGS["gps"]
    ds.PixelData = np.ascontiguousarray(pixels, dtype="<u2").tobytes()
    pydicom.dcmwrite(path, ds, enforce_file_format=True)
    return Path(path)
