"""What an input image is: a camera frame (linear light) or a display radiograph.

The two kinds need different processing. A **camera frame** (camera raw, or a TIFF/PNG of
linear counts from a camera photographing the scintillator) is linear in light: more X-rays
give more light, so bone is dark; the pipeline takes the logarithm, finds the exposed screen
and turns it bone-white. A **display radiograph** (a CR/DX DICOM, or an exported radiograph)
is already log-scaled and bone-bright (after MONOCHROME1 inversion on reading); it needs only
the display stages: collimation, value-of-interest window, dynamic range and contrast. Sending
one through the other's path gives an inverted image or blanks anatomy.

:func:`decide_input_kind` is the one rule, used by ``dslrxr run``
(:func:`napari_dslrxr.core.files.run_file`), the napari reader (which stores the decision
in the layer's metadata) and the contrast widget:

1. camera raw (CR2, NEF, DNG...) is a camera frame, always;
2. a DICOM whose header says so decides: ``PixelIntensityRelationship = LIN`` is linear
   counts (camera path); a projection-radiography modality (CR, DX, MG, RG, IO, PX, RF, XA)
   with a MONOCHROME1/2 image is a display radiograph;
3. otherwise (TIFF, PNG, arrays, other DICOMs) the parameter ``[input] input_kind`` decides
   when it is ``"camera"`` or ``"display"``;
4. with ``"auto"``, evidence in the file: a TIFF written by this package (its description
   says what it holds: ``dslrxr run`` output is display-ready), a colour frame with a tint (a photograph of a scintillator), an 8-bit grey image (display
   encoded), else a 16-bit or float grey image is taken as linear counts. Only the first two
   are certain; the others are guesses, marked ``certain=False``, so callers say so. (A DICOM
   that reaches this step is guessed to be a display radiograph, as nearly all are.)
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..param_fields import check_value, validate_fields

CAMERA, DISPLAY, AUTO = "camera", "display", "auto"
INPUT_KINDS = (AUTO, CAMERA, DISPLAY)

#: DICOM modalities of projection radiographs (stored for display, bone bright).
DISPLAY_MODALITIES = frozenset({"CR", "DX", "MG", "RG", "IO", "PX", "RF", "XA"})
#: Mean channel difference (fraction of the mean level) above which a colour frame is tinted.
_TINT_FRACTION = 0.02


@dataclass
class InputParams:
    """What the input is (TOML section ``[input]``).

    Attributes
    ----------
    input_kind : str
        ``"auto"`` (decide from the file: DICOM header, camera raw, colour, bit depth),
        ``"camera"`` (linear counts from the camera: the full pipeline) or ``"display"``
        (a radiograph already in display form, bone bright: only the display stages). Camera
        raw files are always camera frames, and a CR/DX DICOM header decides for itself.
    """

    input_kind: str = field(default=AUTO, metadata={
        "help": "what TIFF/PNG inputs are: auto = decide from the file (and say when unsure); camera = "
                "linear counts from the camera; display = a radiograph in display form, bone bright "
                "(camera raw and CR/DX DICOM headers decide for themselves)",
        "choices": INPUT_KINDS})

    def __post_init__(self) -> None:
        validate_fields(self, "input")


@dataclass(frozen=True)
class InputKind:
    """The decision for one input.

    Attributes
    ----------
    kind : str
        ``"camera"`` or ``"display"``.
    certain : bool
        False when the kind is a guess (callers print one line and record it).
    evidence : str
        Why, in a few words (for the sidecar, the widget and the message).
    requested : str
        The ``input_kind`` parameter it was decided under.
    overridden : bool
        True when the file's own header decided against an explicit ``requested`` kind.
    """

    kind: str
    certain: bool
    evidence: str
    requested: str = AUTO
    overridden: bool = False

    def message(self) -> str | None:
        """One line for the user when the kind was guessed or the parameter was overruled."""
        if self.overridden:
            return (f"input kind {self.kind}, not the requested {self.requested}: {self.evidence}")
        if not self.certain:
            other = DISPLAY if self.kind == CAMERA else CAMERA
            return (f"input kind not certain, guessed {self.kind} ({self.evidence}); "
                    f"if wrong, set [input] input_kind = \"{other}\"")
        return None

    def as_record(self) -> dict:
        """Plain dict for a sidecar or a layer's metadata."""
        return {"kind": self.kind, "certain": self.certain, "evidence": self.evidence,
                "requested": self.requested, "overridden": self.overridden}

    @classmethod
    def from_record(cls, record: Mapping) -> InputKind:
        return cls(kind=str(record["kind"]), certain=bool(record.get("certain", False)),
                   evidence=str(record.get("evidence", "")), requested=str(record.get("requested", AUTO)),
                   overridden=bool(record.get("overridden", False)))


