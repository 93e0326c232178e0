"""Full pipeline on a 6000x4000 colour frame (no deblurring): <= 15 s and <= 3 GB peak memory.

The frame is a synthetic DSLR-like radiograph (napari_dslrxr.core.phantom) with a flat and a
dark frame. Reports the total wall time of one run, the share of each stage and the peak
resident memory of the process (which includes generating the test frames).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import peak_rss_mb, record  # noqa: E402


def main() -> int:
    from napari_dslrxr.core.flatfield import prepare_flat_reference
    from napari_dslrxr.core.params import PipelineParams
    from napari_dslrxr.core.phantom import make_dslr_radiograph
    from napari_dslrxr.core.pipeline import process_frame

    frames = make_dslr_radiograph((4000, 6000), seed=0)
    raw, flat, dark = frames.raw_rgb, frames.flat, frames.dark
    del frames
    params = PipelineParams()
    t0 = time.perf_counter()
    reference = prepare_flat_reference(raw.shape, flats=[flat], darks=[dark], params=params.flatfield)
    t_reference = time.perf_counter() - t0
    del flat, dark
    t1 = time.perf_counter()
    result = process_frame(raw, params=params, reference=reference)
    t_run = time.perf_counter() - t1
    total = t_reference + t_run
    stages = {"flat_reference": t_reference, **result.timings_s}
    values = {
        "shape": list(raw.shape), "total_s": round(total, 2),
        "stage_s": {k: round(v, 2) for k, v in stages.items()},
        "stage_share": {k: round(v / total, 3) for k, v in stages.items()},
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "target": "<= 15 s and <= 3072 MB",
    }
    values["pass"] = bool(total <= 15.0 and values["peak_rss_mb"] <= 3072)
    record("pipeline", values)
    return 0


if __name__ == "__main__":
    sys.exit(main())
