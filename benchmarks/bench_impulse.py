"""Benchmark: impulse removal on a 6000x4000 RGB frame against a 3x3 median of its channels.

Target (issue 2): ``remove_impulses`` (HSV, default passes H 3, S 1, V 1) in at most a third
of the time ``scipy.ndimage.median_filter(size=3)`` takes on the three channels, both
measured in this run on the same frame. The frame is synthetic but realistic: smooth
radiograph-like content (blobs, edges, gradients, blurred like a scintillator), tinted like
Gd2O2S:Tb light, Poisson noise, and multi-pixel pulses (bright zingers in V, hue and
saturation patches). Also reports peak memory and the detection quality on the frame.

Run: ``.venv/bin/python benchmarks/bench_impulse.py [--small]`` (``--small``: 1500x1000 for
a quick check). Timings are inflated when other jobs share the CPU.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import best_time, peak_rss_mb, record  # noqa: E402

PULSE_FRACTION = 0.001  # of the pixels, in patches of 1x1 to 4x4


def reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS mark of this process (Linux); False where unsupported."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def current_peak_rss_mb() -> float:
    """Peak RSS since the last reset (VmHWM), MiB; falls back to the process's lifetime peak."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return peak_rss_mb()


def synthetic_frame(height: int, width: int, seed: int = 7):
    """Radiograph-like RGB frame (uint16 counts) with pulses; returns frame and truth mask."""
    import cv2

    from napari_dslrxr.core.stages.impulse import hsv_counts_to_rgb, rgb_to_hsv_counts

    rng = np.random.default_rng(seed)
    small_h, small_w = height // 10, width // 10
    yy, xx = np.mgrid[:small_h, :small_w].astype(np.float32)
    attenuation = np.zeros((small_h, small_w), np.float32)
    for _ in range(40):  # soft "anatomy"
        cy, cx = rng.uniform(0, small_h), rng.uniform(0, small_w)
        sy, sx = rng.uniform(5, 60, 2)
        attenuation += rng.uniform(0.1, 0.6) * np.exp(-((yy - cy) ** 2 / (2 * sy ** 2) + (xx - cx) ** 2 / (2 * sx ** 2)))
    for _ in range(12):  # sharp-edged "bones" and plates
        cy, cx, r = rng.uniform(0, small_h), rng.uniform(0, small_w), rng.uniform(5, 40)
        attenuation += 0.5 * (((yy - cy) ** 2 + (xx - cx) ** 2) < r * r)
    light = np.exp(-attenuation)
    light = cv2.resize(light, (width, height), interpolation=cv2.INTER_LINEAR)
    light = cv2.GaussianBlur(light, (0, 0), 2.0)  # screen blur
    vignetting = (1 - 0.3 * (((np.arange(width) - width / 2) / width) ** 2)).astype(np.float32)
    light = 150 + 3500 * (light / light.max()) * vignetting[None, :]
    tint = np.array([0.35, 1.0, 0.15], np.float32)
    frame = rng.poisson(light[..., None] * tint).astype(np.float32)
    del light
    hue, sat, val = rgb_to_hsv_counts(frame)
    truth = np.zeros((height, width), bool)
    n_patches = int(PULSE_FRACTION * height * width / 4)
    sides = rng.integers(1, 5, n_patches)
    rows = rng.integers(0, height - 4, n_patches)
    cols = rng.integers(0, width - 4, n_patches)
    kinds = rng.integers(0, 3, n_patches)
    for side, r, c, kind in zip(sides, rows, cols, kinds, strict=True):
        patch = (slice(r, r + side), slice(c, c + side))
        if kind == 0:
            val[patch] *= rng.uniform(1.5, 4.0)
        elif kind == 1:
            hue[patch] = (hue[patch] + rng.uniform(0.1, 0.3)) % 1.0
        else:
            sat[patch] = np.clip(sat[patch] - rng.uniform(0.35, 0.6), 0, 1)
        truth[patch] = True
    changed = np.nonzero(truth)
    frame[changed] = hsv_counts_to_rgb(hue[changed], sat[changed], val[changed])
    return np.clip(np.rint(frame), 0, 65535).astype(np.uint16), truth


def main() -> None:
    from scipy import ndimage as ndi

    from napari_dslrxr.core.stages.impulse import remove_impulses

    parser = argparse.ArgumentParser()
    parser.add_argument("--small", action="store_true", help="1500x1000 instead of 6000x4000")
    args = parser.parse_args()
    height, width = (1000, 1500) if args.small else (4000, 6000)
    frame, truth = synthetic_frame(height, width)
    reset = reset_peak_rss()
    rss_before = current_peak_rss_mb()

    t0, c0 = time.perf_counter(), time.process_time()
    result = remove_impulses(frame)
    t_first, cpu_ours = time.perf_counter() - t0, time.process_time() - c0
    rss_ours = current_peak_rss_mb()
    # Best of three wall times for both (the harness's convention): other jobs on the two
    # shared cores inflate single runs by up to 2x.
    t_ours = min(t_first, best_time(lambda: remove_impulses(frame), repeat=2))
    found = result.any_mask()
    hit = int(np.count_nonzero(found & truth))
    recall, precision = hit / max(int(truth.sum()), 1), hit / max(int(found.sum()), 1)
    del result

    def median_three_channels() -> None:
        for channel in range(3):
            ndi.median_filter(frame[..., channel], size=3)

    c0 = time.process_time()
    t_median = best_time(median_three_channels, repeat=3)
    cpu_median = (time.process_time() - c0) / 3

    ratio = t_ours / t_median
    record("impulse", {
        "frame": f"{width}x{height} RGB uint16",
        "remove_impulses_s": round(t_ours, 2),
        "scipy_median3_three_channels_s": round(t_median, 2),
        "ratio": round(ratio, 3),
        "remove_impulses_cpu_s": round(cpu_ours, 2),
        "scipy_median3_cpu_s": round(cpu_median, 2),
        "cpu_ratio": round(cpu_ours / cpu_median, 3),
        "target_ratio": round(1 / 3, 3),
        "rss_mb_before_remove_impulses": round(rss_before, 1),
        "peak_rss_mb_during_remove_impulses": round(rss_ours, 1),
        "peak_rss_mb_added_by_remove_impulses": round(rss_ours - rss_before, 1),
        "peak_reset_supported": reset,
        "pulse_recall": round(recall, 4),
        "pulse_precision": round(precision, 4),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "note": "wall: best of 3 each; CPU: ours first run, median mean of 3; other jobs on the "
                "2 shared cores inflate wall times",
        "pass": bool(ratio <= 1 / 3),
    })


if __name__ == "__main__":
    main()
