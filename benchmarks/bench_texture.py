"""Texture synthesis: fast Efros–Leung against the slow reference, and image quilting against Efros–Leung.

Two comparisons in one run, on scikit-image's textures (offline), all from the texture module's own
functions:

1. Efros–Leung, fast (``efros_leung``: the masked SSD expanded into matrix products batched over an
   onion layer, the sequential rest in a Numba kernel) against the readable reference
   (``efros_leung_reference``: one sample window at a time), on the same sample and seed: a 64 x 64
   texture from a 32 x 32 sample, window 11. The outputs must be identical (same fill order, same
   sources, same pixels); the speed-up is the reference's time over the fast one's (median of
   ``--repeat`` runs for the fast one after a warm-up run that compiles its kernel; one run of the
   reference).
2. Image quilting (``image_quilting``, what the ``quilt`` step runs: minimum-error cuts, block 24,
   overlap 5) against the fast Efros–Leung (window 11) at the same output size: 256 x 256 from a
   64 x 64 sample. Efros–Leung at this size takes long even fast, so it runs once; quilting is the
   median of ``--repeat`` runs. Both times are synthesis only (the metrics are computed afterwards,
   for both alike). Quality is the texture statistics distance to the sample
   (``texture_statistics_distance``: pyramid subband histograms and Gram matrices of filter
   responses) and the visible-seam score.

Samples are 8-bit crops of ``skimage.data.<texture>()`` shrunk 2x (area averaging), taken from
the centre; ``--textures`` picks which (default brick; the RESULT keys without a prefix are the
first texture's; with several, the ratios per texture are added as ``<texture>_...``).

    python benchmarks/bench_texture.py [--repeat 3] [--textures brick grass gravel]

The last line is ``RESULT {json}`` with el_identical, el_speedup (reference time / fast time),
quilt_speedup_vs_el (Efros–Leung time / quilting time at 256 x 256), quilt_stat_ratio (quilting's
statistics distance / Efros–Leung's), the times, distances and seam scores.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import numpy as np

from lab.data.textures import brick, grass, gravel
from lab.modules.texture import (efros_leung, efros_leung_reference, image_quilting, seam_score,
                                 texture_statistics_distance)

LOADERS = {"brick": brick, "grass": grass, "gravel": gravel}
SEED = 2001


def _timed(function, *args, **kwargs):
    started = time.perf_counter()
    value = function(*args, **kwargs)
    return value, time.perf_counter() - started


def compare_el(sample, *, repeat: int) -> dict:
    size, window = (64, 64), 11
    # warm-up: compiles the kernel
    efros_leung(sample, size=(16, 16), window=window, rng=np.random.default_rng(0))
    reference, reference_s = _timed(efros_leung_reference, sample, size=size, window=window,
                                    rng=np.random.default_rng(SEED))
    fast_times = []
    for _ in range(repeat):
        fast, seconds = _timed(efros_leung, sample, size=size, window=window, rng=np.random.default_rng(SEED))
        fast_times.append(seconds)
    fast_s = statistics.median(fast_times)
    identical = bool(np.array_equal(fast[0], reference[0])
                     and np.array_equal(fast[1].fill_order, reference[1].fill_order)
                     and np.array_equal(fast[1].source, reference[1].source))
    return {"el_identical": identical, "el_reference_s": reference_s, "el_fast_s": fast_s,
            "el_speedup": reference_s / fast_s}


def compare_quilting(sample, *, repeat: int) -> dict:
    size = (256, 256)
    (el_pixels, el_trace), el_s = _timed(efros_leung, sample, size=size, window=11,
                                         rng=np.random.default_rng(SEED))
    quilt_times = []
    for _ in range(repeat):
        (quilt_pixels, quilt_source, _), seconds = _timed(image_quilting, sample, size=size, block=24,
                                                          overlap=5, rng=np.random.default_rng(SEED))
        quilt_times.append(seconds)
    quilt_s = statistics.median(quilt_times)
    el_stat = texture_statistics_distance(el_pixels, sample.pixels)
    quilt_stat = texture_statistics_distance(quilt_pixels, sample.pixels)
    return {"el256_s": el_s, "quilt256_s": quilt_s, "quilt_speedup_vs_el": el_s / quilt_s,
            "el_stat_distance": el_stat, "quilt_stat_distance": quilt_stat,
            "quilt_stat_ratio": quilt_stat / el_stat,
            "el_seam_score": seam_score(el_pixels, el_trace.source, sample.pixels),
            "quilt_seam_score": seam_score(quilt_pixels, quilt_source, sample.pixels)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs of the fast methods (median)")
    parser.add_argument("--textures", nargs="+", default=["brick"], choices=sorted(LOADERS))
    args = parser.parse_args()
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover
        cpus = os.cpu_count() or 1
    out: dict = {}
    for index, name in enumerate(args.textures):
        small = LOADERS[name](size=32, downsample=2).state["sample"]
        large = LOADERS[name](size=64, downsample=2).state["sample"]
        el = compare_el(small, repeat=args.repeat)
        print(f"{name}: Efros-Leung 64x64 from 32x32, window 11: reference {el['el_reference_s']:.2f} s, "
              f"fast {el['el_fast_s']:.3f} s, speed-up {el['el_speedup']:.1f}x, "
              f"identical {el['el_identical']}")
        quilting = compare_quilting(large, repeat=args.repeat)
        print(f"{name}: 256x256 from 64x64: Efros-Leung {quilting['el256_s']:.2f} s (stat distance "
              f"{quilting['el_stat_distance']:.3f}, seam score {quilting['el_seam_score']:.2f}); quilting "
              f"{quilting['quilt256_s']:.3f} s (stat distance {quilting['quilt_stat_distance']:.3f}, "
              "seam score "
              f"{quilting['quilt_seam_score']:.2f}); quilting {quilting['quilt_speedup_vs_el']:.0f}x faster, "
              f"stat ratio {quilting['quilt_stat_ratio']:.2f}")
        values = {**el, **quilting}
        if index == 0:
            out.update(values)
        if len(args.textures) > 1:
            out.update({f"{name}_{key}": value for key, value in values.items()})
    out["cpus"] = cpus
    out["textures"] = args.textures
    print("RESULT " + json.dumps({k: round(v, 6) if isinstance(v, float) else v for k, v in out.items()}))


if __name__ == "__main__":
    main()
