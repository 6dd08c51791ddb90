"""Epipolar geometry: our F -> E -> pose pipeline against OpenCV's, on the same matches.

Three data sets, in one run:

* the synthetic benchmark (the headline numbers): the ``correspondences`` dataset's defaults, 400
  random points seen by two known cameras 1 m apart at 5 m, 0.5 px noise, 30 % wrong matches
  (exact truth, controlled noise and outliers), one set per seed;
* rendered two-view scenes (the module's default dataset: the "room" scene, 640 x 480, 0.5 m
  baseline, one scene per seed); features and matches come from our steps (SIFT, ratio test,
  mutual check), then every method gets the same matches and K. SIFT on these images gives only
  about 3 % wrong matches, so RANSAC has little to do: OpenCV's FM_RANSAC stops after a handful of
  7-point samples (about 0.3 ms) while our step's fixed costs (Python, the local optimization, the
  Sampson refit, the degeneracy check) dominate; the ``rendered_`` keys report it;
* OpenCV's leuvenA/B photos with their K (``../shared/data/opencv-samples``).

Methods on the same matches:

* ours: ``estimate_fundamental_ransac`` (8-point RANSAC, threshold 1 px Sampson, confidence 0.99),
  ``estimate_essential``, ``recover_pose``, ``refine_pose``;
* OpenCV (E): ``cv2.findEssentialMat(x1, x2, K, cv2.RANSAC, 0.999, 1.0)`` + ``cv2.recoverPose``;
* OpenCV (F): ``cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, 1.0, 0.99)``, ``E = K^T F K`` +
  ``cv2.recoverPose``.

The ``_opencv`` numbers are those of the better OpenCV method (lower median). The RANSAC time
ratio is our ``estimate_fundamental_ransac`` (the whole step, degeneracy check included) over
``cv2.findFundamentalMat(FM_RANSAC)``, each the median of ``--repeat`` runs, then the median over
the scenes; both run on one thread (``OPENBLAS_NUM_THREADS=1``, ``cv2.setNumThreads(1)``),
so other processes on the machine disturb the ratio as little as possible. On leuven, the inlier
overlap is |ours & OpenCV's| / |ours | OpenCV's| against ``FM_RANSAC`` (threshold 1 px), and the
Sampson RMS ratio compares each method's inliers under its own F.

    python benchmarks/bench_epipolar.py [--seeds 8] [--repeat 9]

The last line is ``RESULT {json}``.
"""

from __future__ import annotations

import os

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import timeit  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from lab.core import open_session  # noqa: E402
from lab.geometry.rotations import rotation_angle_deg  # noqa: E402
from lab.modules.epipolar import (PIPELINE, estimate_essential, estimate_fundamental_ransac, recover_pose,  # noqa: E402
                                  refine_pose, sampson_distance)

SAMPLES = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "opencv-samples"
THRESHOLD_PX = 1.0


def median_seconds(func, repeat: int) -> float:
    return statistics.median(timeit.repeat(func, number=1, repeat=repeat))


def angle_errors(R: np.ndarray, t: np.ndarray, truth: dict) -> tuple[float, float]:
    t_true = truth["t"] / np.linalg.norm(truth["t"])
    cosine = float(np.ravel(t) @ t_true / np.linalg.norm(t))
    return float(rotation_angle_deg(R, truth["R"])), float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


def ours(session, x1, x2, seed: int):
    ransac = estimate_fundamental_ransac(x1, x2, threshold_px=THRESHOLD_PX, rng=np.random.default_rng(seed))
    E = estimate_essential(ransac.F, session.state["images"], session.state["K1"], session.state["K2"])
    pose = recover_pose(E, x1, x2, session.state["K1"], session.state["K2"], ransac.inliers)
    refined = refine_pose(pose, x1, x2, session.state["K1"], session.state["K2"], ransac.inliers)
    return ransac, refined.R, refined.t


def opencv_essential(x1, x2, K):
    E, mask = cv2.findEssentialMat(x1, x2, K, cv2.RANSAC, 0.999, THRESHOLD_PX)
    _, R, t, _ = cv2.recoverPose(E[:3], x1, x2, K, mask=mask.copy())
    return R, t.ravel()


