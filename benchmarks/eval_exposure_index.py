"""Exposure index (IEC 62494-1) against air kerma, on frames the project's phantom did not make.

The generators of ``tests/_cli/test_cli_exposure_index.py`` (an analytic soft-tissue ellipse with a
bone rod in an open beam; the NEMA lower-leg CR in ``$DSLRXR_DATA/cr_dicom`` as a transmission map
with vignetting and a flat), Poisson quanta (300 per pixel per µGy) at two camera gains, air
kerma 0.5 to 8 µGy. Each frame goes through the pipeline (dark, flat field, region) with the
generator's calibration; EI is compared with the baseline 100 x K x the median transmission of
the object (analytic: its exact mask; leg: its shaft, a hand-picked band of columns).

Writes ``results/eval_exposure_index.json`` and ``docs/exposure_index_linearity.png``.
Run: ``python benchmarks/eval_exposure_index.py``.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import load_test_module, record  # noqa: E402

from napari_dslrxr.core.params import PipelineParams  # noqa: E402
from napari_dslrxr.core.pipeline import process_frame  # noqa: E402
from napari_dslrxr.core.stages.exposure_index import ExposureParams  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("DSLRXR_DATA", REPO.parent / "shared" / "data"))
KERMAS_UGY = (0.5, 1.0, 2.0, 4.0, 8.0)
GAINS = (1.5, 4.0)


def main() -> None:
    gen = load_test_module("tests/_cli/test_cli_exposure_index.py", "exposure_index_generators")
    rng = np.random.default_rng(7)
    cases = {}
    analytic, inside = gen.analytic_object()
    cases["analytic object"] = (analytic, 1.0, float(np.median(analytic[inside])))
    if (DATA / "cr_dicom" / "RG3_UNCR.dcm").is_file():
        leg = gen.leg_transmission_map(DATA)
        vignetting = gen.vignetting_of(leg.shape)
        cases["NEMA leg (RG3) as transmission"] = (leg, vignetting, gen.leg_shaft_median(leg) * float(vignetting.mean()))
    results = {}
    for name, (transmission, illumination, t_ref) in cases.items():
        for gain in GAINS:
            params = PipelineParams(exposure=ExposureParams(calibration_dn_per_ugy=gen.QUANTA_PER_UGY * gain))
            dark = gen.dark_frame(transmission.shape, rng)
            flats = [] if np.isscalar(illumination) else [
                gen.expose(np.broadcast_to(illumination, transmission.shape), 20.0, gain, rng)]
            rows = []
            for k in KERMAS_UGY:
                frame = gen.expose(transmission * illumination, k, gain, rng)
                rec = process_frame(frame, params=params, darks=[dark], flats=flats).results["exposure_index"]
                rows.append({"air_kerma_ugy": k, "exposure_index": rec["exposure_index"],
                             "baseline_100_k_t": round(100 * k * t_ref, 2),
                             "ratio_to_baseline": round(rec["exposure_index"] / (100 * k * t_ref), 4),
                             "region_fraction": rec["region_fraction"]})
            slope = np.polyfit(np.log([r["air_kerma_ugy"] for r in rows]),
                               np.log([r["exposure_index"] for r in rows]), 1)[0]
            results[f"{name}, {gain:g} counts/quantum"] = {"rows": rows, "log_log_slope": round(float(slope), 4)}
    record("eval_exposure_index", {"quanta_per_ugy": gen.QUANTA_PER_UGY, "cases": results})
    _figure(results, REPO / "docs" / "exposure_index_linearity.png")


def _figure(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4.2))
    for (name, res), marker in zip(results.items(), "osD^", strict=False):
        k = [r["air_kerma_ugy"] for r in res["rows"]]
        ax.loglog(k, [r["exposure_index"] for r in res["rows"]], marker, alpha=0.8, fillstyle="none")
        ax.loglog(k, [r["baseline_100_k_t"] for r in res["rows"]], "k:", lw=0.8)
        bx.semilogx(k, [r["ratio_to_baseline"] for r in res["rows"]], marker + "-", fillstyle="none",
                    label=f"{name} (log-log slope {res['log_log_slope']:.3f})")
    ax.set_xlabel("air kerma at the detector, µGy")
    ax.set_ylabel("exposure index (pipeline)")
    ax.set_title("EI vs air kerma; dotted: 100 x K x median T")
    bx.legend(fontsize=7, loc="upper right")
    for axis in (ax, bx):
        axis.set_xticks(KERMAS_UGY, [f"{k:g}" for k in KERMAS_UGY])
        axis.minorticks_off()
    bx.axhline(1.0, color="k", lw=0.8)
    bx.set_ylim(0.85, 1.15)
    bx.set_xlabel("air kerma at the detector, µGy")
    bx.set_ylabel("EI / (100 x K x median T)")
    bx.set_title("EI relative to the baseline")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


if __name__ == "__main__":
    main()
