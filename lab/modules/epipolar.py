"""Epipolar geometry of two views, step by step: features, matches, F, E, the relative pose, 3D points.

References: R. Hartley and A. Zisserman, Multiple View Geometry in Computer Vision (2nd ed., 2004),
chapters 9 (epipolar geometry, F and E), 11 (computing F: the normalized 8-point algorithm,
algorithm 11.1; RANSAC, algorithm 11.4) and 12 (triangulation); R. Hartley, "In defense of the
eight-point algorithm", TPAMI 19(6), 1997; M. Fischler and R. Bolles, "Random sample consensus",
CACM 24(6), 1981; D. Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 60(2),
2004 (SIFT and the ratio test).

Conventions (DESIGN.md section 3): image 1 is view 0 of ``images`` and image 2 is view 1; camera 1
is the world frame and camera 2 sees ``X_2 = R X_1 + t``; ``x2^T F x1 = 0``; ``E = [t]_x R``,
``F = K2^-T E K1^-1``. The intrinsics are two matrices, ``K1`` and ``K2`` (equal when one camera
took both photos), so a pair from two different cameras needs no special case.

State names (float64 unless said):
    images          ImageSet (2)      the two photos (dataset)
    K1, K2          (3, 3)            camera matrices of image 1 and image 2 (dataset; absent when unknown)
    keypoints       Points2D          SIFT keypoints of both images, ``view`` 0 (image 1) or 1 (image 2)
    descriptors     (N, 128) float32  one descriptor per keypoint
    matches         (M, 2) int        indices into ``keypoints``: [keypoint in image 1, keypoint in image 2]
    x1, x2          (M, 2)            the matched pixels in image 1 and image 2
    F               (3, 3)            fundamental matrix, rank 2, unit Frobenius norm; written by the
                                      8-point step (all matches) and again by RANSAC (the robust estimate):
                                      the later steps read the last one written
    inliers         (M,) bool         RANSAC's inliers (absent before RANSAC runs: every match counts)
    ransac_trace    Curve             best inlier count and the adaptive iteration bound N, per hypothesis
    epipolar_lines  Segments2D        epipolar lines of a sample of inliers, clipped to the images: in
                                      image 2 ``F x1`` (view 1), in image 1 ``F^T x2`` (view 0)
    line_points     Points2D          the sampled inliers themselves, coloured as their lines
    epipoles        (2, 3)            homogeneous unit epipoles: row 0 ``e1`` (``F e1 = 0``, in image 1),
                                      row 1 ``e2`` (``F^T e2 = 0``, in image 2); finite even at infinity
    epipole_points  Points2D          the epipoles that are finite, in pixels (view 0 / 1)
    E               (3, 3)            essential matrix ``K2^T F K1`` projected onto singular values (1, 1, 0)
    candidates      (4, 3, 4)         the four ``[R | t]`` that E admits, in ``cv2.recoverPose``'s order
                                      (R1, t), (R2, t), (R1, -t), (R2, -t)
    pose            (3, 4)            ``[R | t]`` of camera 2 chosen by the cheirality test, ``|t| = 1``
    R, t            (3, 3), (3,)      the relative pose after refinement (``X_2 = R X_1 + t``, ``|t| = 1``)
    points3d_dlt    (N, 3)            linear triangulation of the inliers (camera 1 frame, baseline = 1)
    points3d        PointCloud        the refined points, coloured from image 1
    cameras         Cameras (2)       camera 1 at the origin, camera 2 at ``(R, t)``
    residuals       Segments2D        observed pixel -> observed + scale x (reprojected - observed)

Hand-written here, with the OpenCV call each one corresponds to (and is tested against): the
8-point algorithm and rank-2 enforcement (``cv2.findFundamentalMat(..., cv2.FM_8POINT)``), RANSAC
(``cv2.FM_RANSAC``), the Sampson distance (``cv2.sampsonDistance``), epipolar lines
(``cv2.computeCorrespondEpilines``), the decomposition of E (``cv2.decomposeEssentialMat``), the
cheirality test (``cv2.recoverPose``) and triangulation (``cv2.triangulatePoints``, in
:mod:`lab.geometry.triangulation`). SIFT and the homography used to detect degenerate input are
OpenCV's.
"""

from __future__ import annotations

import functools
from typing import Annotated, Any, Literal

import numpy as np

from lab.core.step import step_result, Warnings
from lab.core import (Cameras, Curve, ImageSet, InvalidValue, Pipeline, PointCloud, Points2D, Range, Segments2D,
                      StepFailed, metric)
from lab.data.two_view import correspondences, photos, rendered
from lab.geometry.camera import as_intrinsics, pixels_to_normalized
from lab.geometry.homogeneous import hartley_normalization, to_homogeneous
from lab.geometry.robust import random_samples, ransac_iterations
from lab.geometry.rotations import rotation_angle_deg
from lab.geometry.triangulation import point_depths, projection_matrix, reprojection_residuals, triangulate_dlt
from lab.geometry.triangulation import refine_points as refine_point_positions

#: Correspondences per minimal sample of the 8-point algorithm.
SAMPLE_SIZE = 8

#: OpenCV's SIFT reports keypoints this many pixels right of and below where they are (pixel centres at
#: integer coordinates): its first octave is the image upsampled 2x by a centre-aligned ``cv2.resize``,
#: but coordinates found there are halved as if the grids were corner-aligned (a Gaussian blob centred at
#: (50, 60) is reported at about (50.24, 60.24)). A shift shared by every keypoint of every image acts like
#: a wrong principal point and tilts the cameras by ``0.25 / f`` radians (0.04 degrees at f = 554 px), so
#: :func:`detect_features` subtracts it; the SfM module reads its keypoints from there.
SIFT_OFFSET_PX = 0.25


# ----------------------------------------------------------------------------------------------------
# Errors: degenerate input gets a clear error, never a wrong answer
# ----------------------------------------------------------------------------------------------------
class DegenerateInput(StepFailed):
    """The matches do not determine the geometry: any answer would be arbitrary."""


class TooFewMatches(DegenerateInput):
    """Fewer correspondences than the algorithm needs."""


class CollinearPoints(DegenerateInput):
    """All points lie on one line in an image."""


class CoplanarPoints(DegenerateInput):
    """One homography explains every match: the points lie on one plane."""


class ZeroBaseline(DegenerateInput):
    """One homography that is a rotation explains every match: the cameras share their centre."""


class MissingIntrinsics(InvalidValue):
    """A step needs K and none was given (and none can be assumed)."""


