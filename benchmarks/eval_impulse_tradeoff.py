"""Trade-off of the impulse detector's sensitivity knobs on the independent pulse generator.

Issue 13 asks for recall >= 0.90 at precision >= 0.95 *and* at most 0.1 % PE on clean pixels
(pixels 2 px or more from any pulse). This script sweeps the five settings that trade
between them, all at once, and reports every combination and the Pareto front (highest
recall for a given PE), so that the targets can be judged against what the detector can do:

* ``posterior_threshold`` and ``neighbour_prior`` (:class:`ImpulseParams`): the test of
  every pixel and of the growth's rings;
* ``min_contrast`` (:class:`ImpulseParams`): Weber's contrast rule;
* ``_FOOTPRINT_SIGMAS`` and ``_STRONG_RIM_PRIOR`` (module constants of
  ``core/stages/impulse/detection.py``, set here for the sweep only): the integrated-excess
  seeds' threshold and the prior of strong seeds' first ring.

Scores are those of ``eval_impulse_independent.py --set pulses`` (the same frames: tinted,
grey RGB and grey, 600 pulses each), averaged over the frames. Results:
``benchmarks/results/impulse_tradeoff_<seeds>.json`` and, with ``--figure``, the plot
``docs/impulse_tradeoff.png`` (recall against PE on clean pixels, the target region shaded).

Run: ``.venv/bin/python benchmarks/eval_impulse_tradeoff.py --seeds dev [--figure]``
(about 3.5 s per combination and seed pair on one core; 144 combinations).
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import ROOT, record  # noqa: E402
from eval_impulse_independent import (KINDS, SEEDS, TARGET_PE_CLEAN_PCT, TARGET_PRECISION,  # noqa: E402
                                      TARGET_RECALL, pulse_frame, score_pulses)

GRID = {
    "footprint_sigmas": [4.0, 4.5, 5.0, 5.5],
    "min_contrast": [0.0, 0.07],
    "neighbour_prior": [0.5, 0.75, 0.9],
    "strong_rim_prior": [0.75, 0.9],
    "posterior_threshold": [0.3, 0.5, 0.8],
}
#: The shipped settings (the sweep must reproduce eval_impulse_independent's "ours" row).
DEFAULT = {"footprint_sigmas": 5.0, "min_contrast": 0.07, "neighbour_prior": 0.5,
           "strong_rim_prior": 0.75, "posterior_threshold": 0.5}
TARGET = {"recall": TARGET_RECALL, "precision": TARGET_PRECISION, "pe_clean_pct": TARGET_PE_CLEAN_PCT}


def score(frames, setting: dict) -> dict:
    from napari_dslrxr.core.stages.impulse import ImpulseParams, detection, remove_impulses

    saved = detection._FOOTPRINT_SIGMAS, detection._STRONG_RIM_PRIOR
    detection._FOOTPRINT_SIGMAS = setting["footprint_sigmas"]
    detection._STRONG_RIM_PRIOR = setting["strong_rim_prior"]
    try:
        params = ImpulseParams(min_contrast=setting["min_contrast"], neighbour_prior=setting["neighbour_prior"],
                               posterior_threshold=setting["posterior_threshold"])
        rows = []
        for frame in frames:
            res = remove_impulses(frame.dirty, params)
            rows.append(score_pulses(frame, res.image, res.any_mask(), detector=True))
    finally:
        detection._FOOTPRINT_SIGMAS, detection._STRONG_RIM_PRIOR = saved
    pe = [r["pe_clean_pct"] for r in rows]
    return {**setting,
            "recall": round(float(np.mean([r["recall_all"] for r in rows])), 4),
            "precision": round(float(np.mean([r["precision"] for r in rows])), 4),
            "residual_energy": round(float(np.mean([r["residual_energy_all"] for r in rows])), 4),
            "pe_clean_pct": round(float(np.mean(pe)), 4), "pe_clean_max_frame_pct": round(float(np.max(pe)), 4)}


def pareto(rows: list[dict]) -> list[dict]:
    """Rows not beaten on both recall (higher) and PE on clean pixels (lower), by PE."""
    front, best = [], -1.0
    for row in sorted(rows, key=lambda r: (r["pe_clean_pct"], -r["recall"])):
        if row["recall"] > best:
            front.append(row)
            best = row["recall"]
    return front


def figure(rows: list[dict], label: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5.2))
    pe = np.array([r["pe_clean_pct"] for r in rows])
    rec = np.array([r["recall"] for r in rows])
    prec = np.array([r["precision"] for r in rows])
    ax.add_patch(plt.Rectangle((0, TARGET["recall"]), TARGET["pe_clean_pct"], 1 - TARGET["recall"],
                               color="tab:green", alpha=0.15, label="issue 13's targets (recall, PE)"))
    sc = ax.scatter(pe, rec, c=prec, cmap="viridis", s=18, vmin=min(0.93, prec.min()), vmax=1.0)
    front = pareto(rows)
    ax.plot([r["pe_clean_pct"] for r in front], [r["recall"] for r in front], "k-", lw=1, label="Pareto front")
    d = next(r for r in rows if all(r[k] == v for k, v in DEFAULT.items()))
    ax.plot(d["pe_clean_pct"], d["recall"], "r*", ms=14, label="shipped settings")
    ax.set_xlabel("PE on clean pixels, % (mean over the frames)")
    ax.set_ylabel("recall on pulse pixels of at least 3 sigma")
    ax.set_xlim(0, min(max(pe) * 1.05, 0.6))
    ax.set_ylim(min(rec.min(), 0.8) - 0.01, 0.95)
    ax.set_title(f"Impulse detector, {len(rows)} settings, seeds {label}")
    fig.colorbar(sc, label="precision")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", choices=sorted(SEEDS), default="dev")
    parser.add_argument("--figure", action="store_true", help="also write docs/impulse_tradeoff.png")
    args = parser.parse_args()
    frames = [pulse_frame(seed, kind) for seed in SEEDS[args.seeds] for kind in KINDS]
    rows = []
    t0 = time.perf_counter()
    for values in itertools.product(*GRID.values()):
        row = score(frames, dict(zip(GRID, values, strict=True)))
        rows.append(row)
        print(row, flush=True)
    front = pareto(rows)
    meeting = [r for r in rows if r["recall"] >= TARGET["recall"] and r["precision"] >= TARGET["precision"]
               and r["pe_clean_pct"] <= TARGET["pe_clean_pct"]]
    best_at_target_pe = max((r for r in rows if r["pe_clean_pct"] <= TARGET["pe_clean_pct"]),
                            key=lambda r: r["recall"], default=None)
    least_pe_at_target_recall = min((r for r in rows if r["recall"] >= TARGET["recall"]
                                     and r["precision"] >= TARGET["precision"]),
                                    key=lambda r: r["pe_clean_pct"], default=None)
    print("Pareto front (PE on clean pixels -> recall):")
    for r in front:
        print(f"  PE {r['pe_clean_pct']:.4f} %  recall {r['recall']:.4f}  precision {r['precision']:.4f}  "
              f"{ {k: r[k] for k in GRID} }")
    record(f"impulse_tradeoff_{args.seeds}", {
        "seeds": list(SEEDS[args.seeds]), "grid": GRID, "default": DEFAULT, "target": TARGET,
        "settings_meeting_all_targets": meeting, "best_recall_at_target_pe": best_at_target_pe,
        "least_pe_at_target_recall_and_precision": least_pe_at_target_recall,
        "pareto_front": front, "rows": rows, "seconds": round(time.perf_counter() - t0, 1)})
    if args.figure:
        figure(rows, f"{args.seeds} {SEEDS[args.seeds]}", ROOT / "docs" / "impulse_tradeoff.png")


if __name__ == "__main__":
    main()
