"""Parameters of ``dslrxr qc`` (TOML section ``[qc]``) and the beam-quality table.

The section is the single source of defaults, ranges, units and help for the command-line
options and the QC widget (see :mod:`..param_fields`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..errors import ParameterError
from ..param_fields import validate_fields

#: Squared signal-to-noise ratio per unit air kerma, SNR²_in / K, in photons per mm² per µGy,
#: of the IEC 62220-1-1:2015 standard beam qualities (its Table 2). The 2003 edition
#: (IEC 62220-1) gave 21 759 for RQA3; the 2015 edition changed the RQA3 spectrum's value to
#: 20 673 and kept the others. We follow the 2015 edition throughout (docs/algorithms/qc.md).
SNR2_IN_PER_UGY: dict[str, float] = {
    "RQA3": 20673.0,
    "RQA5": 29653.0,
    "RQA7": 32490.0,
    "RQA9": 31007.0,
}

#: Edge angles (degrees from the pixel axis) the standard asks for; outside them we warn.
EDGE_ANGLE_RANGE_DEG = (1.5, 3.0)


@dataclass
class QcParams:
    """Detector-quality measurement settings (TOML section ``[qc]``), checked on construction.

    Attributes
    ----------
    beam : str
        Radiation quality (IEC 61267): sets q per µGy of air kerma.
    pixel_pitch_mm : float
        Pixel pitch at the detector; 0 = not set (the command then requires
        ``--pixel-pitch-mm``).
    air_kerma_ugy : float
        Air kerma at the detector surface of the flats and the edge; 0 = not set.
    roi_size_px : int
        Side of the square NNPS regions (IEC: 256).
    nnps_area_fraction : float
        Side of the central analysis area of each flat, as a fraction of the frame's shorter
        side.
    nnps_cut_half_width : int
        Rows (columns) on each side of the frequency axis averaged into the 1-D NNPS; the axis
        itself is excluded (IEC: 7).
    frequency_bin : int
        Width of the output frequency bins, in native NNPS frequency samples 1/(roi_size·p).
    edge_oversampling : int
        ESF bins per pixel pitch (IEC/ISO: 4).
    lsf_half_width_px : int
        Half width of the line-spread function window, in pixels.
    outlier_sigma : float
        Pixels beyond this many robust standard deviations of their neighbourhood (spots, dust)
        are left out of the edge and NNPS estimates; 0 keeps every pixel.
    flat_field_edge : bool
        Divide the dark-subtracted edge image by the mean dark-subtracted flat (pixel gain).
    linearity_tolerance_percent : float
        Largest allowed deviation of mean signal / air kerma from the fitted conversion
        function; beyond it the input is refused as not linear.
    raw_plane : str
        For camera raw input: the linear CFA plane analysed (its pixel pitch is twice the
        sensor's; give the sensor pitch, the command doubles it).
    """

    beam: str = field(default="RQA5", metadata={
        "help": "radiation quality (IEC 61267); sets the photon fluence per uGy",
        "choices": tuple(SNR2_IN_PER_UGY)})
    pixel_pitch_mm: float = field(default=0.0, metadata={
        "help": "pixel pitch at the detector; 0 = not set", "unit": "mm", "min": 0.0, "max": 10.0})
    air_kerma_ugy: float = field(default=0.0, metadata={
        "help": "air kerma at the detector for the flats and the edge; 0 = not set",
        "unit": "uGy", "min": 0.0, "max": 1e5})
    roi_size_px: int = field(default=256, metadata={
        "help": "side of the square NNPS regions (IEC 62220-1-1: 256)", "unit": "px", "min": 32, "max": 2048,
        "choices": (32, 64, 128, 256, 512, 1024, 2048)})
    nnps_area_fraction: float = field(default=0.9, metadata={
        "help": "side of the central NNPS analysis area as a fraction of the frame's shorter side",
        "min": 0.2, "max": 1.0})
    nnps_cut_half_width: int = field(default=7, metadata={
        "help": "rows/columns each side of the frequency axis averaged into the 1-D NNPS (axis excluded)",
        "unit": "px", "min": 1, "max": 64})
    frequency_bin: int = field(default=4, metadata={
        "help": "output frequency step, in native NNPS frequency samples 1/(roi_size x pitch)",
        "min": 1, "max": 32})
    edge_oversampling: int = field(default=4, metadata={
        "help": "edge-spread-function bins per pixel pitch", "min": 2, "max": 16})
    lsf_half_width_px: int = field(default=64, metadata={
        "help": "half width of the line-spread-function window", "unit": "px", "min": 4, "max": 1024})
    outlier_sigma: float = field(default=6.0, metadata={
        "help": "leave out pixels beyond this many robust sigmas of their neighbourhood (spots); 0 keeps all",
        "unit": "sigma", "min": 0.0, "max": 100.0})
    flat_field_edge: bool = field(default=True, metadata={
        "help": "divide the dark-subtracted edge by the mean dark-subtracted flat (pixel gain)"})
    linearity_tolerance_percent: float = field(default=5.0, metadata={
        "help": "largest deviation of signal / air kerma from the conversion function before the input is refused",
        "unit": "%", "min": 0.1, "max": 100.0})
    raw_plane: str = field(default="G1", metadata={
        "help": "camera raw input: the linear CFA plane analysed (pitch = 2 x sensor pitch)",
        "choices": ("R", "G1", "G2", "B")})

    def __post_init__(self) -> None:
        validate_fields(self, "qc")
        if self.nnps_cut_half_width >= self.roi_size_px // 2:
            raise ParameterError(f"qc.nnps_cut_half_width: {self.nnps_cut_half_width} must be below half "
                                 f"of qc.roi_size_px ({self.roi_size_px})")
