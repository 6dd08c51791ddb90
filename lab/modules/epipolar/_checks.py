"""Errors and input checks shared by the epipolar steps: degenerate input gets a clear error, never a wrong
answer."""

from __future__ import annotations

from typing import Any

import numpy as np

from lab.core import ImageSet, InvalidValue, StepFailed
from lab.geometry.camera import as_intrinsics

#: Correspondences per minimal sample of the 8-point algorithm.
SAMPLE_SIZE = 8


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


def check_pair(x1: Any, x2: Any, *, minimum: int = SAMPLE_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """``x1``, ``x2`` as finite ``(M, 2)`` float arrays of equal length, at least ``minimum`` rows."""
    arrays = []
    for name, value in (("x1", x1), ("x2", x2)):
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise InvalidValue(name, "cannot be read as an (M, 2) array of pixels "
                                     f"({type(value).__name__})") from None
        if array.ndim != 2 or array.shape[1] != 2:
            raise InvalidValue(name, f"expected shape (M, 2), got {array.shape}")
        bad = ~np.all(np.isfinite(array), axis=1)
        if bad.any():
            raise InvalidValue(name, f"{int(bad.sum())} of {len(array)} points contain NaN or infinite "
                                     f"coordinates (first at row {int(np.argmax(bad))}); remove them first")
        arrays.append(array)
    if len(arrays[0]) != len(arrays[1]):
        raise InvalidValue("x2", f"x1 has {len(arrays[0])} points and x2 {len(arrays[1])}: one per match in "
                                 "each")
    if len(arrays[0]) < minimum:
        needs = "the 8-point algorithm needs" if minimum == SAMPLE_SIZE else "this step needs"
        raise TooFewMatches("x1", f"{len(arrays[0])} matches; {needs} at least {minimum} (detect more "
                                  "features: lower the contrast threshold, raise the ratio)")
    return arrays[0], arrays[1]


def inliers_or_all(inliers: Any, count: int) -> np.ndarray:
    if inliers is None:
        return np.ones(count, dtype=bool)
    mask = np.asarray(inliers)
    if mask.shape != (count,) or mask.dtype.kind not in "bi":
        raise InvalidValue("inliers", f"expected ({count},) booleans, one per match, got {mask.dtype} "
                                      f"{mask.shape}")
    return mask.astype(bool)


def check_matrix(value: Any, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != (3, 3):
        raise InvalidValue(name, f"expected a (3, 3) matrix, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    if not np.any(array):
        raise InvalidValue(name, "is all zeros")
    return array


def check_pose(value: Any) -> tuple[np.ndarray, np.ndarray]:
    pose = np.asarray(value, dtype=np.float64)
    if pose.shape != (3, 4):
        raise InvalidValue("pose", f"expected a (3, 4) [R | t], got shape {pose.shape}")
    return check_rotation_translation(pose[:, :3], pose[:, 3], "pose")


def check_rotation_translation(R: Any, t: Any, name: str = "R") -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or t.shape != (3,) or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise InvalidValue(name, f"expected a finite rotation (3, 3) and translation (3,), got {R.shape} and "
                                 f"{t.shape}")
    problem = rotation_problem(R)
    if problem:
        raise InvalidValue(name, f"{problem} (a rotation has R^T R = I and det R = +1)")
    return R, t


def rotation_problem(R: np.ndarray) -> str | None:
    """Why the finite ``(3, 3)`` ``R`` is no rotation, naming its value ("R has det -1: a reflection, not a
    rotation"), or None."""
    error = float(np.abs(R @ R.T - np.eye(3)).max())
    if error > 1e-6:
        return f"R is not orthonormal (R R^T differs from I by up to {error:.3g})"
    det = float(np.linalg.det(R))
    if det < 0:
        return f"R has det {det:.3g}: a reflection, not a rotation"
    return None


def check_two_images(images: Any) -> ImageSet:
    if not isinstance(images, ImageSet) or len(images) != 2:
        count = len(images) if isinstance(images, ImageSet) else type(images).__name__
        raise InvalidValue("images", f"epipolar geometry needs exactly two images, got {count}")
    return images


def intrinsics_for(images: ImageSet, K1: Any, K2: Any) -> tuple[np.ndarray, np.ndarray]:
    if K1 is None or K2 is None:
        sizes = [f"{im.width}x{im.height}" for im in images.images] if isinstance(images, ImageSet) else []
        if len(sizes) == 2 and sizes[0] != sizes[1]:
            raise MissingIntrinsics("K1", f"the two images have different sizes ({sizes[0]} and {sizes[1]}) "
                                          "and no K was given, so no common camera can be assumed: give K1 "
                                          "and K2 (a K file or fx, fy, cx, cy)")
        raise MissingIntrinsics("K1", "no camera matrix: E needs K1 and K2 (give a K file or fx, fy, cx, cy)")
    return as_intrinsics(K1), as_intrinsics(K2)