def opencv_fundamental(x1, x2, K):
    F, mask = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, THRESHOLD_PX, 0.99)
    E = K.T @ F[:3] @ K
    _, R, t, _ = cv2.recoverPose(E, x1, x2, K, mask=mask.copy())
    return R, t.ravel()


def compare_scene(dataset: str, options: dict, seed: int, repeat: int) -> dict:
    session = open_session(PIPELINE, dataset, dict(options, seed=seed), seed=seed)
    if "x1" not in session.state:
        session.run("detect_features")
        session.run("match_features")
    x1, x2, K = session.state["x1"], session.state["x2"], session.state["K1"]
    truth = session.truth
    ransac, R, t = ours(session, x1, x2, seed)
    row = {"seed": seed, "matches": len(x1), "inliers": int(ransac.inliers.sum()), "iterations": ransac.iterations}
    row["rot_ours"], row["trans_ours"] = angle_errors(R, t, truth)
    row["rot_cv_e"], row["trans_cv_e"] = angle_errors(*opencv_essential(x1, x2, K), truth)
    row["rot_cv_f"], row["trans_cv_f"] = angle_errors(*opencv_fundamental(x1, x2, K), truth)
    rng = np.random.default_rng(seed)
    row["t_ours_ms"] = 1000 * median_seconds(
        lambda: estimate_fundamental_ransac(x1, x2, threshold_px=THRESHOLD_PX, rng=rng), repeat)
    row["t_cv_ms"] = 1000 * median_seconds(
        lambda: cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, THRESHOLD_PX, 0.99), repeat)
    row["time_ratio"] = row["t_ours_ms"] / row["t_cv_ms"]
    return row


def summarize(rows: list[dict]) -> dict:
    med = lambda key: float(np.median([r[key] for r in rows]))  # noqa: E731
    out = {"rot_ours": med("rot_ours"), "trans_ours": med("trans_ours"), "rot_cv_e": med("rot_cv_e"),
           "trans_cv_e": med("trans_cv_e"), "rot_cv_f": med("rot_cv_f"), "trans_cv_f": med("trans_cv_f"),
           "time_ratio": med("time_ratio"), "t_ours_ms": med("t_ours_ms"), "t_cv_ms": med("t_cv_ms")}
    out["rot_cv"] = min(out["rot_cv_e"], out["rot_cv_f"])
    out["trans_cv"] = min(out["trans_cv_e"], out["trans_cv_f"])
    return out


def print_table(title: str, rows: list[dict], summary: dict) -> None:
    print(f"\n{title}")
    print(f"{'seed':>4} {'match':>6} {'inl':>5} {'iter':>5} | {'rot ours':>8} {'cv E':>7} {'cv F':>7} | "
          f"{'t ours':>7} {'cv E':>7} {'cv F':>7} | {'ms ours':>8} {'ms cv':>7} {'ratio':>6}")
    for r in rows:
        print(f"{r['seed']:>4} {r['matches']:>6} {r['inliers']:>5} {r['iterations']:>5} | {r['rot_ours']:8.3f} "
              f"{r['rot_cv_e']:7.3f} {r['rot_cv_f']:7.3f} | {r['trans_ours']:7.3f} {r['trans_cv_e']:7.3f} "
              f"{r['trans_cv_f']:7.3f} | {r['t_ours_ms']:8.2f} {r['t_cv_ms']:7.2f} {r['time_ratio']:6.2f}")
    s = summary
    print(f"{'median':>23} | {s['rot_ours']:8.3f} {s['rot_cv_e']:7.3f} {s['rot_cv_f']:7.3f} | {s['trans_ours']:7.3f} "
          f"{s['trans_cv_e']:7.3f} {s['trans_cv_f']:7.3f} | {s['t_ours_ms']:8.2f} {s['t_cv_ms']:7.2f} "
          f"{s['time_ratio']:6.2f}")