def _header_decision(file_format: str | None, metadata: Mapping) -> tuple[str, str] | None:
    """(kind, evidence) when the file format or header is decisive, else None."""
    if file_format == "raw":
        return CAMERA, "camera raw file (linear sensor counts)"
    if file_format == "dicom":
        relationship = str(metadata.get("pixel_intensity_relationship") or "").strip().upper()
        modality = str(metadata.get("modality") or "").strip().upper()
        photometric = str(metadata.get("photometric_original") or "").strip().upper()
        if relationship == "LIN":
            return CAMERA, f"DICOM {modality or 'image'} with PixelIntensityRelationship LIN (linear counts)"
        if modality in DISPLAY_MODALITIES and photometric in ("MONOCHROME1", "MONOCHROME2"):
            return DISPLAY, f"DICOM modality {modality}, {photometric}"
    return None


def _own_output(metadata: Mapping) -> str | None:
    """The kind a TIFF written by this package declares: ``dslrxr run`` output is display-ready;
    a layer saved from napari records ``input_kind``. None for any other file."""
    text = metadata.get("description")
    if not isinstance(text, str) or not text.lstrip().startswith("{"):
        return None
    try:
        record = json.loads(text)
    except (ValueError, RecursionError):
        return None
    if not isinstance(record, dict) or record.get("software") != "napari-dslrxr":
        return None
    if record.get("stage") == "run":
        return DISPLAY
    return record.get("input_kind") if record.get("input_kind") in (CAMERA, DISPLAY) else None


def _tint(data: np.ndarray) -> float:
    """Mean absolute channel difference relative to the mean level (0 for grey stored as RGB)."""
    step = max(1, int(np.sqrt(data.shape[0] * data.shape[1] / 250_000)))
    sub = np.asarray(data[::step, ::step], np.float32)
    level = float(np.mean(sub))
    if level <= 0:
        return 0.0
    spread = np.mean(np.abs(sub[..., 0] - sub[..., 1])) + np.mean(np.abs(sub[..., 1] - sub[..., 2]))
    return float(spread) / (2.0 * level)


def _evidence(file_format: str | None, metadata: Mapping, data: np.ndarray | None) -> tuple[str, bool, str]:
    """(kind, certain, evidence) from the content, for ``input_kind = "auto"``."""
    what = {"tiff": "TIFF", "png": "PNG", "dicom": "DICOM"}.get(file_format or "", "image")
    own = _own_output(metadata)
    if own is not None:
        return own, True, f"{what} written by napari-dslrxr as {'a display radiograph' if own == DISPLAY else 'linear counts'}"
    if file_format == "dicom":
        modality = str(metadata.get("modality") or "no modality").strip() or "no modality"
        return DISPLAY, False, f"DICOM ({modality}), no LIN header: display radiograph assumed"
    if data is None:
        return CAMERA, False, f"{what} with no pixel data to judge, linear counts assumed"
    arr = np.asarray(data)
    if arr.ndim == 3 and arr.shape[-1] == 3:
        tint = _tint(arr)
        if tint > _TINT_FRACTION:
            return CAMERA, True, f"colour {what} with a tint ({tint:.0%} channel difference): a camera frame"
        grey = "grey stored as colour"
    else:
        grey = "grey"
    if arr.dtype == np.uint8:
        return DISPLAY, False, f"8-bit {grey} {what}: display-encoded, not linear counts"
    depth = "16-bit" if arr.dtype == np.uint16 else f"{arr.dtype}"
    return CAMERA, False, f"{depth} {grey} {what}, no radiograph header: linear counts assumed"


def decide_input_kind(file_format: str | None = None, metadata: Mapping | None = None,
                      data: np.ndarray | None = None, requested: str = AUTO) -> InputKind:
    """Decide whether an input is a camera frame or a display radiograph.

    Parameters
    ----------
    file_format : str or None
        ``"raw"``, ``"dicom"``, ``"tiff"``, ``"png"`` (:attr:`~.images.LoadedImage.format`), or None
        for an array that did not come from a file.
    metadata : mapping, optional
        The reader's metadata (:attr:`~.images.LoadedImage.metadata`: DICOM ``modality``,
        ``photometric_original``, ``pixel_intensity_relationship``; TIFF ``description``).
    data : ndarray, optional
        The pixels (dtype and colour are evidence for ``"auto"``).
    requested : str
        The ``[input] input_kind`` parameter: ``"auto"``, ``"camera"`` or ``"display"``.

    Returns
    -------
    InputKind
    """
    requested = check_value(InputParams, "input", "input_kind", requested)
    metadata = metadata or {}
    decided = _header_decision(file_format, metadata)
    if decided is not None:
        kind, evidence = decided
        overridden = requested != AUTO and requested != kind
        return InputKind(kind, True, evidence, requested, overridden)
    if requested != AUTO:
        return InputKind(requested, True, "set by [input] input_kind", requested)
    kind, certain, evidence = _evidence(file_format, metadata, data)
    return InputKind(kind, certain, evidence, requested)


def input_kind_of(image, requested: str = AUTO) -> InputKind:
    """:func:`decide_input_kind` for a :class:`~.images.LoadedImage`."""
    return decide_input_kind(image.format, image.metadata, image.data, requested)