# ----------------------------------------------------------------------------------------------------
# Input checks shared by the steps
# ----------------------------------------------------------------------------------------------------
def _pair(x1: Any, x2: Any, *, minimum: int = SAMPLE_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """``x1``, ``x2`` as finite ``(M, 2)`` float arrays of equal length, at least ``minimum`` rows."""
    arrays = []
    for name, value in (("x1", x1), ("x2", x2)):
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise InvalidValue(name, f"cannot be read as an (M, 2) array of pixels ({type(value).__name__})") from None
        if array.ndim != 2 or array.shape[1] != 2:
            raise InvalidValue(name, f"expected shape (M, 2), got {array.shape}")
        bad = ~np.all(np.isfinite(array), axis=1)
        if bad.any():
            raise InvalidValue(name, f"{int(bad.sum())} of {len(array)} points contain NaN or infinite coordinates "
                                     f"(first at row {int(np.argmax(bad))}); remove them first")
        arrays.append(array)
    if len(arrays[0]) != len(arrays[1]):
        raise InvalidValue("x2", f"x1 has {len(arrays[0])} points and x2 {len(arrays[1])}: one per match in each")
    if len(arrays[0]) < minimum:
        needs = "the 8-point algorithm needs" if minimum == SAMPLE_SIZE else "this step needs"
        raise TooFewMatches("x1", f"{len(arrays[0])} matches; {needs} at least {minimum} (detect more features: "
                                  "lower the contrast threshold, raise the ratio)")
    return arrays[0], arrays[1]


def _inlier_mask(inliers: Any, count: int) -> np.ndarray:
    if inliers is None:
        return np.ones(count, dtype=bool)
    mask = np.asarray(inliers)
    if mask.shape != (count,) or mask.dtype.kind not in "bi":
        raise InvalidValue("inliers", f"expected ({count},) booleans, one per match, got {mask.dtype} {mask.shape}")
    return mask.astype(bool)


def _matrix(value: Any, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != (3, 3):
        raise InvalidValue(name, f"expected a (3, 3) matrix, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    if not np.any(array):
        raise InvalidValue(name, "is all zeros")
    return array


def _pose(value: Any) -> tuple[np.ndarray, np.ndarray]:
    pose = np.asarray(value, dtype=np.float64)
    if pose.shape != (3, 4):
        raise InvalidValue("pose", f"expected a (3, 4) [R | t], got shape {pose.shape}")
    return _rotation_translation(pose[:, :3], pose[:, 3], "pose")


def _rotation_translation(R: Any, t: Any, name: str = "R") -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or t.shape != (3,) or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise InvalidValue(name, f"expected a finite rotation (3, 3) and translation (3,), got {R.shape} and {t.shape}")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InvalidValue(name, "the rotation must be orthonormal with determinant +1")
    return R, t


def _check_collinear(x: np.ndarray, name: str, tolerance: float) -> None:
    """Raise :class:`CollinearPoints` when the RMS distance of ``x`` from its best line is <= ``tolerance``."""
    centred = x - x.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    rms_off_line = singular[1] / np.sqrt(len(x))
    if rms_off_line <= tolerance:
        spread = singular[0] / np.sqrt(len(x))
        raise CollinearPoints(name, f"all {len(x)} points lie on one line (RMS distance from it {rms_off_line:.3g} px, "
                                    f"spread along it {spread:.3g} px): the epipolar geometry is not determined; "
                                    "match points spread over the image")


# ----------------------------------------------------------------------------------------------------
# The math (batched, plain arrays): what the lesson covers
# ----------------------------------------------------------------------------------------------------
def enforce_rank2(F: np.ndarray) -> np.ndarray:
    """The rank-2 matrix nearest in Frobenius norm: zero the smallest singular value, ``(..., 3, 3)``.

    Every fundamental matrix is singular (its null vectors are the epipoles); the linear solution
    of the 8-point algorithm is not, and its epipolar lines would not meet in one point.
    Reference: H&Z section 11.1.1 (the singularity constraint).
    """
    U, singular, Vt = np.linalg.svd(np.asarray(F, dtype=np.float64))
    singular = singular.copy()
    singular[..., 2] = 0.0
    return (U * singular[..., None, :]) @ Vt


def _null_vector(A: np.ndarray) -> np.ndarray:
    """Unit vector ``f`` minimizing ``|A f|`` for each ``(..., N, 9)`` system: its (least-squares) null vector.

    With at most 8 rows (a minimal sample) it is exact: the last column of the complete QR
    factorization of ``A^T`` is orthogonal to every row (4x faster than an SVD, which matters inside
    RANSAC). With more rows, the right singular vector of the smallest singular value, after a QR
    reduction of ``A`` to 9 x 9 (same singular values, without squaring the condition number as
    ``A^T A`` would).
    """
    if A.shape[-2] <= 8:
        Q, _ = np.linalg.qr(np.swapaxes(A, -1, -2), mode="complete")
        return Q[..., :, -1]
    if A.shape[-2] > 9:
        A = np.linalg.qr(A, mode="r")
    return np.linalg.svd(A)[2][..., -1, :]


def _design_matrix(n1: np.ndarray, n2: np.ndarray) -> np.ndarray:
    """The rows ``[u2 u1, u2 v1, u2, v2 u1, v2 v1, v2, u1, v1, 1]`` of ``A f = 0``, ``(..., N, 9)``.

    ``x2^T F x1 = 0`` is linear in the entries of F (``f``, row-major): one row per correspondence.
    """
    u1, v1 = n1[..., 0], n1[..., 1]
    u2, v2 = n2[..., 0], n2[..., 1]
    return np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones_like(u1)], axis=-1)


def eight_point(x1: np.ndarray, x2: np.ndarray, *, normalize: bool = True) -> np.ndarray:
    """The 8-point algorithm, batched: ``(..., N, 2)`` pairs -> ``(..., 3, 3)`` rank-2 F, unit norm.

    See :func:`estimate_fundamental_8point` (the step, with input checks). No degeneracy checks
    here: RANSAC calls it on thousands of random samples at once.
    """
    x1 = np.asarray(x1, dtype=np.float64)
    x2 = np.asarray(x2, dtype=np.float64)
    if normalize:
        T1, x1 = hartley_normalization(x1)
        T2, x2 = hartley_normalization(x2)
    f = _null_vector(_design_matrix(x1, x2))  # x2^T F x1 = 0 is linear in F: one row per match
    F = enforce_rank2(f.reshape(f.shape[:-1] + (3, 3)))
    if normalize:
        F = np.swapaxes(T2, -1, -2) @ F @ T1
    return F / np.linalg.norm(F, axis=(-2, -1), keepdims=True)


def _line_terms(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``F x1`` and ``F^T x2`` ``(..., 3, N)`` and the algebraic residuals ``x2^T F x1`` ``(..., N)``.

    One matrix product for all the matrices of a batch (``(B 3, 3) x (3, N)``): RANSAC scores
    hundreds of hypotheses against every match at once.
    """
    F = np.asarray(F, dtype=np.float64)
    h1, h2 = to_homogeneous(x1), to_homogeneous(x2)
    lead = F.shape[:-2]
    Fx1 = (F.reshape(-1, 3) @ h1.T).reshape(lead + (3, len(h1)))  # lines in image 2, a column per point
    Ftx2 = (np.swapaxes(F, -1, -2).reshape(-1, 3) @ h2.T).reshape(lead + (3, len(h2)))  # lines in image 1
    algebraic = np.sum(h2.T * Fx1, axis=-2)
    return Fx1, Ftx2, algebraic


def sampson_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """First-order geometric error of each pair, in pixels.

    ``d = |x2^T F x1| / sqrt((F x1)_1^2 + (F x1)_2^2 + (F^T x2)_1^2 + (F^T x2)_2^2)``:
    the distance in the joint image space ``(x1, y1, x2, y2)`` from the pair to the variety
    ``x2^T F x1 = 0``, linearized (Sampson 1982): about the smallest total move of the two points
    that makes them consistent with F. Batched: ``F`` ``(..., 3, 3)`` against ``x1``, ``x2``
    ``(N, 2)`` gives ``(..., N)``. ``cv2.sampsonDistance(x1, x2, F)`` returns its square.

    Reference: H&Z section 11.4.3, eq. (11.9).
    """
    Fx1, Ftx2, algebraic = _line_terms(F, x1, x2)
    gradient = Fx1[..., 0, :] ** 2 + Fx1[..., 1, :] ** 2 + Ftx2[..., 0, :] ** 2 + Ftx2[..., 1, :] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(algebraic) / np.sqrt(gradient)


def epipolar_distances(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-line distances (px), ``(..., N)`` each: ``x1`` from ``F^T x2``, ``x2`` from ``F x1``."""
    Fx1, Ftx2, algebraic = _line_terms(F, x1, x2)
    algebraic = np.abs(algebraic)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (algebraic / np.hypot(Ftx2[..., 0, :], Ftx2[..., 1, :]),
                algebraic / np.hypot(Fx1[..., 0, :], Fx1[..., 1, :]))


def symmetric_epipolar_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """``sqrt(d(x1, F^T x2)^2 + d(x2, F x1)^2)`` in pixels, ``(..., N)``: both point-to-line distances.

    Reference: H&Z section 11.4.3, eq. (11.10) (whose sum over points is this squared).
    """
    d1, d2 = epipolar_distances(F, x1, x2)
    return np.sqrt(d1 * d1 + d2 * d2)


def epipolar_lines(F: np.ndarray, points: np.ndarray, *, image: Literal[1, 2] = 1) -> np.ndarray:
    """Epipolar lines ``(a, b, c)`` with ``a^2 + b^2 = 1`` (so ``a x + b y + c`` is a signed distance), ``(N, 3)``.

    Points of image 1 give their lines in image 2, ``l2 = F x1``; points of image 2 (``image=2``)
    give lines in image 1, ``l1 = F^T x2``. Corresponds to ``cv2.computeCorrespondEpilines(points,
    image, F)``. Reference: H&Z section 9.2.1 (result 9.5).
    """
    F = _matrix(F, "F")
    h = to_homogeneous(np.asarray(points, dtype=np.float64).reshape(-1, 2))
    lines = h @ (F.T if image == 1 else F)
    norm = np.hypot(lines[:, 0], lines[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        return lines / norm[:, None]


def epipoles(F: np.ndarray) -> np.ndarray:
    """The two epipoles as homogeneous unit vectors, ``(2, 3)``: ``e1`` with ``F e1 = 0``, ``e2`` with ``F^T e2 = 0``.

    ``e1`` is the image of camera 2's centre in image 1 (where every epipolar line of image 1
    meets) and ``e2`` that of camera 1's centre in image 2: the right and left singular vectors of
    F's smallest singular value. The sign makes the last coordinate non-negative; an epipole at
    infinity (a sideways motion) has last coordinate 0 and stays finite this way.
    Reference: H&Z section 9.2.4 (result 9.8).
    """
    U, _, Vt = np.linalg.svd(_matrix(F, "F"))
    pair = np.stack([Vt[2], U[:, 2]])
    return pair * np.where(pair[:, 2:] < 0, -1.0, 1.0)


def essential_candidates(E: np.ndarray) -> np.ndarray:
    """The four ``[R | t]`` of an essential matrix, ``(4, 3, 4)``: ``(R1, t), (R2, t), (R1, -t), (R2, -t)``.

    With ``E = U diag(1, 1, 0) V^T`` (U, V turned into rotations), ``R1 = U W V^T``,
    ``R2 = U W^T V^T``, ``t = u3`` (U's last column), ``W = [[0, 1, 0], [-1, 0, 0], [0, 0, 1]]``.
    ``R1`` and ``R2`` differ by a half turn about the baseline, and ``+-t`` by the sign of the
    translation; only one of the four puts the points in front of both cameras (see
    :func:`recover_pose`). Corresponds to ``cv2.decomposeEssentialMat(E)`` (same W, same order as
    ``cv2.recoverPose`` tries them).

    Reference: H&Z section 9.6.2, result 9.19.
    """
    U, _, Vt = np.linalg.svd(_matrix(E, "E"))
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    R1, R2, t = U @ W @ Vt, U @ W.T @ Vt, U[:, 2]
    return np.stack([np.column_stack([R, s * t]) for s, R in ((1, R1), (1, R2), (-1, R1), (-1, R2))])


def cheirality_counts(candidates: np.ndarray, n1: np.ndarray, n2: np.ndarray) -> np.ndarray:
    """How many normalized pairs each candidate ``[R | t]`` ``(C, 3, 4)`` puts in front of both cameras, ``(C,)``.

    Each pair is triangulated (DLT, :func:`lab.geometry.triangulation.triangulate_dlt`) with
    ``P1 = [I | 0]`` and ``P2 = [R | t]``; a point counts when its depth is positive in both.
    """
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    x = np.stack([n1, n2])
    counts = []
    for candidate in candidates:
        P = np.stack([P1, candidate])
        X = triangulate_dlt(P, x)
        finite = np.all(np.isfinite(X), axis=1)
        depth = point_depths(P, np.where(finite[:, None], X, 0.0))
        counts.append(int(np.sum(finite & (depth[0] > 0) & (depth[1] > 0))))
    return np.array(counts)


# ----------------------------------------------------------------------------------------------------
# Fast kernels for RANSAC's inner loop: the same math as the readable functions above (their tests
# use those as the oracle), without input checks and with fewer NumPy calls per hypothesis
# ----------------------------------------------------------------------------------------------------
def _hartley_fast(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`lab.geometry.homogeneous.hartley_normalization` of ``(..., N, 2)`` without checks or mask.

    Returns the scale ``s`` ``(...)``, the centroid ``c`` ``(..., 2)`` and the moved points
    ``s (x - c)``; ``T = [[s, 0, -s c0], [0, s, -s c1], [0, 0, 1]]`` (:func:`_similarity`).
    Coincident points give an infinite scale (the caller discards non-finite results).
    """
    centroid = np.einsum("...ni->...i", x) / x.shape[-2]  # x.mean(axis=-2), in a third of the time
    centred = x - centroid[..., None, :]
    scale = np.sqrt(2.0) / np.hypot(centred[..., 0], centred[..., 1]).mean(axis=-1)
    return scale, centroid, centred * scale[..., None, None]


def _similarity(scale: np.ndarray, centroid: np.ndarray) -> np.ndarray:
    """``T`` ``(..., 3, 3)`` of :func:`_hartley_fast`'s scale and centroid."""
    T = np.zeros(np.shape(scale) + (3, 3))
    T[..., 0, 0] = T[..., 1, 1] = scale
    T[..., :2, 2] = -scale[..., None] * centroid
    T[..., 2, 2] = 1.0
    return T


def _minimal_fundamentals(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """:func:`eight_point` (normalized) of a batch of samples ``(B, n, 2)``, ``n <= 8``: ``(B, 3, 3)``.

    Same steps (Hartley normalization, the null vector of the 8 x 9 system by a complete QR, rank 2
    by SVD, ``T2^T F T1``, unit norm) with a lean normalization without checks. ``eight_point`` is
    the oracle of its test.
    """
    s1, c1, n1 = _hartley_fast(x1)
    s2, c2, n2 = _hartley_fast(x2)
    f = _null_vector(_design_matrix(n1, n2))
    F = enforce_rank2(f.reshape(f.shape[:-1] + (3, 3)))
    F = np.swapaxes(_similarity(s2, c2), -1, -2) @ F @ _similarity(s1, c1)
    return F / np.linalg.norm(F, axis=(-2, -1), keepdims=True)


def _kernel(func: Any) -> Any:
    """``numba.njit``, cached on disk where the package folder is writable (else compiled once per process)."""
    import numba

    try:
        return numba.njit(cache=True, nogil=True)(func)
    except RuntimeError:  # no writable cache location (a read-only install, a sandbox)
        return numba.njit(nogil=True)(func)


def _pair_normalization_py(x1: np.ndarray, x2: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Hartley's normalization of the pairs ``mask`` selects, ``[s1, c1x, c1y, s2, c2x, c2y]``: each image's
    centroid ``c`` and the scale ``s`` that brings the mean distance from it to sqrt(2)
    (:func:`lab.geometry.homogeneous.hartley_normalization`, one pass per sum, no copies)."""
    count = 0
    c = np.zeros(4)
    for i in range(len(x1)):
        if mask[i]:
            count += 1
            c[0] += x1[i, 0]
            c[1] += x1[i, 1]
            c[2] += x2[i, 0]
            c[3] += x2[i, 1]
    c /= count
    d1 = 0.0
    d2 = 0.0
    for i in range(len(x1)):
        if mask[i]:
            d1 += np.sqrt((x1[i, 0] - c[0]) ** 2 + (x1[i, 1] - c[1]) ** 2)
            d2 += np.sqrt((x2[i, 0] - c[2]) ** 2 + (x2[i, 1] - c[3]) ** 2)
    return np.array([np.sqrt(2.0) / (d1 / count), c[0], c[1], np.sqrt(2.0) / (d2 / count), c[2], c[3]])


_pair_normalization = _kernel(_pair_normalization_py)


def _normal_equations_py(x1: np.ndarray, x2: np.ndarray, mask: np.ndarray,
                         F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 8-point normal equations ``A^T W A`` ``(9, 9)`` of the pairs ``mask`` selects, in Hartley-normalized
    coordinates, and the normalization ``[s1, c1x, c1y, s2, c2x, c2y]``.

    ``W = I`` when ``F`` (normalized coordinates) is all zeros; else each row is divided by its Sampson
    gradient norm under ``F``, ``sqrt((F x1)_1^2 + (F x1)_2^2 + (F^T x2)_1^2 + (F^T x2)_2^2)`` (floored at
    1e-12 of the largest), as :func:`_sampson_weighted_refit` needs. One pass per sum, then ``A^T A``:
    the loop body of :func:`_normal_equations` (compiled by numba); this plain-Python form is the
    oracle its test compares with, and the same arithmetic as ``_hartley_fast`` + ``_design_matrix``.
    """
    normalization = _pair_normalization(x1, x2, mask)
    s1, s2 = normalization[0], normalization[3]
    c = np.array([normalization[1], normalization[2], normalization[4], normalization[5]])
    count = np.count_nonzero(mask)
    weighted = np.any(F != 0.0)
    gradient = np.ones(len(x1))
    if weighted:
        largest = 0.0
        for i in range(len(x1)):
            if mask[i]:
                u1, v1 = (x1[i, 0] - c[0]) * s1, (x1[i, 1] - c[1]) * s1
                u2, v2 = (x2[i, 0] - c[2]) * s2, (x2[i, 1] - c[3]) * s2
                a = F[0, 0] * u1 + F[0, 1] * v1 + F[0, 2]
                b = F[1, 0] * u1 + F[1, 1] * v1 + F[1, 2]
                p = F[0, 0] * u2 + F[1, 0] * v2 + F[2, 0]
                q = F[0, 1] * u2 + F[1, 1] * v2 + F[2, 1]
                gradient[i] = np.sqrt(a * a + b * b + p * p + q * q)
                largest = max(largest, gradient[i])
        floor = 1e-12 * largest
        for i in range(len(x1)):
            gradient[i] = max(gradient[i], floor)
    A = np.empty((count, 9))  # the weighted design matrix of the selected pairs
    r = 0
    for i in range(len(x1)):
        if mask[i]:
            u1, v1 = (x1[i, 0] - c[0]) * s1, (x1[i, 1] - c[1]) * s1
            u2, v2 = (x2[i, 0] - c[2]) * s2, (x2[i, 1] - c[3]) * s2
            w = 1.0 / gradient[i]
            A[r, 0], A[r, 1], A[r, 2] = u2 * u1 * w, u2 * v1 * w, u2 * w
            A[r, 3], A[r, 4], A[r, 5] = v2 * u1 * w, v2 * v1 * w, v2 * w
            A[r, 6], A[r, 7], A[r, 8] = u1 * w, v1 * w, w
            r += 1
    M = A.T @ A  # one BLAS product (compiled too), 5x faster than accumulating 45 sums per pair
    for j in range(9):
        for k in range(j):
            M[j, k] = M[k, j]
    return M, normalization


_normal_equations = _kernel(_normal_equations_py)


def _fit_masked(x1: np.ndarray, x2: np.ndarray, mask: np.ndarray, Fn: np.ndarray | None = None) -> np.ndarray:
    """The normalized 8-point F of the pairs ``mask`` selects (Sampson-weighted under ``Fn`` when given):
    the compiled :func:`_normal_equations`, the eigenvector of the smallest eigenvalue, rank 2,
    ``T2^T F T1``, unit norm. Returns ``(F, Fn, normalization)`` with ``Fn`` the normalized-coordinate F."""
    M, n = _normal_equations(x1, x2, mask, np.zeros((3, 3)) if Fn is None else Fn)
    Fn = enforce_rank2(np.linalg.eigh(M)[1][:, 0].reshape(3, 3))
    F = _similarity(n[3], n[4:]).T @ Fn @ _similarity(n[0], n[1:3])
    return F / np.linalg.norm(F), Fn, n


# Compiled post-processing of RANSAC (local optimization, the Sampson refit, the inlier masks): the same
# math as _Scorer.inliers, _fit_masked, _local_optimization_reference and _sampson_weighted_refit (their
# tests use those as the oracle), as plain loops that numba compiles into one call each, so that an easy
# pair (few samples) does not pay a hundred small NumPy calls per RANSAC. Each ``_x_py`` is the readable body
# and ``_x`` its compiled form; bodies call the compiled helpers, so each helper compiles once (the first
# call of a fresh checkout compiles them all, about 10 s, then numba's on-disk cache serves them).
def _epipolar_terms_py(F: np.ndarray, u1: float, v1: float, u2: float, v2: float) -> tuple[float, float, float]:
    """For one pair: the algebraic residual ``x2^T F x1`` and the squared norms of the first two entries of
    ``F^T x2`` (the line in image 1) and of ``F x1`` (the line in image 2): :func:`_line_terms` of one pair,
    all that the Sampson and the epipolar distances need."""
    a = F[0, 0] * u1 + F[0, 1] * v1 + F[0, 2]  # F x1: the line in image 2
    b = F[1, 0] * u1 + F[1, 1] * v1 + F[1, 2]
    c = F[2, 0] * u1 + F[2, 1] * v1 + F[2, 2]
    p = F[0, 0] * u2 + F[1, 0] * v2 + F[2, 0]  # F^T x2: the line in image 1
    q = F[0, 1] * u2 + F[1, 1] * v2 + F[2, 1]
    return u2 * a + v2 * b + c, p * p + q * q, a * a + b * b


_epipolar_terms = _kernel(_epipolar_terms_py)


def _inliers_py(x1: np.ndarray, x2: np.ndarray, F: np.ndarray, t2: float, sampson: bool) -> np.ndarray:
    """:meth:`_Scorer.inliers` as one loop: the pairs ``(M, 2)`` whose error under ``F`` is within ``sqrt(t2)``."""
    mask = np.empty(len(x1), dtype=np.bool_)
    for i in range(len(x1)):
        residual, norm1, norm2 = _epipolar_terms(F, x1[i, 0], x1[i, 1], x2[i, 0], x2[i, 1])
        scale = norm1 + norm2 if sampson else min(norm1, norm2)
        mask[i] = residual * residual <= t2 * scale
    return mask


_inliers = _kernel(_inliers_py)


def _count_inliers_py(x1: np.ndarray, x2: np.ndarray, F: np.ndarray, t2: float, sampson: bool) -> np.ndarray:
    """:meth:`_Scorer.counts` as one loop: the inliers of each of ``F`` ``(B, 3, 3)``, ``(B,)``; -1 for an F
    with a non-finite entry (a degenerate sample). RANSAC's inner loop: no ``(M, B)`` temporaries, 5-10x
    faster than the three matrix products of the NumPy form on 256 hypotheses."""
    out = np.empty(len(F), dtype=np.int64)
    for h in range(len(F)):
        f = F[h]
        if not np.all(np.isfinite(f)):
            out[h] = -1
            continue
        inside = 0
        for i in range(len(x1)):
            residual, norm1, norm2 = _epipolar_terms(f, x1[i, 0], x1[i, 1], x2[i, 0], x2[i, 1])
            scale = norm1 + norm2 if sampson else min(norm1, norm2)
            if residual * residual <= t2 * scale:
                inside += 1
        out[h] = inside
    return out


_count_inliers = _kernel(_count_inliers_py)


def _sampson_distances_py(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """:func:`sampson_distance` of one ``F`` ``(3, 3)`` as one loop, ``(M,)``."""
    out = np.empty(len(x1))
    for i in range(len(x1)):
        algebraic, norm1, norm2 = _epipolar_terms(F, x1[i, 0], x1[i, 1], x2[i, 0], x2[i, 1])
        gradient = np.sqrt(norm2 + norm1)
        residual = abs(algebraic)
        if gradient > 0.0:
            out[i] = residual / gradient
        else:  # as NumPy divides: r / 0 = inf, 0 / 0 and nan = nan
            out[i] = np.inf if gradient == 0.0 and residual > 0.0 else np.nan
    return out


_sampson_distances = _kernel(_sampson_distances_py)


def _transform_fundamental_py(F: np.ndarray, a1: float, b1: np.ndarray, a2: float, b2: np.ndarray) -> np.ndarray:
    """``T2^T F T1`` for ``T = [[a, 0, b0], [0, a, b1], [0, 0, 1]]`` (a similarity; written out, no products)."""
    G = np.empty((3, 3))
    for i in range(3):  # F T1
        G[i, 0], G[i, 1] = F[i, 0] * a1, F[i, 1] * a1
        G[i, 2] = F[i, 0] * b1[0] + F[i, 1] * b1[1] + F[i, 2]
    out = np.empty((3, 3))
    for j in range(3):  # T2^T (F T1)
        out[0, j], out[1, j] = a2 * G[0, j], a2 * G[1, j]
        out[2, j] = b2[0] * G[0, j] + b2[1] * G[1, j] + G[2, j]
    return out


_transform_fundamental = _kernel(_transform_fundamental_py)


def _rank2_py(F: np.ndarray) -> np.ndarray:
    """:func:`enforce_rank2` of one ``(3, 3)``: the SVD without its smallest singular value."""
    U, singular, Vt = np.linalg.svd(F)
    rank2 = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            rank2[i, j] = U[i, 0] * singular[0] * Vt[0, j] + U[i, 1] * singular[1] * Vt[1, j]
    return rank2


_rank2 = _kernel(_rank2_py)


def _minimal_fundamentals_py(x1: np.ndarray, x2: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """:func:`_minimal_fundamentals` of the samples ``(B, 8)`` (indices into ``x1``, ``x2`` ``(M, 2)``) as one
    compiled call: ``(B, 3, 3)``. The same steps per sample: Hartley normalization, the 8 x 9 system, its
    null vector as the last column of the complete QR factorization of ``A^T`` (Householder reflections as
    LAPACK's ``geqrf`` + ``orgqr``: ``Q e9 = H1 H2 ... H8 e9``), rank 2, ``T2^T F T1``, unit norm."""
    count, size = samples.shape
    out = np.empty((count, 3, 3))
    At = np.empty((9, size))  # A^T: a column per pair
    for h in range(count):
        c1x = c1y = c2x = c2y = 0.0
        for k in range(size):
            i = samples[h, k]
            c1x += x1[i, 0]
            c1y += x1[i, 1]
            c2x += x2[i, 0]
            c2y += x2[i, 1]
        c1x, c1y, c2x, c2y = c1x / size, c1y / size, c2x / size, c2y / size
        d1 = d2 = 0.0
        for k in range(size):
            i = samples[h, k]
            d1 += np.hypot(x1[i, 0] - c1x, x1[i, 1] - c1y)
            d2 += np.hypot(x2[i, 0] - c2x, x2[i, 1] - c2y)
        if not (d1 > 0.0 and d2 > 0.0):  # coincident points: no normalization, no F (scored -1)
            out[h] = np.nan
            continue
        s1, s2 = np.sqrt(2.0) / (d1 / size), np.sqrt(2.0) / (d2 / size)
        for k in range(size):
            i = samples[h, k]
            u1, v1 = (x1[i, 0] - c1x) * s1, (x1[i, 1] - c1y) * s1
            u2, v2 = (x2[i, 0] - c2x) * s2, (x2[i, 1] - c2y) * s2
            At[0, k], At[1, k], At[2, k] = u2 * u1, u2 * v1, u2
            At[3, k], At[4, k], At[5, k] = v2 * u1, v2 * v1, v2
            At[6, k], At[7, k], At[8, k] = u1, v1, 1.0
        taus = np.zeros(size)
        for k in range(size):  # Householder QR of A^T (9 x size), reflectors stored below the diagonal
            norm = 0.0
            for r in range(k, 9):
                norm += At[r, k] * At[r, k]
            norm = np.sqrt(norm)
            if norm == 0.0:
                continue
            alpha = At[k, k]
            beta = -norm if alpha >= 0.0 else norm
            taus[k] = (beta - alpha) / beta
            scale = 1.0 / (alpha - beta)
            for r in range(k + 1, 9):
                At[r, k] *= scale
            At[k, k] = beta
            for j in range(k + 1, size):  # apply H_k = I - tau w w^T (w = [1, At[k+1:, k]]) to the rest
                dot = At[k, j]
                for r in range(k + 1, 9):
                    dot += At[r, k] * At[r, j]
                dot *= taus[k]
                At[k, j] -= dot
                for r in range(k + 1, 9):
                    At[r, j] -= dot * At[r, k]
        f = np.zeros(9)  # Q e9, the null vector
        f[8] = 1.0
        for k in range(size - 1, -1, -1):
            dot = f[k]
            for r in range(k + 1, 9):
                dot += At[r, k] * f[r]
            dot *= taus[k]
            f[k] -= dot
            for r in range(k + 1, 9):
                f[r] -= dot * At[r, k]
        Fn = np.empty((3, 3))
        for k in range(9):
            Fn[k // 3, k % 3] = f[k]
        F = _transform_fundamental(_rank2(Fn), s1, np.array([-s1 * c1x, -s1 * c1y]), s2,
                                   np.array([-s2 * c2x, -s2 * c2y]))
        out[h] = F / np.sqrt(np.sum(F * F))
    return out


_minimal_fundamentals_compiled = _kernel(_minimal_fundamentals_py)


def _refit_py(x1: np.ndarray, x2: np.ndarray, mask: np.ndarray,
              Fn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_fit_masked` as one compiled call: the normalized 8-point F of the pairs ``mask`` selects
    (Sampson-weighted under the normalized-coordinate ``Fn`` unless it is all zeros). Returns ``(F, Fn,
    normalization)``: F unit norm in pixels, the rank-2 ``Fn`` and ``[s1, c1x, c1y, s2, c2x, c2y]``."""
    M, n = _normal_equations(x1, x2, mask, Fn)
    vectors = np.linalg.eigh(M)[1]  # the eigenvector of the smallest eigenvalue: least-squares null vector
    solution = np.empty((3, 3))
    for k in range(9):
        solution[k // 3, k % 3] = vectors[k, 0]
    rank2 = _rank2(solution)
    shift1 = np.array([-n[0] * n[1], -n[0] * n[2]])
    shift2 = np.array([-n[3] * n[4], -n[3] * n[5]])
    F = _transform_fundamental(rank2, n[0], shift1, n[3], shift2)
    return F / np.sqrt(np.sum(F * F)), rank2, n


_refit = _kernel(_refit_py)


def _local_optimization_py(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, t2: float,
                           sampson: bool) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_local_optimization_reference` as one compiled call (``t2``: squared threshold; ``sampson``: the
    error): refit on all the inliers while that gains inliers, at most 4 times. Returns ``(F, inliers)``."""
    inliers = _inliers(x1, x2, F, t2, sampson)
    unweighted = np.zeros((3, 3))
    for _ in range(4):
        count = np.sum(inliers)
        if count < SAMPLE_SIZE:
            break
        refit = _refit(x1, x2, inliers, unweighted)[0]
        more = _inliers(x1, x2, refit, t2, sampson)
        if np.sum(more) < count:
            break
        done = np.all(more == inliers)
        F, inliers = refit, more
        if done:
            break
    return F, inliers


_local_optimization = _kernel(_local_optimization_py)


def _sampson_refit_py(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, mask: np.ndarray,
                      iterations: int) -> np.ndarray:
    """:func:`_sampson_weighted_refit` of the pairs ``mask`` selects (no copies) as one compiled call."""
    n = _pair_normalization(x1, x2, mask)
    Fn = _transform_fundamental(F, 1.0 / n[0], n[1:3].copy(), 1.0 / n[3], n[4:6].copy())  # T2^-T F T1^-1
    if not np.any(Fn != 0.0):
        return F
    for _ in range(iterations):  # the weights of each solve come from the previous F
        F, Fn, _ = _refit(x1, x2, mask, Fn)
    return F


_sampson_refit = _kernel(_sampson_refit_py)


def _distance_from_best_line_py(x: np.ndarray, mask: np.ndarray) -> float:
    """RMS distance (px) of the points ``x[mask]`` ``(N, 2)`` from their best line, without copying them:
    the square root of the smaller eigenvalue of their 2 x 2 covariance, in closed form. The same number as
    :func:`_check_collinear`'s ``singular[1] / sqrt(N)``, to ~1e-16 of the largest over the smallest spread
    (plenty to screen against a threshold of 0.01 px or more)."""
    count = 0
    cx = 0.0
    cy = 0.0
    for i in range(len(x)):
        if mask[i]:
            count += 1
            cx += x[i, 0]
            cy += x[i, 1]
    cx /= count
    cy /= count
    sxx = 0.0
    syy = 0.0
    sxy = 0.0
    for i in range(len(x)):
        if mask[i]:
            dx, dy = x[i, 0] - cx, x[i, 1] - cy
            sxx += dx * dx
            syy += dy * dy
            sxy += dx * dy
    half_trace = 0.5 * (sxx + syy) / count
    radius = np.sqrt((0.5 * (sxx - syy) / count) ** 2 + (sxy / count) ** 2)
    return np.sqrt(max(half_trace - radius, 0.0))


_distance_from_best_line = _kernel(_distance_from_best_line_py)


# ----------------------------------------------------------------------------------------------------
# 1. Features
# ----------------------------------------------------------------------------------------------------
@step_result
class FeatureDetection:
    """Result of :func:`detect_features`."""

    keypoints: Points2D
    descriptors: np.ndarray
    warnings: Warnings
    keypoints_image1: int = metric("keypoints found in image 1")
    keypoints_image2: int = metric("keypoints found in image 2")


def _two_images(images: Any) -> ImageSet:
    if not isinstance(images, ImageSet) or len(images) != 2:
        count = len(images) if isinstance(images, ImageSet) else type(images).__name__
        raise InvalidValue("images", f"epipolar geometry needs exactly two images, got {count}")
    return images


def detect_features(images: ImageSet, *, max_features: Annotated[int, Range(0, 50000)] = 4000,
                    contrast_threshold: Annotated[float, Range(0.001, 0.5)] = 0.04) -> FeatureDetection:
    """SIFT keypoints and descriptors in both images (OpenCV's ``cv2.SIFT_create``).

    Keypoints are extrema of the difference-of-Gaussians scale space, kept where their contrast
    exceeds ``contrast_threshold`` and away from edges; each gets a 128-D histogram of gradient
    orientations around it, rotated to its dominant orientation and scaled to its scale, so it
    can be matched across viewpoints. Run on the 8-bit grayscale image. OpenCV's coordinates are
    moved by ``-SIFT_OFFSET_PX`` in x and y, to undo its quarter-pixel bias (:data:`SIFT_OFFSET_PX`):
    a blob centred on pixel (x, y) is reported at (x, y).

    Args:
        max_features: keep the strongest this many keypoints per image (0: all).
        contrast_threshold: reject weak extrema (OpenCV's contrastThreshold; lower finds more).

    Returns ``keypoints`` (Points2D, ``view`` 0 for image 1 then 1 for image 2) and
    ``descriptors`` ``(N, 128)`` float32 in the same order.

    Reference: D. Lowe, IJCV 60(2), 2004, sections 3-6.
    """
    import cv2

    images = _two_images(images)
    sift = cv2.SIFT_create(nfeatures=int(max_features), contrastThreshold=float(contrast_threshold))
    xy, view, descriptors, warnings, counts = [], [], [], [], []
    for index, image in enumerate(images.images):
        gray8 = np.clip(image.gray() * 255.0 + 0.5, 0, 255).astype(np.uint8)
        found, described = sift.detectAndCompute(gray8, None)
        points = np.array([k.pt for k in found], dtype=np.float64).reshape(-1, 2) - SIFT_OFFSET_PX
        described = np.zeros((0, 128), np.float32) if described is None else described.astype(np.float32)
        xy.append(points)
        view.append(np.full(len(points), index))
        descriptors.append(described)
        counts.append(len(points))
        if len(points) < SAMPLE_SIZE:
            warnings.append(f"{images.names[index]}: only {len(points)} keypoints; lower the contrast threshold")
    keypoints = Points2D(np.concatenate(xy), view=np.concatenate(view), image="images")
    return FeatureDetection(keypoints, np.concatenate(descriptors), tuple(warnings), counts[0], counts[1])


# ----------------------------------------------------------------------------------------------------
# 2. Matching
# ----------------------------------------------------------------------------------------------------
@step_result
class Matching:
    """Result of :func:`match_features`."""

    matches: np.ndarray
    x1: np.ndarray
    x2: np.ndarray
    warnings: Warnings
    num_matches: int = metric("matches kept")
    rejected_by_ratio: int = metric("nearest neighbours rejected by the ratio test")
    rejected_by_mutual: int = metric("nearest neighbours rejected by the mutual check")


def nearest_neighbours_reference(query: np.ndarray, train: np.ndarray, *,
                                 chunk: int = 1024) -> tuple[np.ndarray, ...]:
    """Brute-force Euclidean nearest neighbours, all in float64: the readable oracle of :func:`nearest_neighbours`.

    For each query row the two nearest train rows and, for each train row, its nearest query row.
    Returns ``first`` ``(Q,)`` index, ``d1`` ``(Q,)`` and ``d2`` ``(Q,)`` (distances to the nearest
    and second nearest; ``inf`` when ``train`` has one row) and ``back`` ``(T,)`` the nearest query
    of each train row. Distances come from ``|a|^2 + |b|^2 - 2 a.b`` in float64, ``chunk`` query
    rows at a time. Corresponds to ``cv2.BFMatcher(cv2.NORM_L2).knnMatch(query, train, k=2)`` and
    ``.match(train, query)``.
    """
    q = np.asarray(query, dtype=np.float64)
    t = np.asarray(train, dtype=np.float64)
    tt = np.sum(t * t, axis=1)
    first = np.zeros(len(q), dtype=np.int64)
    d1 = np.full(len(q), np.inf)
    d2 = np.full(len(q), np.inf)
    back_distance = np.full(len(t), np.inf)
    back = np.zeros(len(t), dtype=np.int64)
    for start in range(0, len(q), chunk):
        block = q[start:start + chunk]
        squared = np.maximum(np.sum(block * block, axis=1)[:, None] + tt[None, :] - 2.0 * block @ t.T, 0.0)
        rows = np.arange(len(block))
        if len(t) >= 2:
            two = np.argpartition(squared, 1, axis=1)[:, :2]
            pair = squared[rows[:, None], two]
            order = np.argsort(pair, axis=1)
            first[start:start + len(block)] = two[rows, order[:, 0]]
            d1[start:start + len(block)] = np.sqrt(pair[rows, order[:, 0]])
            d2[start:start + len(block)] = np.sqrt(pair[rows, order[:, 1]])
        elif len(t) == 1:
            d1[start:start + len(block)] = np.sqrt(squared[:, 0])
        column_best = np.argmin(squared, axis=0)
        column_distance = np.sqrt(squared[column_best, np.arange(len(t))])
        better = column_distance < back_distance
        back[better] = start + column_best[better]
        back_distance[better] = column_distance[better]
    return first, d1, d2, back


def _two_nearest_scan_py(dots: np.ndarray, qq: np.ndarray, tt: np.ndarray, start: int, slack: float,
                         first: np.ndarray, second: np.ndarray, unsure: np.ndarray, column_best: np.ndarray,
                         column_index: np.ndarray, column_second: np.ndarray) -> None:
    """One pass over a block of float32 dot products ``dots`` ``(B, T)`` (query rows ``start ...``): the two
    nearest train rows of each query and the two nearest queries of each train row, by the squared distances
    ``qq + tt - 2 dots`` (``qq`` ``(B,)``, ``tt`` ``(T,)`` float64).

    Writes ``first``, ``second`` ``(B,)`` (train indices, lowest index first on equal values) and ``unsure``
    ``(B,)``: True when the third nearest train row comes within ``2 slack`` of the second or the two nearest
    are within ``2 slack`` of each other (``slack`` bounds the error of a float32 distance, so only then can
    the float64 order differ). Updates ``column_best``, ``column_index``, ``column_second`` ``(T,)`` (the
    smallest and second smallest squared distance of each train row over the queries seen so far, the
    index of the smallest, earliest query on equal values). The loop body of :func:`_two_nearest_scan`
    (compiled by numba); this plain-Python form is the oracle its test compares with.
    """
    rows, columns = dots.shape
    for i in range(rows):
        best = np.inf
        runner = np.inf
        third = np.inf
        j1 = 0
        j2 = 0
        for j in range(columns):
            s = qq[i] + tt[j] - 2.0 * dots[i, j]
            if s < third:
                if s < best:
                    third, runner, j2 = runner, best, j1
                    best, j1 = s, j
                elif s < runner:
                    third, runner, j2 = runner, s, j
                else:
                    third = s
            if s < column_second[j]:
                if s < column_best[j]:
                    column_second[j] = column_best[j]
                    column_best[j] = s
                    column_index[j] = start + i
                else:
                    column_second[j] = s
        first[i], second[i] = j1, j2
        unsure[i] = third - runner <= 2.0 * slack or runner - best <= 2.0 * slack


_two_nearest_scan = _kernel(_two_nearest_scan_py)


def _squared_distances64(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``|q_i - t_j|^2`` ``(Q, T)`` as ``|q|^2 + |t|^2 - 2 q.t`` in float64, clipped at 0 (the reference's formula)."""
    return np.maximum(np.sum(q * q, axis=1)[:, None] + np.sum(t * t, axis=1)[None, :] - 2.0 * q @ t.T, 0.0)


def nearest_neighbours(query: np.ndarray, train: np.ndarray, *, chunk: int = 1024) -> tuple[np.ndarray, ...]:
    """Brute-force Euclidean nearest neighbours: for each query row the two nearest train rows and, for each
    train row, its nearest query row; the float64 answer of :func:`nearest_neighbours_reference`, faster.

    Returns ``first`` ``(Q,)`` index, ``d1`` ``(Q,)`` and ``d2`` ``(Q,)`` (distances to the nearest
    and second nearest; ``inf`` when ``train`` has one row) and ``back`` ``(T,)`` the nearest query
    of each train row. Corresponds to ``cv2.BFMatcher(cv2.NORM_L2).knnMatch(query, train, k=2)`` and
    ``.match(train, query)``.

    How: the dot products ``q.t`` come from one float32 matrix product per block of ``chunk`` queries
    (BLAS sgemm, twice the speed of float64 and half the memory), and one compiled pass over the block
    (:func:`_two_nearest_scan`) finds the two nearest of every row and column from ``|q|^2 + |t|^2 - 2 q.t``.
    A float32 dot product of d-vectors is off by at most ``gamma = (d + 4) u |q| |t|`` (``u = 2^-24``: d
    roundings of the sum, one of each input; Higham, Accuracy and Stability of Numerical Algorithms, 2nd
    ed., section 3.1), so each squared distance by at most ``slack = 2 gamma + 1e-15 (|q|^2 + |t|^2)``.
    Only where two candidates lie within ``2 slack`` of each other can the order differ from the float64
    one: those rows and columns are decided again in float64. Last, ``d1`` and ``d2`` of the chosen pairs
    are computed in float64, so the ratio test compares the same numbers as the reference. The answer is
    the reference's wherever float64 itself separates the candidates (exact ties: lowest index first).
    """
    q = np.asarray(query, dtype=np.float64)
    t = np.asarray(train, dtype=np.float64)
    if len(t) < 2 or len(q) == 0:
        return nearest_neighbours_reference(q, t, chunk=chunk)
    q32, t32 = q.astype(np.float32), t.astype(np.float32)
    qq, tt = np.einsum("ij,ij->i", q, q), np.einsum("ij,ij->i", t, t)
    gamma = (q.shape[1] + 4) * 2.0 ** -24 * np.sqrt(qq.max() * tt.max())
    slack = 2.0 * gamma + 1e-15 * (qq.max() + tt.max())
    first = np.empty(len(q), dtype=np.int64)
    second = np.empty(len(q), dtype=np.int64)
    unsure = np.empty(len(q), dtype=bool)
    column_best = np.full(len(t), np.inf)
    column_second = np.full(len(t), np.inf)
    back = np.zeros(len(t), dtype=np.int64)
    for start in range(0, len(q), chunk):
        stop = min(start + chunk, len(q))
        _two_nearest_scan(q32[start:stop] @ t32.T, qq[start:stop], tt, start, slack, first[start:stop],
                          second[start:stop], unsure[start:stop], column_best, back, column_second)
    rows = np.flatnonzero(unsure)  # float32 cannot order their candidates: decide them in float64
    for begin in range(0, len(rows), chunk):
        these = rows[begin:begin + chunk]
        exact = _squared_distances64(q[these], t)
        first[these] = np.argmin(exact, axis=1)  # the first of equal values: lowest index
        exact[np.arange(len(these)), first[these]] = np.inf
        second[these] = np.argmin(exact, axis=1)
    columns = np.flatnonzero(column_second - column_best <= 2.0 * slack)  # the same for the back matches
    for begin in range(0, len(columns), chunk):
        these = columns[begin:begin + chunk]
        back[these] = np.argmin(_squared_distances64(q, t[these]), axis=0)  # earliest query on equal values
    d1 = np.sqrt(np.maximum(qq + tt[first] - 2.0 * np.einsum("ij,ij->i", q, t[first]), 0.0))
    d2 = np.sqrt(np.maximum(qq + tt[second] - 2.0 * np.einsum("ij,ij->i", q, t[second]), 0.0))
    return first, d1, d2, back


def match_features(keypoints: Points2D, descriptors: np.ndarray, *, ratio: Annotated[float, Range(0.05, 1.0)] = 0.8,
                   mutual: bool = True) -> Matching:
    """Match descriptors of image 1 to image 2: nearest neighbour, Lowe's ratio test, mutual check.

    Each descriptor of image 1 takes its nearest neighbour among those of image 2 (Euclidean). The
    ratio test keeps it only if the nearest is clearly nearer than the second nearest,
    ``d1 < ratio * d2``: a distinctive match (Lowe found that 0.8 rejects 90 % of the wrong
    matches and 5 % of the right ones). The mutual check keeps it only if the descriptor of image
    1 is also the nearest neighbour of its match (a cross check). Written here with NumPy
    (:func:`nearest_neighbours`: float32 distances, re-checked in float64 where float32 cannot decide,
    so the float64 answer of :func:`nearest_neighbours_reference`, several times faster); OpenCV does
    the same with ``cv2.BFMatcher(cv2.NORM_L2)``:
    ``knnMatch(d1, d2, k=2)`` for the ratio test and ``crossCheck=True`` for the mutual check.

    Args:
        ratio: largest allowed ratio of nearest to second-nearest distance (1: no ratio test).
        mutual: keep only matches that are each other's nearest neighbour.

    Returns ``matches`` ``(M, 2)`` (indices into ``keypoints``: image 1, image 2), sorted by
    the image-1 keypoint, and the matched pixels ``x1``, ``x2`` ``(M, 2)``.

    Reference: D. Lowe, IJCV 60(2), 2004, section 7.1.
    """
    if not isinstance(keypoints, Points2D) or keypoints.view is None:
        raise InvalidValue("keypoints", "expected Points2D with a view (0 or 1) per keypoint")
    descriptors = np.asarray(descriptors)
    if descriptors.ndim != 2 or len(descriptors) != len(keypoints):
        raise InvalidValue("descriptors", f"expected one row per keypoint ({len(keypoints)}), got shape "
                                          f"{descriptors.shape}")
    if descriptors.dtype.kind == "f" and not np.all(np.isfinite(descriptors)):
        raise InvalidValue("descriptors", "contains NaN or infinite entries")
    index1 = np.flatnonzero(keypoints.view == 0)
    index2 = np.flatnonzero(keypoints.view == 1)
    warnings: list[str] = []
    if len(index1) == 0 or len(index2) == 0:
        empty = np.zeros((0, 2))
        return Matching(np.zeros((0, 2), dtype=np.int64), empty, empty.copy(),
                        ("no keypoints in one of the images: nothing to match",), 0, 0, 0)
    first, d1, d2, back = nearest_neighbours(descriptors[index1], descriptors[index2])
    passes_ratio = d1 < ratio * d2 if ratio < 1.0 else np.ones(len(index1), dtype=bool)
    is_mutual = back[first] == np.arange(len(index1))
    keep = passes_ratio & (is_mutual if mutual else True)
    matches = np.column_stack([index1[keep], index2[first[keep]]]).astype(np.int64)
    if len(matches) < SAMPLE_SIZE:
        warnings.append(f"only {len(matches)} matches: F needs at least {SAMPLE_SIZE}; raise the ratio or detect "
                        "more features")
    return Matching(matches, keypoints.xy[matches[:, 0]], keypoints.xy[matches[:, 1]], tuple(warnings),
                    len(matches), int(np.sum(~passes_ratio)), int(np.sum(passes_ratio & ~is_mutual)) if mutual else 0)


# ----------------------------------------------------------------------------------------------------
# 3. The 8-point algorithm (a lesson step)
# ----------------------------------------------------------------------------------------------------
def estimate_fundamental_8point(x1: np.ndarray, x2: np.ndarray, *,
                                normalize: bool = True) -> Annotated[np.ndarray, "F"]:
    """The fundamental matrix of all matches by the (normalized) 8-point algorithm, rank 2 enforced.

    Each match gives one linear equation ``x2^T F x1 = 0`` in the nine entries of F::

        [u2 u1, u2 v1, u2, v2 u1, v2 v1, v2, u1, v1, 1] . f = 0

    ``f`` is the right singular vector of the stacked ``A`` with the smallest singular value (the
    least-squares solution with ``|f| = 1``); F is then made singular (:func:`enforce_rank2`).
    With ``normalize`` both point sets are first moved to their centroid and scaled to mean
    distance sqrt(2) (``T1``, ``T2``, :func:`lab.geometry.homogeneous.hartley_normalization`) and
    ``F = T2^T F_n T1``: in pixels the columns of ``A`` differ by ~10^5 in scale, ``A`` is badly
    conditioned and the solution is poor (Hartley 1997); normalized, it is as good as iterative
    methods on clean data. Every match counts: on real matches the outliers spoil it (RANSAC next).

    Args:
        normalize: apply Hartley's normalization before solving (off: to see why it matters).

    Returns F ``(3, 3)``, rank 2, unit Frobenius norm. Corresponds to
    ``cv2.findFundamentalMat(x1, x2, cv2.FM_8POINT)`` (which always normalizes and scales
    ``F[2, 2] = 1``).

    Reference: H&Z section 11.1 and algorithm 11.1; R. Hartley, TPAMI 19(6), 1997.
    """
    x1, x2 = _pair(x1, x2)
    for name, x in (("x1", x1), ("x2", x2)):
        _check_collinear(x, name, 1e-9 * (1.0 + np.abs(x).max()))
    singular = np.linalg.svd(_design_matrix(hartley_normalization(x1)[1], hartley_normalization(x2)[1]),
                             compute_uv=False)
    if singular[7] <= 1e-9 * singular[0]:
        if _is_rotation_homography(x1, x2):
            raise ZeroBaseline("x1", "the matches give fewer than 8 independent equations, so F is not unique, and one "
                                     "homography that is (close to) a rotation maps image 1 onto image 2: the two "
                                     "cameras share their centre (zero baseline); move the camera between the photos")
        raise CoplanarPoints("x1", "the matches give fewer than 8 independent equations, so F is not unique: the "
                                   "points lie on one plane (or the two cameras share a centre); use a scene with "
                                   "depth and move the camera")
    return eight_point(x1, x2, normalize=normalize)


# ----------------------------------------------------------------------------------------------------
# 4. RANSAC
# ----------------------------------------------------------------------------------------------------
@step_result
class RansacFundamental:
    """Result of :func:`estimate_fundamental_ransac`."""

    F: np.ndarray
    inliers: np.ndarray
    ransac_trace: Curve
    num_inliers: int = metric("matches consistent with F")
    inlier_ratio: float = metric("fraction of the matches that are inliers")
    iterations: int = metric("hypotheses drawn (the adaptive N)")
    sampson_rms_px: float = metric("RMS Sampson distance of the inliers", unit="px")
    rank_of_F: int = metric("numerical rank of F (2 for a fundamental matrix)")


class _Scorer:
    """Counts the inliers of many F at once, without forming the distances (RANSAC's inner loop, in NumPy:
    the readable oracle of the compiled :func:`_count_inliers` and :func:`_inliers` that RANSAC calls).

    Everything the errors need is linear in F: ``x2^T F x1 = A f`` (A: :func:`_design_matrix` of all
    matches) and the first two entries of ``F x1`` and ``F^T x2``. So a batch of B hypotheses
    costs three matrix products of ``(M, 9 or 3)`` by ``(., B)``, and the test ``error <= t`` is
    compared squared: Sampson ``r^2 <= t^2 (|Fx1|^2 + |F^T x2|^2)`` (first two entries), epipolar
    ``r^2 <= t^2 min(|Fx1|^2, |F^T x2|^2)``.
    """

    def __init__(self, x1: np.ndarray, x2: np.ndarray, error: str, threshold_px: float) -> None:
        self.A = _design_matrix(x1, x2)
        self.h1, self.h2 = to_homogeneous(x1), to_homogeneous(x2)
        self.error = error
        self.t2 = float(threshold_px) ** 2

    def counts(self, F: np.ndarray) -> np.ndarray:
        """Inliers of each of ``F`` ``(B, 3, 3)``, ``(B,)``."""
        B = len(F)
        residual = self.A @ F.reshape(B, 9).T  # (M, B)
        lines2 = self.h1 @ F[:, :2, :].reshape(2 * B, 3).T  # (M, 2B): (F x1)_1, (F x1)_2 per hypothesis
        lines1 = self.h2 @ np.swapaxes(F[:, :, :2], 1, 2).reshape(2 * B, 3).T  # (F^T x2)_1, (F^T x2)_2
        norm2 = lines2[:, 0::2] ** 2 + lines2[:, 1::2] ** 2
        norm1 = lines1[:, 0::2] ** 2 + lines1[:, 1::2] ** 2
        scale = norm1 + norm2 if self.error == "sampson" else np.minimum(norm1, norm2)
        return np.count_nonzero(residual * residual <= self.t2 * scale, axis=0)

    def inliers(self, F: np.ndarray) -> np.ndarray:
        """The inlier mask ``(M,)`` of one F ``(3, 3)``."""
        residual = self.A @ F.reshape(9)
        lines2, lines1 = self.h1 @ F[:2].T, self.h2 @ F[:, :2]
        norm2 = lines2[:, 0] ** 2 + lines2[:, 1] ** 2
        norm1 = lines1[:, 0] ** 2 + lines1[:, 1] ** 2
        scale = norm1 + norm2 if self.error == "sampson" else np.minimum(norm1, norm2)
        return residual * residual <= self.t2 * scale


def _local_optimization_reference(F: np.ndarray, x1: np.ndarray, x2: np.ndarray,
                                  scorer: _Scorer) -> tuple[np.ndarray, np.ndarray]:
    """Refit F by the 8-point algorithm on all its inliers, again while that gains inliers (at most 4 times).

    A minimal sample's F is spoiled by the noise of its 8 points and misses inliers; the refit on
    all of them is close to the best F, so its inlier ratio sets a realistic adaptive N.
    Reference: O. Chum, J. Matas and J. Kittler, "Locally optimized RANSAC", DAGM 2003. The readable oracle
    of the compiled :func:`_local_optimization` that RANSAC calls.
    """
    inliers = scorer.inliers(F)
    for _ in range(4):
        if inliers.sum() < SAMPLE_SIZE:
            break
        refit = _fit_masked(x1, x2, inliers)[0]
        more = scorer.inliers(refit)
        if more.sum() < inliers.sum():
            break
        F, done = refit, np.array_equal(more, inliers)
        inliers = more
        if done:
            break
    return F, inliers


def _sampson_weighted_refit(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Iteratively reweighted 8-point: weight each equation by the inverse of its Sampson gradient norm.

    ``x2^T F x1 / |grad|`` is the Sampson distance, so solving the 8-point system with row weights
    ``1 / |grad(F_prev)|`` minimizes the sum of squared Sampson distances with the weights frozen at
    the previous F; repeated, it settles close to the minimum of the Sampson error (the weights'
    own dependence on F is ignored, so not exactly at it: on leuven a full Levenberg-Marquardt
    lowers the RMS by another 0.1 %). H&Z section 11.4.3; P. Torr and D. Murray, "The development
    and comparison of robust methods for estimating the fundamental matrix", IJCV 24(3), 1997.
    Solved in normalized coordinates, where the 9 x 9 normal equations are well conditioned (what
    OpenCV's 8-point solves too).
    """
    everything = np.ones(len(x1), dtype=bool)
    n = _pair_normalization(x1, x2, everything)
    inverse1, inverse2 = _similarity(1.0 / n[0], -n[0] * n[1:3]), _similarity(1.0 / n[3], -n[3] * n[4:])  # T^-1
    Fn = inverse2.T @ F @ inverse1
    if not np.any(Fn):
        return F
    for _ in range(iterations):  # the weights of each solve come from the previous F (compiled loop)
        F, Fn, _ = _fit_masked(x1, x2, everything, Fn)
    return F


def _numerical_rank(M: np.ndarray) -> int:
    singular = np.linalg.svd(M, compute_uv=False)
    return int(np.sum(singular > 1e-10 * singular[0]))


def _conjugate_to_rotation(H: np.ndarray) -> bool:
    """Whether the homography ``H`` is ``K2 R K1^-1`` (a camera turning about its centre): scaled to
    determinant 1, its three eigenvalues all have modulus 1 (within 1 %)."""
    determinant = np.linalg.det(H)
    if not np.isfinite(determinant) or determinant == 0:
        return False
    eigenvalues = np.abs(np.linalg.eigvals(H / np.cbrt(determinant)))
    return bool(np.all(np.abs(eigenvalues - 1.0) < 0.01))


def _is_rotation_homography(x1: np.ndarray, x2: np.ndarray) -> bool:
    """Whether one homography fitted to all the pairs (least squares, ``cv2.findHomography``) is a rotation's."""
    import cv2

    H, _ = cv2.findHomography(x1, x2, 0)
    return H is not None and _conjugate_to_rotation(H)


def _homographies_4point(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Homographies ``(B, 3, 3)`` mapping each sample of 4 pairs ``(B, 4, 2)`` exactly (the 4-point DLT).

    Each pair gives the rows ``[x1, y1, 1, 0, 0, 0, -x2 x1, -x2 y1, -x2]`` and
    ``[0, 0, 0, x1, y1, 1, -y2 x1, -y2 y1, -y2]`` of ``A h = 0``; ``h`` is the null vector of the 8 x 9
    system (:func:`_null_vector`). Points should be normalized first. ``cv2.getPerspectiveTransform``
    solves the same system. Reference: H&Z section 4.1 (algorithm 4.1).
    """
    u1, v1 = x1[..., 0], x1[..., 1]
    u2, v2 = x2[..., 0], x2[..., 1]
    one, zero = np.ones_like(u1), np.zeros_like(u1)
    rows_u = np.stack([u1, v1, one, zero, zero, zero, -u2 * u1, -u2 * v1, -u2], axis=-1)
    rows_v = np.stack([zero, zero, zero, u1, v1, one, -v2 * u1, -v2 * v1, -v2], axis=-1)
    A = np.concatenate([rows_u, rows_v], axis=-2)
    try:  # h9 = 1: an 8 x 8 solve, ten times cheaper than the null vector (H[2, 2] = 0 is non-generic)
        h = np.linalg.solve(A[..., :8], -A[..., 8:])[..., 0]
        h = np.concatenate([h, np.ones(h.shape[:-1] + (1,))], axis=-1)
    except np.linalg.LinAlgError:  # a singular sample (repeated points): the null vector, for every sample
        h = _null_vector(A)
    return h.reshape(x1.shape[:-2] + (3, 3))


#: How much looser than the inlier threshold the fast homography screen is, and the share of the F-consistent
#: pairs above which the full model selection (GRIC) runs: a raw 4-point homography of noisy points maps a
#: plane's points less tightly than a refined one. Measured with threshold 1 px, within 2 x 2 px: one plane or
#: one centre with 0.5 px noise 89-100 %, with 1 px noise 71-96 %; general scenes 4-16 %, the rendered room
#: 26 %, leuven 47 %. The tolerance is also at least ``SCREEN_SIGMAS`` times the measured noise, so that a
#: plane with more noise than the threshold (sigma = 2 px at 1 px) still reaches GRIC.
SCREEN_TOLERANCE = 2.0
SCREEN_SHARE = 0.6
SCREEN_SIGMAS = 6.0

#: Torr's GRIC for two views: ``r = 4`` coordinates per correspondence (x1, y1, x2, y2), ``lambda3 = 2``
#: (the robust cap of a squared normalized residual is ``lambda3 (r - d)``). F: a 3-dimensional variety
#: (``d = 3``) with ``k = 7`` parameters; H: ``d = 2``, ``k = 8``.
GRIC_R = 4
GRIC_LAMBDA3 = 2.0
GRIC_F = (3, 7)
GRIC_H = (2, 8)

#: Noise floor (px) of the scale estimate, so that exact synthetic data (residuals ~1e-10) give finite GRIC.
SIGMA_FLOOR_PX = 0.01


@functools.lru_cache(maxsize=64)
def _fixed_samples(population: int, size: int, count: int) -> np.ndarray:
    """``count`` samples of ``size`` distinct indices of ``range(population)`` from a fixed seed (cached, read-only)."""
    samples = random_samples(np.random.default_rng(0), population, size, count)
    samples.flags.writeable = False
    return samples


def _best_homography_share(x1: np.ndarray, x2: np.ndarray, tolerance_px: float, samples: int = 20) -> float:
    """The largest fraction of the pairs ``(N, 2)`` that one 4-point homography maps within ``tolerance_px``.

    A quick RANSAC screen (20 fixed-seed samples of 4, batched; no refinement): if one homography
    explains 90 % of the pairs, 20 samples all miss an all-inlier sample with probability
    (1 - 0.9^4)^20 < 1e-9, so a small share here (with a looser tolerance, ``SCREEN_TOLERANCE``)
    means the pairs are not degenerate. It stands in front of the model selection (GRIC, which
    fits a homography with ``cv2.findHomography``) because that call costs more than the rest of
    our RANSAC on easy input.
    """
    if len(x1) < 8:
        return 1.0
    picks = _fixed_samples(len(x1), 4, samples)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        s1, c1, n1 = _hartley_fast(x1)
        s2, c2, n2 = _hartley_fast(x2)
        H = _homographies_4point(n1[picks], n2[picks])  # (B, 3, 3), normalized coordinates
        mapped = (H.reshape(-1, 3) @ np.column_stack([n1, np.ones(len(n1))]).T).reshape(len(H), 3, -1)  # H x1
        du = mapped[:, 0] / mapped[:, 2] - n2[:, 0]
        dv = mapped[:, 1] / mapped[:, 2] - n2[:, 1]
        inside = du * du + dv * dv <= (tolerance_px * s2) ** 2  # (B, N): within the tolerance in image 2
    return float(np.count_nonzero(inside, axis=1).max() / len(x1))


def _solve_in_place_py(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``x`` with ``A x = b`` for a square ``A`` ``(n, n)`` by Gaussian elimination with partial pivoting
    (``np.linalg.solve``, LAPACK's ``gesv``); overwrites ``A`` and ``b``. All ``nan`` when ``A`` is singular."""
    n = len(b)
    for k in range(n):
        pivot = k
        for i in range(k + 1, n):
            if abs(A[i, k]) > abs(A[pivot, k]):
                pivot = i
        if A[pivot, k] == 0.0:
            return np.full(n, np.nan)
        if pivot != k:
            for j in range(n):
                A[k, j], A[pivot, j] = A[pivot, j], A[k, j]
            b[k], b[pivot] = b[pivot], b[k]
        for i in range(k + 1, n):
            factor = A[i, k] / A[k, k]
            for j in range(k, n):
                A[i, j] -= factor * A[k, j]
            b[i] -= factor * b[k]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        total = b[i]
        for j in range(i + 1, n):
            total -= A[i, j] * x[j]
        x[i] = total / A[i, i]
    return x


_solve_in_place = _kernel(_solve_in_place_py)


def _homography_share_py(x1: np.ndarray, x2: np.ndarray, picks: np.ndarray, tolerance_px: float) -> float:
    """:func:`_best_homography_share` as one compiled call, on the samples ``picks`` ``(B, 4)``.

    The same steps: Hartley-normalize both point sets, the 4-point homography of each sample with
    ``h9 = 1`` (an 8 x 8 solve, Gaussian elimination with partial pivoting as LAPACK's ``gesv``, written out
    because numba's ``np.linalg.solve`` takes seconds to compile), the largest count of pairs mapped within
    the tolerance in image 2. Returns -1 for a singular sample (repeated points): the caller then falls back
    on the NumPy form and its null vectors.
    """
    count = len(x1)
    normalization = _pair_normalization(x1, x2, np.ones(count, dtype=np.bool_))
    s1, s2 = normalization[0], normalization[3]
    centre = np.array([normalization[1], normalization[2], normalization[4], normalization[5]])
    n1 = np.empty((count, 2))
    n2 = np.empty((count, 2))
    for i in range(count):
        n1[i, 0], n1[i, 1] = (x1[i, 0] - centre[0]) * s1, (x1[i, 1] - centre[1]) * s1
        n2[i, 0], n2[i, 1] = (x2[i, 0] - centre[2]) * s2, (x2[i, 1] - centre[3]) * s2
    limit = (tolerance_px * s2) ** 2
    best = 0
    A = np.empty((8, 8))
    rhs = np.empty(8)
    for b in range(len(picks)):
        for k in range(4):
            u1, v1 = n1[picks[b, k], 0], n1[picks[b, k], 1]
            u2, v2 = n2[picks[b, k], 0], n2[picks[b, k], 1]
            A[k, 0], A[k, 1], A[k, 2], A[k, 3], A[k, 4], A[k, 5] = u1, v1, 1.0, 0.0, 0.0, 0.0
            A[k, 6], A[k, 7], rhs[k] = -u2 * u1, -u2 * v1, u2
            A[k + 4, 0], A[k + 4, 1], A[k + 4, 2], A[k + 4, 3], A[k + 4, 4] = 0.0, 0.0, 0.0, u1, v1
            A[k + 4, 5], A[k + 4, 6], A[k + 4, 7], rhs[k + 4] = 1.0, -v2 * u1, -v2 * v1, v2
        h = _solve_in_place(A, rhs)
        if h[0] != h[0]:  # nan: singular
            return -1.0
        inside = 0
        for i in range(count):
            u, v = n1[i, 0], n1[i, 1]
            w = h[6] * u + h[7] * v + 1.0
            du = (h[0] * u + h[1] * v + h[2]) / w - n2[i, 0]
            dv = (h[3] * u + h[4] * v + h[5]) / w - n2[i, 1]
            if du * du + dv * dv <= limit:
                inside += 1
        best = max(best, inside)
    return best / count


def _noise_sigma_py(d: np.ndarray, sigma: float, cut: float, factor: float, iterations: int, floor: float) -> float:
    """The loop of :func:`noise_sigma` compiled: ``d`` the finite absolute residuals, ``sigma`` the start
    (``max(1.4826 median, start_px, floor)``), ``factor`` :func:`_truncated_variance_factor` of ``cut``."""
    for _ in range(iterations):
        total = 0.0
        kept = 0
        for value in d:
            if value <= cut * sigma:
                total += value * value
                kept += 1
        if kept < SAMPLE_SIZE:
            break
        new = max(np.sqrt(total / kept / factor), floor)
        if abs(new - sigma) <= 1e-3 * sigma:
            return new
        sigma = new
    return sigma


_homography_share = _kernel(_homography_share_py)
_noise_sigma = _kernel(_noise_sigma_py)


def homography_sampson_distance(H: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """First-order geometric error of each pair ``(N, 2)`` under the homography ``H`` ``(3, 3)``, in pixels ``(N,)``.

    The two equations ``e = (a - u c, b - v c)`` with ``(a, b, c) = H x1`` and ``x2 = (u, v)`` (the
    rows of H&Z's ``A_i h``) vanish on the variety ``x2 ~ H x1``; linearized, the smallest move of the
    pair ``(x1, y1, x2, y2)`` onto it has squared length ``e^T (J J^T)^-1 e``, ``J`` the 2 x 4
    Jacobian of ``e``. It is the Sampson error of H (H&Z section 4.2.6, eq. 4.12), the same kind of
    distance as :func:`sampson_distance` for F: both measure the move in the joint image space, with
    the noise of both images, which is what GRIC compares (the transfer error ``|x2 - H x1|`` counts
    only image 2 and doubles the variance; the symmetric transfer error counts the noise twice).
    Identity H and ``x2 = x1 + d``: ``|d| / sqrt(2)`` (half the move in each image).
    """
    u, v = x2[:, 0], x2[:, 1]
    a, b, c = (H @ to_homogeneous(x1).T)
    e1, e2 = a - u * c, b - v * c
    p1, q1 = H[0, 0] - u * H[2, 0], H[0, 1] - u * H[2, 1]  # J row 1: (p1, q1, -c, 0)
    p2, q2 = H[1, 0] - v * H[2, 0], H[1, 1] - v * H[2, 1]  # J row 2: (p2, q2, 0, -c)
    m11, m22, m12 = p1 * p1 + q1 * q1 + c * c, p2 * p2 + q2 * q2 + c * c, p1 * p2 + q1 * q2
    with np.errstate(divide="ignore", invalid="ignore"):
        squared = (m22 * e1 * e1 - 2.0 * m12 * e1 * e2 + m11 * e2 * e2) / (m11 * m22 - m12 * m12)
    return np.sqrt(np.maximum(squared, 0.0))


def _truncated_variance_factor(c: float, dof: int = 1) -> float:
    """``E[q | q <= c^2] / dof`` for ``q`` chi-square with ``dof`` (1 or 2) degrees of freedom.

    One: ``1 - 2 c phi(c) / (2 Phi(c) - 1)`` (a truncated normal); two: ``(1 - (1 + c^2/2) e^(-c^2/2)) /
    (1 - e^(-c^2/2))`` (a truncated Rayleigh). 0.973 and 0.949 at ``c = 3``.
    """
    import math

    if dof == 2:
        tail = math.exp(-0.5 * c * c)
        return (1.0 - (1.0 + 0.5 * c * c) * tail) / (1.0 - tail)
    inside = math.erf(c / math.sqrt(2.0))
    return 1.0 - 2.0 * c * math.exp(-0.5 * c * c) / math.sqrt(2.0 * math.pi) / inside


def noise_sigma(residuals: np.ndarray, *, start_px: float = 1.0, cut: float = 3.0, iterations: int = 30) -> float:
    """Robust noise scale (px) from residuals ``(N,)`` that are ``sigma |N(0, 1)|`` for inliers, anything for outliers.

    The iteration is the compiled :func:`_noise_sigma` (its readable body ``_noise_sigma_py``).

    Start from ``max(1.4826 median, start_px)`` (at or above sigma with up to ~50 % outliers), then
    iterate the truncated estimate: keep ``|d| <= cut sigma`` and set ``sigma^2 = mean(d^2) / E[z^2 | |z|
    <= cut]`` (the correction for the truncation, 0.973 at 3 sigma) until it settles; it descends to the
    inliers' scale whatever the RANSAC threshold was (a 1 px threshold on 2 px noise keeps only a
    truncated core, whose spread alone would say ~0.5 px). Floored at ``SIGMA_FLOOR_PX``. Reference:
    Huber, Robust Statistics (1981), the MAD; P. Torr and A. Zisserman, "MLESAC", CVIU 78(1), 2000.
    """
    d = np.abs(residuals[np.isfinite(residuals)])
    if len(d) == 0:
        return SIGMA_FLOOR_PX
    start = max(1.4826 * float(np.median(d)), float(start_px), SIGMA_FLOOR_PX)
    return float(_noise_sigma(d, start, cut, _truncated_variance_factor(cut), iterations, SIGMA_FLOOR_PX))


def gric(residuals: np.ndarray, sigma: float, d: int, k: int, r: int = GRIC_R) -> float:
    """Torr's geometric robust information criterion of a model with residuals ``(n,)`` (px): lower is better.

    ``GRIC = sum rho(e_i^2 / sigma^2) + lambda1 d n + lambda2 k``, ``rho(x) = min(x, lambda3 (r - d))``,
    ``lambda1 = ln r``, ``lambda2 = ln(r n)``, ``lambda3 = 2``; ``d`` the dimension of the model's
    variety, ``k`` its parameters, ``r`` the dimension of the data (4 for two views). A model of lower
    dimension pays less per point (``lambda1 d``) but fits worse: a homography (d = 2) beats F (d = 3)
    when its residuals are hardly larger. Reference: P. Torr, "An assessment of information criteria
    for motion model selection", CVPR 1997; "Geometric motion segmentation and model selection",
    Phil. Trans. R. Soc. A 356, 1998.
    """
    n = len(residuals)
    capped = np.minimum(np.nan_to_num(residuals / sigma, nan=np.inf) ** 2, GRIC_LAMBDA3 * (r - d))
    return float(capped.sum() + np.log(r) * d * n + np.log(r * n) * k)


def _robust_homography(x1: np.ndarray, x2: np.ndarray, tolerance_px: float) -> np.ndarray | None:
    """``cv2.findHomography`` by RANSAC (transfer error within ``tolerance_px``), then least squares on its
    inliers, twice.

    OpenCV's own refinement after RANSAC stops early: on a noisy plane its H leaves Sampson errors ~25 %
    larger than the least-squares H of the same inliers, enough to tip the model selection.
    """
    import cv2

    # GRIC picks H only when it explains ~3/4 of the pairs or more: 30 samples of 4 all miss such an H with
    # probability (1 - 0.75^4)^30 < 1e-4 (and more samples cost more than the rest of RANSAC on easy input)
    H, mask = cv2.findHomography(x1, x2, cv2.RANSAC, tolerance_px, maxIters=30, confidence=0.999)
    for _ in range(2):
        if H is None or mask is None or int(mask.sum()) < 4 or mask.mean() < SCREEN_SHARE:
            return H  # an H of under 60 % of the pairs loses the selection, refined or not (it needs ~3/4)
        refit, _ = cv2.findHomography(x1[mask.ravel() > 0], x2[mask.ravel() > 0], 0)
        if refit is None:
            return H
        H = refit
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            mapped = to_homogeneous(x1) @ H.T
            transfer = np.hypot(mapped[:, 0] / mapped[:, 2] - x2[:, 0], mapped[:, 1] / mapped[:, 2] - x2[:, 1])
        mask = (transfer <= tolerance_px).astype(np.uint8)
    return H


#: Largest mean increase of the squared normalized Sampson error (``e^2 / sigma^2`` per pair) when a
#: homography's eigenvalues are forced to modulus 1, for it to count as a rotation's: the pairs move by less
#: than sigma / 2 RMS. Measured (300 pairs, 0.5 and 2 px noise): one centre 0.00-0.16, one plane 0.40-2.4
#: (planes whose own homography is within 1 % of a rotation's included).
ROTATION_EXTRA_COST = 0.25


def _rotation_explains(H: np.ndarray, x1: np.ndarray, x2: np.ndarray, sigma: float) -> bool:
    """Whether the rotation-conjugate homography nearest ``H`` (its eigenvalues scaled to modulus 1,
    ``V diag(w / |w|) V^-1``) still explains the pairs ``(N, 2)`` within the noise ``sigma``.

    The eigenvalue test alone (:func:`_conjugate_to_rotation`, 1 %) cannot tell some planes from a
    turn of the camera: a plane's homography ``K2 (R - t n^T / d) K1^-1`` may be within 1 % of a
    rotation's. Whether 1 % matters depends on the noise: here it is measured against the residuals.
    """
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        w, V = np.linalg.eig(H / np.cbrt(np.linalg.det(H)))
        try:
            rotation = np.real(V @ np.diag(w / np.abs(w)) @ np.linalg.inv(V))
        except np.linalg.LinAlgError:
            return False
        cap = GRIC_LAMBDA3 * (GRIC_R - GRIC_H[0])
        cost = np.minimum((homography_sampson_distance(rotation, x1, x2) / sigma) ** 2, cap)
        base = np.minimum((homography_sampson_distance(H, x1, x2) / sigma) ** 2, cap)
    extra = float(np.mean(np.nan_to_num(cost, nan=cap) - np.nan_to_num(base, nan=cap)))
    return extra <= ROTATION_EXTRA_COST


def _check_not_degenerate(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, inliers: np.ndarray,
                          threshold_px: float, distances: np.ndarray | None = None) -> None:
    """Raise when the inliers lie on a line, or when a homography explains the matches as well as F (one plane,
    or no baseline).

    A homography ``H`` maps image 1 to image 2 for points on one plane, and for any scene when the
    cameras share a centre (``H = K2 R K1^-1``); then F is not determined (a whole family of F fits
    equally well). Which model the matches support is decided by Torr's GRIC (:func:`gric`), not by
    a share under a threshold (at 1 px noise the transfer error of a plane's points passes 2 px for
    a third of them). The noise ``sigma`` is measured from F's Sampson distances of all matches
    (:func:`noise_sigma`, robust to outliers and to the RANSAC threshold); the pairs F explains within
    3 sigma (at most 300, spread over the list) are the data; ``H`` is fitted to them by
    ``cv2.findHomography`` (RANSAC at 3.5 sigma of transfer error, then least squares on its inliers,
    :func:`_robust_homography`); the residuals are the Sampson errors of F (:func:`sampson_distance`) and of H
    (:func:`homography_sampson_distance`). Degenerate when ``GRIC(H) <= GRIC(F)``. A homography
    conjugate to a rotation has eigenvalues of equal modulus: that says zero baseline. A fast
    4-point screen (:func:`_best_homography_share`) skips the selection when no homography comes
    near most pairs. Reference: H&Z section 11.9 (degeneracies); Torr (CVPR 1997; Phil. Trans. 1998);
    Chum, Werner and Matas, "Two-view geometry estimation unaffected by a dominant plane", CVPR 2005.
    """
    import cv2

    for name, x in (("x1", x1), ("x2", x2)):  # compiled screen; the readable check decides near the line
        if _distance_from_best_line(x, inliers) <= 1.01 * threshold_px:
            _check_collinear(x[inliers], name, threshold_px)
    if distances is None:  # F's Sampson distances of all the pairs (RANSAC passes those it has)
        with np.errstate(divide="ignore", invalid="ignore"):
            distances = sampson_distance(F, x1, x2)
    sigma = noise_sigma(distances, start_px=threshold_px)
    consistent = np.flatnonzero(distances <= max(3.0 * sigma, threshold_px))
    if len(consistent) < SAMPLE_SIZE:
        consistent = np.flatnonzero(inliers)
    spread = np.linspace(0, len(consistent) - 1, 300).round().astype(int) if len(consistent) > 300 \
        else np.arange(len(consistent))
    chosen = consistent[spread]  # at most 300, evenly over the list (steps >= 1 apart: no repeats)
    a, b = x1[chosen], x2[chosen]
    tolerance = max(SCREEN_TOLERANCE * 2.0 * threshold_px, SCREEN_SIGMAS * sigma)
    share = _homography_share(a, b, _fixed_samples(len(a), 4, 20), tolerance) if len(a) >= 8 else 1.0
    if share < 0:  # a singular 4-point sample (repeated points): the NumPy form's null vectors
        share = _best_homography_share(a, b, tolerance)
    if share < SCREEN_SHARE:
        return  # no homography comes near most pairs even far looser: it cannot win the model selection
    H = _robust_homography(a, b, 3.5 * sigma)
    if H is None:
        return
    residuals_F, residuals_H = sampson_distance(F, a, b), homography_sampson_distance(H, a, b)
    close = residuals_H <= 3.0 * sigma
    if close.mean() >= 0.5:  # most pairs follow H: F's spare freedom has absorbed part of the noise, take H's too
        spread = np.mean(residuals_H[close] ** 2) / (2.0 * _truncated_variance_factor(3.0, 2))  # 2 dof, cut at 3
        sigma = max(sigma, float(np.sqrt(spread)))
    gric_F = gric(residuals_F, sigma, *GRIC_F)
    gric_H = gric(residuals_H, sigma, *GRIC_H)
    if gric_H > gric_F:
        return
    share = (f"one homography explains the {len(chosen)} matches tested as well as F (Torr's GRIC: H {gric_H:.0f} "
             f"<= F {gric_F:.0f}, noise {sigma:.2f} px)")
    if _conjugate_to_rotation(H) and _rotation_explains(H, a, b, sigma):
        raise ZeroBaseline("x1", f"{share}, and it is (close to) a rotation: the two cameras share their centre "
                                 "(zero baseline), so there is no parallax and F (and t) are not determined; move the "
                                 "camera between the photos")
    raise CoplanarPoints("x1", f"{share}: the points lie on one plane (or the cameras hardly moved), so F is "
                               "not determined; include points off the plane")


def estimate_fundamental_ransac(x1: np.ndarray, x2: np.ndarray, *,
                                threshold_px: Annotated[float, Range(0.01, 100.0)] = 1.0,
                                confidence: Annotated[float, Range(0.5, 0.999999)] = 0.99,
                                max_iterations: Annotated[int, Range(1, 100000)] = 5000,
                                error: Literal["sampson", "epipolar"] = "sampson", refine: bool = True,
                                check_degenerate: bool = True, rng: np.random.Generator) -> RansacFundamental:
    """Robust F: RANSAC over 8-point samples with the adaptive iteration count, then a refit on the inliers.

    Repeat: draw 8 matches at random, solve the normalized 8-point algorithm on them
    (:func:`eight_point`, a batch of samples at once: 8, 16, 32 ... 256), count the matches whose
    error is below ``threshold_px``; keep the F with the most inliers. Each new best is first
    optimized locally (LO-RANSAC, :func:`_local_optimization`: refit on all its inliers while that
    gains inliers), then the number of samples needed is recomputed from its inlier ratio ``w``:
    ``N = log(1 - confidence) / log(1 - w^8)`` (:func:`lab.geometry.robust.ransac_iterations`),
    capped by ``max_iterations``; sampling stops once ``N`` samples are drawn. With ``refine`` the
    final F is refit on its inliers by Sampson-weighted least squares (close to the F of least
    Sampson error, :func:`_sampson_weighted_refit`). Last, the inliers are checked for degeneracy
    (:func:`_check_not_degenerate`): on one line, on one plane, or seen from one centre, F is not
    determined and the step says so instead of answering.

    Args:
        threshold_px: largest error of an inlier, in pixels.
        confidence: probability that at least one sample is all inliers (sets the adaptive N).
        max_iterations: most samples drawn.
        error: "sampson" (first-order geometric error, :func:`sampson_distance`) or "epipolar"
            (the larger of the two point-to-epipolar-line distances, what ``cv2.FM_RANSAC`` thresholds).
        refine: refit F on the inliers by iteratively Sampson-weighted least squares.
        check_degenerate: refuse degenerate input (a plane, a line, no baseline).

    Returns F ``(3, 3)`` (rank 2, unit norm), ``inliers`` ``(M,)`` bool and ``ransac_trace`` (best
    inlier count and the bound N after each batch). Corresponds to
    ``cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, threshold_px, confidence, max_iterations)``,
    which samples 7 matches (the 7-point algorithm) instead of 8.

    Implementation: everything that runs per batch, per new best or once per call is compiled by numba,
    one call each, so that an easy pair (a few samples) does not pay for a hundred small NumPy calls: the
    minimal solver (:func:`_minimal_fundamentals_compiled`, a batch of samples at once), the inlier counts
    of each batch of hypotheses (:func:`_count_inliers`), the local optimization
    (:func:`_local_optimization`), the Sampson refit (:func:`_sampson_refit`), the inlier masks
    (:func:`_inliers`), the Sampson distances (:func:`_sampson_distances`, computed once and shared with
    the degeneracy check), the noise scale (:func:`_noise_sigma`) and the quick 4-point homography screen
    (:func:`_homography_share`) that spares OpenCV's degeneracy test on clearly non-degenerate input. The
    tests compare each with its readable oracle (:func:`_minimal_fundamentals`, ``_Scorer.counts``,
    ``_local_optimization_reference``, ``_Scorer.inliers``,
    :func:`sampson_distance`, :func:`noise_sigma`, :func:`_best_homography_share`, :func:`eight_point`,
    ``_normal_equations_py``, ``cv2.getPerspectiveTransform``) and the whole step with the NumPy forms.

    Reference: H&Z section 4.7.1 (adaptive RANSAC, algorithm 4.5) and algorithm 11.4; Fischler and
    Bolles (1981); Chum, Matas and Kittler, "Locally optimized RANSAC", DAGM 2003.
    """
    x1, x2 = _pair(x1, x2)
    count = len(x1)
    best_count, best_F, best_inliers = -1, None, None
    needed, drawn = int(max_iterations), 0
    trace_x, trace_best, trace_needed = [], [], []
    t2, sampson = float(threshold_px) ** 2, error == "sampson"
    batch = 8
    while drawn < needed:
        size = min(batch, needed - drawn)
        samples = random_samples(rng, count, SAMPLE_SIZE, size)
        hypotheses = _minimal_fundamentals_compiled(x1, x2, samples)
        scores = _count_inliers(x1, x2, hypotheses, t2, sampson)  # -1 for a non-finite F
        drawn += size
        winner = int(np.argmax(scores))
        if scores[winner] > best_count:  # a new best: optimize it locally, then update N
            best_F, best_inliers = _local_optimization(hypotheses[winner], x1, x2, t2, sampson)
            best_count = int(best_inliers.sum())
            needed = min(needed, max(drawn, ransac_iterations(best_count / count, SAMPLE_SIZE, confidence,
                                                              max_iterations)))
        trace_x.append(drawn)
        trace_best.append(best_count)
        trace_needed.append(needed)
        batch = min(2 * batch, 256)
    if best_F is None or best_count < SAMPLE_SIZE:
        raise TooFewMatches("x1", f"no 8-point sample explains 8 or more matches within {threshold_px:g} px in "
                                  f"{drawn} tries; raise threshold_px or check the matches")
    F, inliers = best_F, best_inliers
    if refine and best_count >= SAMPLE_SIZE:
        refined = _sampson_refit(F, x1, x2, inliers, 3)
        again = _inliers(x1, x2, refined, t2, sampson)
        if np.count_nonzero(again) >= SAMPLE_SIZE:
            F, inliers = refined, again
    num_inliers = int(np.count_nonzero(inliers))
    if num_inliers < SAMPLE_SIZE:
        raise TooFewMatches("x1", f"only {num_inliers} inliers within {threshold_px:g} px; raise threshold_px")
    distances = _sampson_distances(F, x1, x2)  # every match: the degeneracy check reads them too
    if check_degenerate:
        _check_not_degenerate(F, x1, x2, inliers, threshold_px, distances)
    inlier_distances = distances[inliers]
    trace = Curve(np.array(trace_x, dtype=np.float64), np.array([trace_best, trace_needed], dtype=np.float64),
                  kind="line", title=f"RANSAC: {best_count} inliers after {drawn} samples", xlabel="samples drawn",
                  ylabel="count", labels=("best inlier count", "samples needed (N)"))
    return RansacFundamental(F, inliers, trace, num_inliers, num_inliers / count, drawn,
                             float(np.sqrt(np.mean(inlier_distances**2))), _numerical_rank(F))


# ----------------------------------------------------------------------------------------------------
# 5. Epipolar lines and epipoles
# ----------------------------------------------------------------------------------------------------
@step_result
class EpipolarDrawing:
    """Result of :func:`compute_epipolar_lines`."""

    epipolar_lines: Segments2D
    line_points: Points2D
    epipoles: np.ndarray
    epipole_points: Points2D
    sampson_rms_px: float = metric("RMS Sampson distance of the inliers", unit="px")
    symmetric_rms_px: float = metric("RMS symmetric epipolar distance of the inliers", unit="px")
    rank_of_F: int = metric("numerical rank of F")
    lines_drawn: int = metric("inliers whose lines are drawn")


def clip_lines(lines: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Clip lines ``a x + b y + c = 0`` ``(N, 3)`` to the image ``[0, width - 1] x [0, height - 1]``.

    Returns the segment ends ``(N, 2)`` each and a ``(N,)`` mask of the lines that cross the image.
    """
    lines = np.asarray(lines, dtype=np.float64)
    a, b, c = lines[:, 0], lines[:, 1], lines[:, 2]
    right, bottom = width - 1.0, height - 1.0
    ends = []
    with np.errstate(divide="ignore", invalid="ignore"):
        for x in (0.0, right):  # crossings with the left and right borders
            ends.append(np.stack([np.full_like(a, x), -(a * x + c) / b], axis=-1))
        for y in (0.0, bottom):  # with the top and bottom borders
            ends.append(np.stack([-(b * y + c) / a, np.full_like(a, y)], axis=-1))
    candidates = np.stack(ends, axis=1)  # (N, 4, 2)
    eps = 1e-9 * max(width, height)
    inside = (np.isfinite(candidates).all(axis=2) & (candidates[..., 0] >= -eps) & (candidates[..., 0] <= right + eps)
              & (candidates[..., 1] >= -eps) & (candidates[..., 1] <= bottom + eps))
    start = np.zeros((len(lines), 2))
    end = np.zeros((len(lines), 2))
    valid = np.zeros(len(lines), dtype=bool)
    for i in range(len(lines)):
        found = candidates[i][inside[i]]
        if len(found) >= 2:
            distance = np.linalg.norm(found[:, None] - found[None], axis=2)
            j, k = np.unravel_index(np.argmax(distance), distance.shape)
            start[i], end[i], valid[i] = found[j], found[k], distance[j, k] > 0
    return start, end, valid


def _line_colors(count: int) -> np.ndarray:
    """``count`` distinct saturated colours ``(count, 3)`` (hues spread around the circle)."""
    import colorsys

    return np.array([colorsys.hsv_to_rgb((0.61803 * i) % 1.0, 0.85, 1.0) for i in range(count)]).reshape(-1, 3)


def compute_epipolar_lines(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, images: ImageSet,
                           inliers: np.ndarray | None = None, *,
                           num_lines: Annotated[int, Range(1, 500)] = 30) -> EpipolarDrawing:
    """Epipolar lines of a sample of inliers, the epipoles, and how well F fits the inliers.

    A point ``x1`` in image 1 must be seen in image 2 on its epipolar line ``l2 = F x1``, and
    ``x2`` in image 1 on ``l1 = F^T x2`` (:func:`epipolar_lines`, ``cv2.computeCorrespondEpilines``).
    All lines of an image pass through its epipole (:func:`epipoles`), the image of the other
    camera's centre. ``num_lines`` inliers spread evenly over the match list are drawn, each line
    and its two points in one colour. The metrics say how well F explains the inliers:
    the RMS Sampson distance and the RMS symmetric epipolar distance.

    Args:
        num_lines: how many inliers to draw lines for.

    Reference: H&Z sections 9.1-9.2 (result 9.5: ``l' = F x``; result 9.8: ``F e = 0``,
    ``F^T e' = 0``), 11.4.3 (the distances).
    """
    F = _matrix(F, "F")
    x1, x2 = _pair(x1, x2, minimum=1)
    images = _two_images(images)
    mask = _inlier_mask(inliers, len(x1))
    chosen = np.flatnonzero(mask)
    if len(chosen) > num_lines:
        chosen = chosen[np.linspace(0, len(chosen) - 1, num_lines).round().astype(int)]
    colors = _line_colors(len(chosen))
    starts, ends, views, segment_colors = [], [], [], []
    for view, (lines, image) in enumerate(((epipolar_lines(F, x2[chosen], image=2), images[0]),
                                           (epipolar_lines(F, x1[chosen], image=1), images[1]))):
        start, end, valid = clip_lines(lines, image.width, image.height)
        starts.append(start[valid])
        ends.append(end[valid])
        views.append(np.full(int(valid.sum()), view))
        segment_colors.append(colors[valid])
    segments = Segments2D(np.concatenate(starts), np.concatenate(ends), view=np.concatenate(views),
                          colors=np.concatenate(segment_colors), image="images")
    points = Points2D(np.concatenate([x1[chosen], x2[chosen]]), view=np.repeat([0, 1], len(chosen)),
                      colors=np.concatenate([colors, colors]), image="images")
    pair = epipoles(F)
    finite = np.abs(pair[:, 2]) > 1e-12 * np.abs(pair[:, :2]).max(axis=1)
    epipole_xy = pair[finite, :2] / pair[finite, 2:]
    epipole_points = Points2D(epipole_xy, view=np.flatnonzero(finite), colors=np.ones((int(finite.sum()), 3)),
                              image="images")
    sampson = sampson_distance(F, x1[mask], x2[mask])
    symmetric = symmetric_epipolar_distance(F, x1[mask], x2[mask])
    return EpipolarDrawing(segments, points, pair, epipole_points, float(np.sqrt(np.mean(sampson**2))),
                           float(np.sqrt(np.mean(symmetric**2))), _numerical_rank(F), len(chosen))


# ----------------------------------------------------------------------------------------------------
# 6. The essential matrix
# ----------------------------------------------------------------------------------------------------
def _intrinsics_for(images: ImageSet, K1: Any, K2: Any) -> tuple[np.ndarray, np.ndarray]:
    if K1 is None or K2 is None:
        sizes = [f"{im.width}x{im.height}" for im in images.images] if isinstance(images, ImageSet) else []
        if len(sizes) == 2 and sizes[0] != sizes[1]:
            raise MissingIntrinsics("K1", f"the two images have different sizes ({sizes[0]} and {sizes[1]}) and no K "
                                          "was given, so no common camera can be assumed: give K1 and K2 (a K file "
                                          "or fx, fy, cx, cy)")
        raise MissingIntrinsics("K1", "no camera matrix: E needs K1 and K2 (give a K file or fx, fy, cx, cy)")
    return as_intrinsics(K1), as_intrinsics(K2)


def estimate_essential(F: np.ndarray, images: ImageSet, K1: np.ndarray | None = None,
                       K2: np.ndarray | None = None) -> Annotated[np.ndarray, "E"]:
    """The essential matrix ``E = K2^T F K1``, projected onto the essential matrices.

    F relates pixels; E relates normalized image coordinates ``K^-1 x``, so ``E = K2^T F K1``. An
    essential matrix ``[t]_x R`` has two equal singular values and a zero one (H&Z result 9.17);
    the product from an estimated F does not, so it is replaced by the nearest essential matrix in
    Frobenius norm, ``U diag(1, 1, 0) V^T`` (H&Z section 11.7.3; the scale of E is arbitrary and
    (1, 1, 0) goes with ``|t| = 1``). OpenCV has no single call: ``cv2.findEssentialMat`` estimates
    E directly from normalized points (the 5-point algorithm) instead of going through F.

    Returns E ``(3, 3)`` with singular values (1, 1, 0).

    Reference: H&Z section 9.6 (eq. 9.12, result 9.17), section 11.7.3.
    """
    F = _matrix(F, "F")
    K1, K2 = _intrinsics_for(images, K1, K2)
    U, _, Vt = np.linalg.svd(K2.T @ F @ K1)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


# ----------------------------------------------------------------------------------------------------
# 7. The four poses of E, and the one in front of both cameras (lesson steps)
# ----------------------------------------------------------------------------------------------------
def decompose_essential(E: np.ndarray) -> Annotated[np.ndarray, "candidates"]:
    """The four relative poses an essential matrix admits, ``(4, 3, 4)`` stacked ``[R | t]`` (``|t| = 1``).

    ``E = [t]_x R`` fixes ``t`` only up to sign and ``R`` up to a half turn about ``t``, so there
    are four candidates ``(R1, t), (R2, t), (R1, -t), (R2, -t)`` (:func:`essential_candidates`).
    Corresponds to ``cv2.decomposeEssentialMat(E)`` -> ``R1, R2, t``.

    Reference: H&Z section 9.6.2, result 9.19 and figure 9.12.
    """
    return essential_candidates(E)


#: The names of E's four candidates, in the order of :func:`essential_candidates` (the ``candidate`` control).
CANDIDATE_NAMES = ("R1 t", "R2 t", "R1 -t", "R2 -t")


def _candidates(value: Any) -> np.ndarray:
    """``(4, 3, 4)`` candidates; an essential matrix ``(3, 3)`` is decomposed first (callers that hold E)."""
    array = np.asarray(value, dtype=np.float64)
    if array.shape == (3, 3):
        return essential_candidates(array)
    if array.shape != (4, 3, 4):
        raise InvalidValue("candidates", f"expected the four [R | t] of decompose_essential, shape (4, 3, 4), got "
                                         f"{array.shape}")
    if not np.all(np.isfinite(array)):
        raise InvalidValue("candidates", "contains NaN or infinite entries")
    return array


def recover_pose(candidates: np.ndarray, x1: np.ndarray, x2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                 inliers: np.ndarray | None = None, *,
                 candidate: Literal["cheirality", "R1 t", "R2 t", "R1 -t", "R2 -t"] = "cheirality",
                 ) -> Annotated[np.ndarray, "pose"]:
    """The relative pose ``[R | t]`` of camera 2: of E's four candidates, the one with the points in front.

    Triangulate the inliers (normalized by ``K^-1``) with each candidate ``[R | t]`` of
    :func:`decompose_essential` and keep the one that puts the most of them in front of both
    cameras (positive depth in camera 1, ``Z`` of ``X``, and in camera 2, ``Z`` of ``R X + t``: the
    cheirality test). For a correct E one candidate has all of them in front (bar noise on very
    distant points); ``(R, -t)`` puts them all behind both cameras and the two "twisted" ones behind
    one camera.

    Args:
        candidate: "cheirality" (the test above), or one of the four by name, to see what a wrong
            choice does to the rest of the pipeline.

    ``candidates`` may also be an essential matrix ``(3, 3)``, decomposed first. Returns ``pose``
    ``(3, 4)`` = ``[R | t]`` with ``X_2 = R X_1 + t`` and ``|t| = 1`` (the scale of a two-view
    reconstruction is unknown). Corresponds to ``cv2.recoverPose(E, x1, x2, K, mask=inliers)`` (one K
    for both views; which also drops points more than 50 units away from the vote).

    Reference: H&Z section 9.6.3 (figure 9.12) and section 12.2 (triangulation).
    """
    candidates = _candidates(candidates)
    x1, x2 = _pair(x1, x2, minimum=1)
    mask = _inlier_mask(inliers, len(x1))
    if candidate != "cheirality":
        return candidates[CANDIDATE_NAMES.index(candidate)].copy()
    if not mask.any():
        raise TooFewMatches("inliers", "no inliers to test the four poses with")
    K1, K2 = as_intrinsics(K1), as_intrinsics(K2)
    counts = cheirality_counts(candidates, pixels_to_normalized(x1[mask], K1), pixels_to_normalized(x2[mask], K2))
    best = int(np.argmax(counts))
    if counts[best] == 0:
        raise DegenerateInput("candidates", "no candidate pose puts any point in front of both cameras: E does not "
                                            "fit these matches")
    return candidates[best].copy()


@step_result
class RefinedPose:
    """Result of :func:`refine_pose`."""

    R: np.ndarray
    t: np.ndarray
    warnings: Warnings
    sampson_rms_px: float = metric("RMS Sampson distance of the inliers to E(R, t), after", unit="px")
    sampson_rms_start_px: float = metric("the same for the starting pose", unit="px")
    rotation_change_deg: float = metric("angle between the starting and the refined rotation", unit="deg")
    translation_change_deg: float = metric("angle between the starting and the refined t", unit="deg")
    median_parallax_deg: float = metric("median angle between the two rays of an inlier", unit="deg")


def _tangent_basis(t: np.ndarray) -> np.ndarray:
    """Two unit vectors orthogonal to the unit vector ``t`` and to each other, ``(3, 2)``."""
    helper = np.eye(3)[int(np.argmin(np.abs(t)))]
    a = np.cross(t, helper)
    a /= np.linalg.norm(a)
    return np.column_stack([a, np.cross(t, a)])


def refine_pose(pose: np.ndarray, x1: np.ndarray, x2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                inliers: np.ndarray | None = None, *,
                iterations: Annotated[int, Range(0, 200)] = 30) -> RefinedPose:
    """Polish ``(R, t)`` on the inliers: minimize their Sampson distances to ``F(R, t) = K2^-T [t]_x R K1^-1``.

    F from the 8-point algorithm has 7 degrees of freedom and ignores that the cameras are
    calibrated; a relative pose has 5 (3 for R, 2 for the direction of t). Starting from the
    chosen pose, Levenberg-Marquardt (``scipy.optimize.least_squares``) minimizes the sum of squared
    Sampson distances (:func:`sampson_distance`, in pixels) over ``R = exp([w]_x) R0`` and
    ``t = (t0 + B b) / |t0 + B b|`` (``B`` spans the plane orthogonal to ``t0``): the calibrated
    maximum-likelihood estimate to first order. On well-spread points it moves the pose by hundredths
    of a degree; on nearly degenerate ones (a small or flat scene) it repairs what the 7-parameter F
    got wrong.

    Args:
        iterations: most function evaluations per parameter (0: keep the pose as chosen).

    Returns ``R`` ``(3, 3)`` and ``t`` ``(3,)`` with ``|t| = 1``, and a warning when the median
    parallax (the angle between an inlier's two rays, 0 for points at infinity) is below 1 degree:
    then t's direction is uncertain whatever the method. No single OpenCV call: OpenCV's USAC
    estimators polish E on the inliers in the same spirit.

    Reference: H&Z section 11.4.3 (the Sampson error) and section 11.7.3 (E from calibrated points);
    B. Triggs et al., "Bundle adjustment - a modern synthesis" (2000), section 2.2 (local parameterizations).
    """
    from scipy.optimize import least_squares

    from lab.geometry.rotations import rotvec_to_matrix, skew

    R0, t0 = _pose(pose)
    x1, x2 = _pair(x1, x2, minimum=1)
    mask = _inlier_mask(inliers, len(x1))
    K1, K2 = as_intrinsics(K1), as_intrinsics(K2)
    norm = np.linalg.norm(t0)
    if norm == 0:
        raise InvalidValue("pose", "t is zero: the direction of the baseline is undefined")
    t0 = t0 / norm
    B = _tangent_basis(t0)
    a, b = x1[mask], x2[mask]
    inverse1, inverse2 = np.linalg.inv(K1), np.linalg.inv(K2)

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = t0 + B @ p[3:]
        return rotvec_to_matrix(p[:3]) @ R0, t / np.linalg.norm(t)

    def residuals(p: np.ndarray) -> np.ndarray:
        R, t = unpack(p)
        F = inverse2.T @ skew(t) @ R @ inverse1
        Fx1, Ftx2, algebraic = _line_terms(F, a, b)
        return algebraic / np.sqrt(Fx1[0] ** 2 + Fx1[1] ** 2 + Ftx2[0] ** 2 + Ftx2[1] ** 2)

    start = residuals(np.zeros(5))
    if iterations > 0 and len(a) >= 5:
        solution = least_squares(residuals, np.zeros(5), method="lm", max_nfev=int(iterations) * 6, x_scale=1.0)
        p = solution.x if np.sum(solution.fun**2) <= np.sum(start**2) else np.zeros(5)
    else:
        p = np.zeros(5)
    R, t = unpack(p)
    final = residuals(p)
    ray1 = to_homogeneous(a) @ inverse1.T
    ray2 = to_homogeneous(b) @ inverse2.T @ R  # R^T (K2^-1 x2): image 2's ray in camera 1's frame
    cosine = np.sum(ray1 * ray2, axis=1) / (np.linalg.norm(ray1, axis=1) * np.linalg.norm(ray2, axis=1))
    parallax = float(np.degrees(np.median(np.arccos(np.clip(cosine, -1.0, 1.0)))))
    warnings = ()
    if parallax < 1.0:
        warnings = (f"the median parallax is only {parallax:.2f} degrees: the baseline is small compared with the "
                    "depth of the scene, so the direction of t is poorly determined",)
    return RefinedPose(R, t, warnings, float(np.sqrt(np.mean(final**2))), float(np.sqrt(np.mean(start**2))),
                       float(rotation_angle_deg(R0, R)), float(np.degrees(np.arccos(np.clip(t @ t0, -1.0, 1.0)))),
                       parallax)


# ----------------------------------------------------------------------------------------------------
# 8. Triangulation
# ----------------------------------------------------------------------------------------------------
def _projections_of(K1: np.ndarray, K2: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    R, t = _rotation_translation(R, t)
    return np.stack([projection_matrix(as_intrinsics(K1), np.eye(3), np.zeros(3)),
                     projection_matrix(as_intrinsics(K2), R, t)])


def triangulate(x1: np.ndarray, x2: np.ndarray, R: np.ndarray, t: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                inliers: np.ndarray | None = None) -> Annotated[np.ndarray, "points3d_dlt"]:
    """Linear (DLT) triangulation of the inliers with ``P1 = K1 [I | 0]`` and ``P2 = K2 [R | t]`` (the refined pose).

    For each match, the 3D point whose images are ``x1`` and ``x2``: ``x cross (P X) = 0`` gives two
    equations per view, and X is the null vector of the ``4 x 4`` system
    (:func:`lab.geometry.triangulation.triangulate_dlt`). It minimizes an algebraic error, not the
    distance in the images; :func:`refine_points` does that next.

    Returns ``(N, 3)`` points in camera 1's frame, one per inlier in match order, in units of the
    baseline. Corresponds to ``cv2.triangulatePoints(P1, P2, x1.T, x2.T)`` (then dividing by the
    fourth coordinate).

    Reference: H&Z section 12.2.
    """
    x1, x2 = _pair(x1, x2, minimum=1)
    mask = _inlier_mask(inliers, len(x1))
    P = _projections_of(K1, K2, R, t)
    return triangulate_dlt(P, np.stack([x1[mask], x2[mask]]))


@step_result
class Reconstruction:
    """Result of :func:`refine_points`."""

    points3d: PointCloud
    cameras: Cameras
    residuals: Segments2D
    reprojection_cost: Curve
    reprojection_rms_px: float = metric("RMS reprojection error after refinement", unit="px")
    reprojection_rms_dlt_px: float = metric("RMS reprojection error of the DLT points", unit="px")
    points: int = metric("triangulated points")
    points_behind: int = metric("points behind either camera (cheirality violated)")


def _colors_at(image, xy: np.ndarray) -> np.ndarray:
    """Colours ``(N, 3)`` of the pixels nearest to ``xy`` (grey images give grey colours)."""
    pixels = image.pixels
    cols = np.clip(np.round(xy[:, 0]).astype(int), 0, image.width - 1)
    rows = np.clip(np.round(xy[:, 1]).astype(int), 0, image.height - 1)
    values = pixels[rows, cols].astype(np.float64)
    return values if values.ndim == 2 else np.repeat(values[:, None], 3, axis=1)


def refine_points(points3d_dlt: np.ndarray, x1: np.ndarray, x2: np.ndarray, R: np.ndarray, t: np.ndarray,
                  K1: np.ndarray, K2: np.ndarray, images: ImageSet, inliers: np.ndarray | None = None, *,
                  iterations: Annotated[int, Range(0, 100)] = 10,
                  residual_scale: Annotated[float, Range(1.0, 1000.0)] = 20.0) -> Reconstruction:
    """Move each triangulated point to minimize its reprojection error in both images (cameras fixed).

    Levenberg-Marquardt on ``|pi(P1 X) - x1|^2 + |pi(P2 X) - x2|^2`` for every point at once
    (:func:`lab.geometry.triangulation.refine_points`): the maximum-likelihood point under
    Gaussian pixel noise, where the DLT minimized an algebraic error. Then the values to look at: the
    point cloud coloured from image 1, the two cameras, and the residuals drawn magnified.

    Args:
        iterations: most Levenberg-Marquardt iterations (0: keep the DLT points).
        residual_scale: magnification of the residual segments drawn on the images.

    Returns ``points3d`` (PointCloud), ``cameras`` (Cameras: camera 1 at the origin, camera 2 at
    ``(R, t)``, carrying the images), ``residuals`` (Segments2D per observation: observed ->
    observed + scale x (reprojected - observed)), ``reprojection_cost`` (RMS per iteration).
    No single OpenCV call (see :func:`lab.geometry.triangulation.refine_points`).

    Reference: H&Z section 12.5 (the maximum-likelihood criterion) and appendix A6.2.
    """
    x1, x2 = _pair(x1, x2, minimum=1)
    images = _two_images(images)
    mask = _inlier_mask(inliers, len(x1))
    X0 = np.asarray(points3d_dlt, dtype=np.float64)
    if X0.shape != (int(mask.sum()), 3):
        raise InvalidValue("points3d_dlt", f"expected one point per inlier ({int(mask.sum())}, 3), got {X0.shape}")
    P = _projections_of(K1, K2, R, t)
    observed = np.stack([x1[mask], x2[mask]])
    finite = np.all(np.isfinite(X0), axis=1)
    X = np.where(finite[:, None], X0, 0.0)
    visible = np.broadcast_to(finite, observed.shape[:2])
    if finite.any() and iterations > 0:
        refined, history = refine_point_positions(P, observed[:, finite], X[finite], iterations=iterations)
        X[finite] = refined
    else:
        history = np.array([np.sqrt(np.mean(np.sum(reprojection_residuals(P, X[finite], observed[:, finite]) ** 2,
                                                   axis=2)))]) if finite.any() else np.array([0.0])
    residual = reprojection_residuals(P, X, observed)
    residual = np.where(visible[..., None] & np.isfinite(residual), residual, 0.0)
    depth = point_depths(P, X)
    behind = int(np.sum(finite & ~np.all(depth > 0, axis=0)))
    R, t = _rotation_translation(R, t)
    cameras = Cameras(K=np.stack([as_intrinsics(K1), as_intrinsics(K2)]), R=np.stack([np.eye(3), R]),
                      t=np.stack([np.zeros(3), t]), width=images[0].width, height=images[0].height, image="images")
    n = len(X)
    start = np.concatenate([observed[0], observed[1]])
    residuals = Segments2D(start, start + residual_scale * np.concatenate([residual[0], residual[1]]),
                           view=np.repeat([0, 1], n), image="images")
    cloud = PointCloud(X[finite], colors=_colors_at(images[0], observed[0][finite]))
    cost = Curve(np.arange(len(history), dtype=np.float64), history, kind="line", title="Point refinement",
                 xlabel="iteration", ylabel="RMS reprojection error (px)", labels=("RMS",))
    rms = float(np.sqrt(np.sum(residual**2) / max(2 * int(finite.sum()), 1)))
    return Reconstruction(cloud, cameras, residuals, cost, rms, float(history[0]), int(finite.sum()), behind)


# ----------------------------------------------------------------------------------------------------
# Evaluations (run after a step; truth may be empty)
# ----------------------------------------------------------------------------------------------------
def _correct_matches(state: dict[str, Any], truth: dict[str, Any], tolerance_px: float = 3.0) -> np.ndarray | None:
    """Which matches are right, ``(M,)`` bool, from the truth (the generator's tracks, or depth maps)."""
    matches = state.get("matches")
    if "keypoint_track" in truth and matches is not None:
        track = np.asarray(truth["keypoint_track"])
        if len(track) == len(state["keypoints"]):
            a, b = track[matches[:, 0]], track[matches[:, 1]]
            return (a == b) & (a >= 0)
    if "depth" in truth and "x1" in state:
        points = _true_points(state, truth)
        projected = points @ truth["R"].T + truth["t"]
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = projected @ truth["K2"].T
            pixels = pixels[:, :2] / pixels[:, 2:]
        return np.linalg.norm(pixels - state["x2"], axis=1) <= tolerance_px
    return None


def _true_points(state: dict[str, Any], truth: dict[str, Any]) -> np.ndarray:
    """The true 3D point (camera 1 frame) behind each match's ``x1``, ``(M, 3)`` (NaN where unknown)."""
    x1 = np.asarray(state["x1"])
    if "keypoint_track" in truth and "points3d" in truth and "matches" in state:
        track = np.asarray(truth["keypoint_track"])[state["matches"][:, 0]]
        points = np.full((len(x1), 3), np.nan)
        points[track >= 0] = truth["points3d"][track[track >= 0]]
        return points
    depth = np.asarray(truth["depth"])[0]
    cols = np.clip(np.round(x1[:, 0]).astype(int), 0, depth.shape[1] - 1)
    rows = np.clip(np.round(x1[:, 1]).astype(int), 0, depth.shape[0] - 1)
    z = depth[rows, cols]
    z = np.where(np.isfinite(z) & (z > 0), z, np.nan)
    rays = to_homogeneous(x1) @ np.linalg.inv(truth["K1"]).T
    return rays * z[:, None]


def _f_metrics(F: np.ndarray, state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    out: dict[str, float] = {"rank_of_F": _numerical_rank(F)}
    mask = _inlier_mask(state.get("inliers"), len(state["x1"]))
    out["sampson_rms_px"] = float(np.sqrt(np.mean(sampson_distance(F, state["x1"][mask], state["x2"][mask]) ** 2)))
    if "F" in truth and np.any(truth["F"]):
        a, b = F / np.linalg.norm(F), truth["F"] / np.linalg.norm(truth["F"])
        out["f_error"] = float(min(np.linalg.norm(a - b), np.linalg.norm(a + b)))
    if "x1_exact" in truth:
        exact = sampson_distance(F, truth["x1_exact"], truth["x2_exact"])
        out["truth_sampson_rms_px"] = float(np.sqrt(np.mean(exact**2)))
    return out


def evaluate_matches(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``match_precision``: the fraction of the matches that are right (with truth)."""
    correct = _correct_matches(state, truth)
    if correct is None or len(correct) == 0:
        return {}
    return {"match_precision": float(correct.mean()), "correct_matches": int(correct.sum())}


def evaluate_fundamental(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``rank_of_F``, ``sampson_rms_px`` (inliers, or all matches); with truth ``f_error`` (distance
    between the unit-norm F and the true one, sign aligned), ``truth_sampson_rms_px`` (how far the
    exact, noise-free correspondences are from F), and after RANSAC ``inlier_precision`` /
    ``inlier_recall`` against the right matches."""
    F = np.asarray(state["F"])
    out = _f_metrics(F, state, truth)
    correct = _correct_matches(state, truth)
    if correct is not None and "inliers" in state and state.get("inliers") is not None:
        inliers = np.asarray(state["inliers"], dtype=bool)
        if len(inliers) == len(correct):
            out["inlier_precision"] = float(np.sum(inliers & correct) / max(inliers.sum(), 1))
            out["inlier_recall"] = float(np.sum(inliers & correct) / max(correct.sum(), 1))
    return out


def evaluate_fundamental_8point(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """As :func:`evaluate_fundamental`, over all matches (the 8-point step uses them all)."""
    everything = {k: v for k, v in state.items() if k != "inliers"}
    return _f_metrics(np.asarray(state["F"]), everything, truth)


def evaluate_essential(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``essential_singular_ratio``: sigma2 / sigma1 of ``K2^T F K1`` before the projection (1 for an
    exact F and K); with truth ``e_error`` (distance to the true unit-norm-t E, sign aligned)."""
    out: dict[str, float] = {}
    if state.get("K1") is not None and state.get("K2") is not None:
        singular = np.linalg.svd(np.asarray(state["K2"]).T @ state["F"] @ np.asarray(state["K1"]), compute_uv=False)
        out["essential_singular_ratio"] = float(singular[1] / singular[0])
    if "E" in truth and np.any(truth["E"]):
        a = state["E"] / np.linalg.norm(state["E"])
        b = truth["E"] / np.linalg.norm(truth["E"])
        out["e_error"] = float(min(np.linalg.norm(a - b), np.linalg.norm(a + b)))
    return out


def _rotation_and_direction_errors(R: np.ndarray, t: np.ndarray, truth: dict[str, Any]) -> dict[str, float]:
    out = {"rotation_error_deg": float(rotation_angle_deg(R, truth["R"]))}
    norm = np.linalg.norm(truth["t"])
    if norm > 0:
        cosine = float(np.dot(t / np.linalg.norm(t), truth["t"] / norm))
        out["translation_direction_error_deg"] = float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
    return out


def evaluate_candidates(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """With truth, ``best_candidate_rotation_error_deg``: the candidate rotation nearest the true one."""
    if "R" not in truth:
        return {}
    angles = rotation_angle_deg(state["candidates"][:, :, :3], np.broadcast_to(truth["R"], (4, 3, 3)))
    return {"best_candidate_rotation_error_deg": float(np.min(angles))}


def evaluate_pose(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """With truth, ``rotation_error_deg`` and ``translation_direction_error_deg`` (angle between t and the true t)."""
    if "R" not in truth:
        return {}
    pose = np.asarray(state["pose"])
    return _rotation_and_direction_errors(pose[:, :3], pose[:, 3], truth)


def evaluate_refined_pose(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """With truth, ``rotation_error_deg`` and ``translation_direction_error_deg`` of the refined ``R``, ``t``."""
    if "R" not in truth:
        return {}
    return _rotation_and_direction_errors(np.asarray(state["R"]), np.asarray(state["t"]), truth)


def _point_errors(points: np.ndarray, state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Median relative 3D error of the points, the reconstruction scaled by the true baseline length."""
    if "R" not in truth or not np.linalg.norm(truth["t"]) > 0:
        return {}
    mask = _inlier_mask(state.get("inliers"), len(state["x1"]))
    true_points = _true_points(state, truth)[mask]
    points = np.asarray(points) * np.linalg.norm(truth["t"])
    known = np.all(np.isfinite(true_points), axis=1) & np.all(np.isfinite(points), axis=1)
    correct = _correct_matches(state, truth)
    if correct is not None:
        known &= correct[mask]
    if not known.any():
        return {}
    relative = np.linalg.norm(points[known] - true_points[known], axis=1) / np.linalg.norm(true_points[known], axis=1)
    return {"point_rel_error_median": float(np.median(relative))}


def evaluate_triangulation(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """With truth, ``point_rel_error_median`` of the DLT points (scaled by the true baseline)."""
    return _point_errors(state["points3d_dlt"], state, truth)


def evaluate_refinement(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """With truth, ``point_rel_error_median`` of the refined points (scaled by the true baseline)."""
    mask = _inlier_mask(state.get("inliers"), len(state["x1"]))
    points = np.full((int(mask.sum()), 3), np.nan)
    finite = np.all(np.isfinite(np.asarray(state["points3d_dlt"])), axis=1)
    points[finite] = state["points3d"].xyz
    return _point_errors(points, state, truth)


PIPELINE = Pipeline.build(
    name="epipolar",
    title="Epipolar geometry",
    summary="Two views step by step: SIFT features, matches with the ratio test, the normalized 8-point "
            "algorithm and RANSAC for F, epipolar lines and epipoles, the essential matrix, the four poses and "
            "the cheirality test, triangulation and its refinement.",
    steps=[detect_features, match_features, estimate_fundamental_8point, estimate_fundamental_ransac,
           compute_epipolar_lines, estimate_essential, decompose_essential, recover_pose, refine_pose, triangulate,
           refine_points],
    datasets=[rendered, correspondences, photos],
    evaluations={"match_features": evaluate_matches, "estimate_fundamental_8point": evaluate_fundamental_8point,
                 "estimate_fundamental_ransac": evaluate_fundamental, "estimate_essential": evaluate_essential,
                 "decompose_essential": evaluate_candidates, "recover_pose": evaluate_pose,
                 "refine_pose": evaluate_refined_pose,
                 "triangulate": evaluate_triangulation, "refine_points": evaluate_refinement},
)

__all__ = ["PIPELINE", "SAMPLE_SIZE", "CANDIDATE_NAMES", "DegenerateInput", "TooFewMatches", "CollinearPoints",
           "CoplanarPoints",
           "ZeroBaseline", "MissingIntrinsics", "FeatureDetection", "Matching", "RansacFundamental", "EpipolarDrawing",
           "RefinedPose", "Reconstruction", "enforce_rank2", "eight_point", "sampson_distance", "epipolar_distances",
           "symmetric_epipolar_distance", "epipolar_lines", "epipoles", "essential_candidates", "cheirality_counts",
           "nearest_neighbours", "nearest_neighbours_reference", "clip_lines", "detect_features", "match_features",
           "estimate_fundamental_8point",
           "estimate_fundamental_ransac", "compute_epipolar_lines", "estimate_essential", "decompose_essential",
           "recover_pose", "refine_pose", "triangulate", "refine_points", "evaluate_matches", "evaluate_fundamental",
           "evaluate_fundamental_8point", "evaluate_essential", "evaluate_candidates", "evaluate_pose",
           "evaluate_refined_pose",
           "evaluate_triangulation", "evaluate_refinement"]