def compare_leuven(repeat: int) -> dict:
    session = open_session(PIPELINE, "photos", {"path": str(SAMPLES), "k_file": "essential_mat_data.txt"})
    session.run("detect_features")
    session.run("match_features")
    x1, x2 = session.state["x1"], session.state["x2"]
    F_cv, mask_cv = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, THRESHOLD_PX, 0.99)
    mask_cv = mask_cv.ravel() > 0
    rms = lambda F, m: float(np.sqrt(np.mean(sampson_distance(F, x1[m], x2[m]) ** 2)))  # noqa: E731
    rms_cv = rms(F_cv, mask_cv)
    out = {"matches": len(x1), "opencv_inliers": int(mask_cv.sum()), "opencv_sampson_rms_px": rms_cv}
    for error in ("sampson", "epipolar"):
        result = estimate_fundamental_ransac(x1, x2, threshold_px=THRESHOLD_PX, error=error,
                                             rng=np.random.default_rng(0))
        m = result.inliers
        out[error] = {"inliers": int(m.sum()), "overlap": float((m & mask_cv).sum() / (m | mask_cv).sum()),
                      "sampson_rms_px": rms(result.F, m), "sampson_rms_ratio": rms(result.F, m) / rms_cv}
    rng = np.random.default_rng(0)
    t_ours = median_seconds(lambda: estimate_fundamental_ransac(x1, x2, threshold_px=THRESHOLD_PX, rng=rng), repeat)
    t_cv = median_seconds(lambda: cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, THRESHOLD_PX, 0.99), repeat)
    out["time_ratio"] = t_ours / t_cv
    print(f"\nleuvenA/B: {len(x1)} matches; OpenCV FM_RANSAC {int(mask_cv.sum())} inliers, Sampson RMS {rms_cv:.4f} px")
    for error in ("sampson", "epipolar"):
        r = out[error]
        print(f"  ours ({error:8s}): {r['inliers']} inliers, overlap {r['overlap']:.3f}, Sampson RMS "
              f"{r['sampson_rms_px']:.4f} px (ratio {r['sampson_rms_ratio']:.3f})")
    print(f"  RANSAC time ratio {t_ours * 1000:.2f} ms / {t_cv * 1000:.2f} ms = {out['time_ratio']:.2f}")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=8, help="scenes per synthetic data set")
    parser.add_argument("--repeat", type=int, default=9, help="timing repeats (median)")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    corr_rows = [compare_scene("correspondences", {}, seed, args.repeat) for seed in range(args.seeds)]
    corr = summarize(corr_rows)
    print_table("Synthetic benchmark: correspondences, 400 points, 0.5 px noise, 30 % outliers (errors in degrees)",
                corr_rows, corr)
    rendered_rows = [compare_scene("rendered", {}, seed, args.repeat) for seed in range(args.seeds)]
    rendered = summarize(rendered_rows)
    print_table("Rendered 'room' scenes, 640x480, baseline 0.5 m, SIFT matches", rendered_rows, rendered)
    leuven = compare_leuven(args.repeat)
    result = {
        "rot_err_deg_median": corr["rot_ours"], "rot_err_deg_median_opencv": corr["rot_cv"],
        "trans_err_deg_median": corr["trans_ours"], "trans_err_deg_median_opencv": corr["trans_cv"],
        "rot_err_deg_median_opencv_essential": corr["rot_cv_e"],
        "rot_err_deg_median_opencv_fundamental": corr["rot_cv_f"],
        "trans_err_deg_median_opencv_essential": corr["trans_cv_e"],
        "trans_err_deg_median_opencv_fundamental": corr["trans_cv_f"],
        "ransac_time_ratio": corr["time_ratio"],
        "rendered_rot_err_deg_median": rendered["rot_ours"], "rendered_rot_err_deg_median_opencv": rendered["rot_cv"],
        "rendered_trans_err_deg_median": rendered["trans_ours"],
        "rendered_trans_err_deg_median_opencv": rendered["trans_cv"],
        "rendered_ransac_time_ratio": rendered["time_ratio"],
        "rendered_ransac_ms_ours": rendered["t_ours_ms"], "rendered_ransac_ms_opencv": rendered["t_cv_ms"],
        "leuven_inlier_overlap": leuven["sampson"]["overlap"],
        "leuven_sampson_rms_ratio": leuven["sampson"]["sampson_rms_ratio"],
        "leuven_inlier_overlap_epipolar_error": leuven["epipolar"]["overlap"],
        "leuven_sampson_rms_ratio_epipolar_error": leuven["epipolar"]["sampson_rms_ratio"],
        "leuven_ransac_time_ratio": leuven["time_ratio"],
        "seeds": args.seeds,
    }
    print("RESULT " + json.dumps({k: round(v, 5) if isinstance(v, float) else v for k, v in result.items()}))


if __name__ == "__main__":
    main()
