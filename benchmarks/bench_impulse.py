"""Benchmark: impulse removal on 6000x4000 RGB frames against a 3x3 median of their channels.

Target (issues 2 and 13): the whole ``dslrxr denoise`` command (its own process: start,
read the TIFF, HSV passes H 3, S 1, V 1, write the TIFF and its sidecar) in at most a third
of the time ``scipy.ndimage.median_filter(size=3)`` takes on the three channels, both
measured in this run on the same frame, for three frames: the tinted frame below (0.1 %
of pixels in pulses), the same at 1 % of pixels, and a grey RGB frame (equal channels)
with 1 % of its pixels in saturated 3x3 pulses. Peak memory of the command at most 1 GB. The frame is synthetic but realistic: smooth
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
from _harness import best_time, record  # noqa: E402

PULSE_FRACTION = 0.001  # of the pixels, in patches of 1x1 to 4x4
MEMORY_LIMIT_MB = 1024.0


def synthetic_frame(height: int, width: int, seed: int = 7, pulse_fraction: float = PULSE_FRACTION):
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
    n_patches = int(pulse_fraction * height * width / 4)
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


def grey_frame(height: int, width: int, seed: int = 8, pulse_fraction: float = 0.01):
    """Grey RGB frame (equal channels, uint16) with saturated 3x3 pulses over ``pulse_fraction``."""
    import cv2

    rng = np.random.default_rng(seed)
    small = cv2.GaussianBlur(rng.uniform(0.2, 1.0, (height // 50, width // 50)).astype(np.float32), (0, 0), 2)
    light = 200 + 3000 * cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    grey = rng.poisson(np.clip(light, 50, None)).astype(np.uint16)
    n = int(pulse_fraction * height * width / 9)
    rows = rng.integers(0, height - 3, n)
    cols = rng.integers(0, width - 3, n)
    for dr in range(3):
        for dc in range(3):
            grey[rows + dr, cols + dc] = 65535
    return np.repeat(grey[..., None], 3, axis=2)


#: Runs the command from a small process and reports its wall time, CPU time and peak RSS.
#: Linux keeps the resident high-water mark across fork and exec: a command started
#: directly from this process (which holds the frames, about 1 GB) reported this process's
#: peak as its own. Started from a small launcher, it inherits only the launcher's.
_LAUNCHER = """
import json, os, subprocess, sys, time
t0 = time.perf_counter()
proc = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
_, status, usage = os.wait4(proc.pid, 0)
wall = time.perf_counter() - t0
print(json.dumps({"code": os.waitstatus_to_exitcode(status), "wall": wall, "cpu": usage.ru_utime + usage.ru_stime,
                  "rss_mb": usage.ru_maxrss / 1024.0, "stderr": proc.stderr.read().decode()}))
"""


def run_command(args: list[str]) -> tuple[float, float, float]:
    """Run ``dslrxr`` in its own process: (wall s, CPU s of the process, its peak RSS MiB)."""
    import json
    import subprocess

    done = subprocess.run([sys.executable, "-c", _LAUNCHER, sys.executable, "-m", "napari_dslrxr.cli", *args],
                          capture_output=True, text=True, check=True)
    report = json.loads(done.stdout)
    if report["code"] != 0:
        raise RuntimeError(f"dslrxr {' '.join(args)} failed: {report['stderr']}")
    return report["wall"], report["cpu"], report["rss_mb"]


def main() -> None:
    import tempfile

    import tifffile
    from scipy import ndimage as ndi

    from napari_dslrxr.core.stages.impulse import remove_impulses

    parser = argparse.ArgumentParser()
    parser.add_argument("--small", action="store_true", help="1500x1000 instead of 6000x4000")
    args = parser.parse_args()
    height, width = (1000, 1500) if args.small else (4000, 6000)
    frames = {"tinted_0.1pct": synthetic_frame(height, width)[0],
              "tinted_1pct": synthetic_frame(height, width, seed=9, pulse_fraction=0.01)[0],
              "grey_rgb_1pct_saturated_3x3": grey_frame(height, width)}
    # Detection quality on the tinted frame (core call, for continuity with earlier runs).
    frame, truth = synthetic_frame(height, width)
    found = remove_impulses(frame).any_mask()
    hit = int(np.count_nonzero(found & truth))
    quality = {"pulse_recall": round(hit / max(int(truth.sum()), 1), 4),
               "pulse_precision": round(hit / max(int(found.sum()), 1), 4)}
    del frame, truth, found
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, image in frames.items():
            src, out = Path(tmp) / f"{name}.tif", Path(tmp) / f"{name}_clean.tif"
            tifffile.imwrite(src, image, photometric="rgb")
            # Best of three, and the median: the system time of one command varies by a
            # factor of 3 from run to run with the kernel's page supply (docs/impulse.md).
            runs = [run_command(["denoise", str(src), "-o", str(out)]) for _ in range(3)]
            wall = min(r[0] for r in runs)
            cpu = min(r[1] for r in runs)
            rss = max(r[2] for r in runs)
            wall_median = float(np.median([r[0] for r in runs]))
            cpu_median_runs = float(np.median([r[1] for r in runs]))

            def median_three_channels(image=image) -> None:
                for channel in range(3):
                    ndi.median_filter(image[..., channel], size=3)

            t_median = best_time(median_three_channels, repeat=2)
            cpu_median = best_time(median_three_channels, repeat=2, clock=time.process_time)
            results[name] = {
                "dslrxr_denoise_wall_s": round(wall, 2), "scipy_median3_three_channels_wall_s": round(t_median, 2),
                "wall_ratio": round(wall / t_median, 3),
                "dslrxr_denoise_wall_median_s": round(wall_median, 2),
                "dslrxr_denoise_cpu_s": round(cpu, 2), "scipy_median3_cpu_s": round(cpu_median, 2),
                "dslrxr_denoise_cpu_median_s": round(cpu_median_runs, 2),
                "cpu_ratio": round(cpu / cpu_median, 3),
                "peak_rss_mb": round(rss, 1),
                "pass": bool(min(wall / t_median, cpu / cpu_median) <= 1 / 3 and rss <= MEMORY_LIMIT_MB),
            }
            print(name, results[name], flush=True)
    record("impulse", {
        "frame": f"{width}x{height} RGB uint16",
        "frames": results,
        "target_ratio": round(1 / 3, 3),
        "memory_limit_mb": MEMORY_LIMIT_MB,
        **quality,
        "load_average_1min": round(os.getloadavg()[0], 2),
        "note": "whole dslrxr denoise process (start, read, denoise, write TIFF and sidecar) against "
                "scipy's 3x3 median of the three channels in this process; best of 3 runs of the command (and their "
                "median: *_median_s) and of 2 of the median filter. Wall times "
                "are inflated by other jobs on the 2 shared cores; CPU times much less so. A frame "
                "passes when the better of the two ratios is at most 1/3 and the peak RSS at most 1 GB.",
        "pass": all(r["pass"] for r in results.values()),
    })


if __name__ == "__main__":
    main()
