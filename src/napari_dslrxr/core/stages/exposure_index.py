"""Exposure index and deviation index of a camera frame (IEC 62494-1).

The exposure index tells the radiographer how much X-ray exposure reached the detector behind
the anatomy, in units every DR console uses: EI = 100 x K_cal, where K_cal (µGy) is the air
kerma of the calibration beam (RQA5) that would give the same value of interest. The deviation
index DI = 10 log10(EI / EI_T) says how far an exposure is from the site's target EI_T (DI = +1
is about 26 % too much, -3 half).

The value of interest is the median of the linear signal (dark subtracted, flat fielded,
before the logarithm and any display mapping) over the relevant image region: by default the
exposed field (the screen, minus collimator bands) without the direct-exposure background,
see docs/algorithms/exposure_index.md, section 'Value of interest'. K_cal is that value
divided by the calibration (DN per µGy at RQA5), which this project's detector is linear in.

:func:`exposure_index_record` gives what the sidecar records (also when the detector is not
calibrated, with the reason); :func:`dicom_exposure_tags` the DICOM attributes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..param_fields import validate_fields

#: IEC 62494-1 scaling constant: EI per µGy of calibration air kerma.
EI_PER_UGY = 100.0

#: Relevant image regions the value of interest may come from (``[exposure] region``).
EXPOSURE_REGIONS = ("anatomy", "field", "centre")

#: Fewest samples the value of interest is taken from before the next wider region is used.
_MIN_SAMPLES = 64


@dataclass
class ExposureParams:
    """Exposure index calibration and target (TOML section ``[exposure]``).

    Attributes
    ----------
    calibration_dn_per_ugy : float
        Linear grey signal (sum of the colour channels after dark subtraction and flat field,
        in camera counts) per µGy of air kerma at the detector with the RQA5 beam; 0 = the
        detector is not calibrated (no EI is computed, the sidecar says so).
    target_ei : float
        Target exposure index EI_T of the deviation index (a site setting per examination).
    region : str
        Where the value of interest is taken: ``"anatomy"`` (the exposed field without the
        direct-exposure background, as IEC 62494-1 asks), ``"field"`` (the whole exposed field:
        a flat or phantom exposure), ``"centre"`` (the middle third of the field's extent).
    """

    calibration_dn_per_ugy: float = field(default=0.0, metadata={
        "help": "linear grey signal (counts, dark subtracted, flat fielded) per µGy at the detector "
                "with the RQA5 beam; 0 = not calibrated (no exposure index)",
        "unit": "counts/µGy", "min": 0.0, "max": 1e9})
    target_ei: float = field(default=250.0, metadata={
        "help": "target exposure index EI_T of the deviation index DI = 10 log10(EI / EI_T)",
        "unit": "EI (100 per µGy)", "min": 1.0, "max": 1e6})
    region: str = field(default="anatomy", metadata={
        "help": "value-of-interest region: anatomy (field without direct exposure), field (whole exposed "
                "field), centre (middle third of the field)", "choices": EXPOSURE_REGIONS})

    def __post_init__(self) -> None:
        validate_fields(self, "exposure")

    @property
    def calibrated(self) -> bool:
        return self.calibration_dn_per_ugy > 0


def _centre_of(mask: np.ndarray) -> np.ndarray:
    """``mask`` limited to the middle third of its bounding box (rows and columns)."""
    rows, cols = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    out = np.zeros_like(mask)
    dr, dc = (r1 - r0) // 3, (c1 - c0) // 3
    out[r0 + dr:r1 - dr, c0 + dc:c1 - dc] = True
    return out & mask


def value_of_interest(linear: np.ndarray, field_mask: np.ndarray | None, region: str = "anatomy") -> dict:
    """Median linear signal over the relevant region of a frame.

    Parameters
    ----------
    linear : ndarray, float, (H, W)
        Linear grey signal (counts, dark subtracted, flat fielded); a regular subsample is fine.
    field_mask : ndarray, bool, (H, W) or None
        The exposed field (screen minus collimator bands); None = the whole frame.
    region : str
        One of :data:`EXPOSURE_REGIONS`.

    Returns
    -------
    dict
        ``value_dn`` (the median), ``region`` (the region actually used: a narrower one with
        fewer than 64 samples falls back to the field, with ``region_note`` saying why) and
        ``region_fraction`` (its share of the frame).
    """
    from .region import direct_exposure_level

    linear = np.asarray(linear, np.float64)
    field = np.ones(linear.shape, bool) if field_mask is None or not field_mask.any() else field_mask
    chosen, used, note = field, region, None
    if region == "anatomy":
        # which pixels are direct exposure is decided on a 5 x 5 median: at a few hundred quanta per
        # pixel the photon noise of the object's dense parts smears the attenuation histogram and
        # hides the valley above the direct-exposure mode; a median (unlike a mean) keeps the
        # object's outline where it is. The value of interest is then taken unfiltered.
        smooth = cv2.medianBlur(np.ascontiguousarray(linear, np.float32), 5)
        positive = field & (smooth > 0)
        # attenuation (high = more attenuating), NaN where there is no signal: the direct-exposure
        # mode is the low end of the field's attenuation
        with np.errstate(divide="ignore", invalid="ignore"):
            attenuation = -np.log(np.where(smooth > 0, smooth, np.nan))
        level = direct_exposure_level(attenuation[positive]) if positive.sum() >= 16 else None
        if level is None:
            note = "no direct-exposure background found: the whole field is the anatomy"
        else:
            with np.errstate(invalid="ignore"):
                direct = attenuation < level  # NaN compares False: kept
            chosen = field & ~direct
    elif region == "centre":
        chosen = _centre_of(field)
    if np.count_nonzero(chosen) < _MIN_SAMPLES and chosen is not field:
        chosen, used = field, "field"
        note = f"the {region} region has fewer than {_MIN_SAMPLES} samples: the whole field is used"
    out = {"value_dn": float(np.median(linear[chosen])), "region": used,
           "region_fraction": round(float(chosen.mean()), 5)}
    if note:
        out["region_note"] = note
    return out


def exposure_index_record(linear: np.ndarray, field_mask: np.ndarray | None, params: ExposureParams) -> dict:
    """What a run records about its exposure: EI, EI_T and DI when calibrated, else why not.

    Parameters
    ----------
    linear, field_mask
        As :func:`value_of_interest`.
    params : ExposureParams

    Returns
    -------
    dict
        ``computed`` (bool); when true ``exposure_index``, ``target_exposure_index``,
        ``deviation_index``, ``k_cal_ugy`` and the calibration; always the value of interest
        (``value_of_interest_dn``: with a known air kerma it gives the calibration) and, when
        false, ``reason``.
    """
    voi = value_of_interest(linear, field_mask, params.region)
    record = {"standard": "IEC 62494-1", "statistic": "median of the linear signal",
              "value_of_interest_dn": round(voi["value_dn"], 4),
              **{k: v for k, v in voi.items() if k != "value_dn"}}
    if not params.calibrated:
        return {"computed": False, **record,
                "reason": "detector not calibrated: set [exposure] calibration_dn_per_ugy (counts per µGy at RQA5)"}
    if not voi["value_dn"] > 0:
        return {"computed": False, **record, "reason": "no signal above the dark level in the region"}
    k_cal_ugy = voi["value_dn"] / params.calibration_dn_per_ugy
    ei = EI_PER_UGY * k_cal_ugy
    return {"computed": True, **record, "exposure_index": round(ei, 2), "target_exposure_index": params.target_ei,
            "deviation_index": round(10.0 * math.log10(ei / params.target_ei), 3),
            "k_cal_ugy": round(k_cal_ugy, 5), "calibration_dn_per_ugy": params.calibration_dn_per_ugy,
            "calibration_beam": "RQA5"}


def not_linear_record(reason: str) -> dict:
    """The record of an input that has no linear calibration (a display radiograph)."""
    return {"computed": False, "standard": "IEC 62494-1", "reason": reason}


def _ds(value: float, decimals: int) -> str:
    """A DICOM decimal string (at most 16 characters)."""
    text = f"{value:.{decimals}f}"
    return text if len(text) <= 16 else f"{value:.6g}"


def dicom_exposure_tags(record: dict | None) -> dict[str, str]:
    """DICOM attributes (keyword -> decimal string) of an exposure record; empty when not computed.

    ExposureIndex (0018,1411), TargetExposureIndex (0018,1412) and DeviationIndex (0018,1413),
    all VR DS.
    """
    if not record or not record.get("computed"):
        return {}
    return {"ExposureIndex": _ds(record["exposure_index"], 1),
            "TargetExposureIndex": _ds(record["target_exposure_index"], 1),
            "DeviationIndex": _ds(record["deviation_index"], 2)}
