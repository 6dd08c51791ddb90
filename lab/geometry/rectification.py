"""Stereo rectification of a calibrated pair: Bouguet's algorithm, as ``cv2.stereoRectify`` computes it.

A calibrated pair (:class:`StereoCalibration`) relates its cameras by OpenCV's convention
``X_right = R X_left + T`` (``cv2.stereoCalibrate``): a right camera ``B`` metres to the right of
the left one has ``T = (-B, 0, 0)``. Rectification turns both cameras about their centres so that
they share one orientation whose x axis is the baseline, and gives them one camera matrix: then
every epipolar line is an image row, and a point at depth ``Z`` (in the rectified left frame) lies
``d = f B / Z`` pixels further left in the right image.

Bouguet's construction (the Camera Calibration Toolbox for Matlab, implemented by OpenCV):

1. split the relative rotation in two halves, ``r = rodrigues(-rodrigues(R) / 2)``, so that each
   camera turns by half: ``R_left' = r^T``, ``R_right' = r`` bring both to the mean orientation,
   where the baseline is ``t = r T``;
2. turn both by the smallest rotation ``w`` taking ``t`` onto the x axis (``u = (+-1, 0, 0)``,
   axis ``t x u``, angle ``acos(|t_x| / |t|)``): ``R1 = w r^T``, ``R2 = w r``;
3. both new cameras get the focal length ``f = (fy_left + fy_right) / 2`` and a principal point that
   keeps the centre of the image in view (the mean of the image's four corners, undistorted and
   turned, lands at the image centre); with ``zero_disparity`` (OpenCV's CALIB_ZERO_DISPARITY,
   the default) both get the mean of the two principal points, so points at infinity have
   disparity 0; otherwise only the rows' ``cy`` is shared.

``P1 = K [I | 0]`` and ``P2 = K [I | (T_x', 0, 0)]`` with ``T' = R2 T`` project rectified-left-frame
points; ``Q`` maps ``(x, y, d, 1)`` to homogeneous 3D points. The images are resampled with
:func:`rectification_map` (``cv2.initUndistortRectifyMap``) and ``cv2.remap``.

Reference: J.-Y. Bouguet, Camera Calibration Toolbox for Matlab, ``rectify_stereo_pair.m``;
G. Bradski and A. Kaehler, *Learning OpenCV* (2008), chapter 12, "Stereo rectification"
(Bouguet's algorithm); A. Fusiello, E. Trucco, A. Verri, "A compact algorithm for rectification of
stereo pairs", Machine Vision and Applications 12 (2000) (the same idea, in one rotation);
OpenCV's ``cvStereoRectify`` (calib3d/src/calibration.cpp). Only OpenCV's default scaling
(``alpha = -1``: no zoom to valid pixels) is reproduced.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lab.core.errors import InvalidValue
from lab.geometry.camera import (as_distortion, as_intrinsics, normalized_to_pixels, pixels_to_normalized,
                                 undistort, undistortion_map)
from lab.geometry.rotations import matrix_to_rotvec, nearest_rotation, rotvec_to_matrix


def _matrix(value: object, name: str, shape: tuple[int, ...]) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidValue(name, f"cannot be read as numbers: {value!r}") from None
    if array.size != int(np.prod(shape)):
        raise InvalidValue(name, f"expected {int(np.prod(shape))} numbers (shape {shape}), "
                                 f"got shape {array.shape}")
    array = array.reshape(shape)
    if not np.all(np.isfinite(array)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    return array


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """A calibrated stereo pair, in the convention of ``cv2.stereoCalibrate``.

    ``K_left``, ``K_right`` ``(3, 3)`` camera matrices; ``dist_left``, ``dist_right`` ``(5,)``
    OpenCV distortion (k1, k2, p1, p2, k3); ``R`` ``(3, 3)`` and ``T`` ``(3,)`` (metres) take
    left-camera coordinates to right-camera coordinates, ``X_right = R X_left + T``. A right
    camera ``B`` metres to the right of the left one has ``T = (-B, 0, 0)``.
    """

    K_left: np.ndarray
    dist_left: np.ndarray
    K_right: np.ndarray
    dist_right: np.ndarray
    R: np.ndarray
    T: np.ndarray

    def __post_init__(self) -> None:
        for side in ("left", "right"):
            try:
                K = as_intrinsics(_matrix(getattr(self, f"K_{side}"), f"K_{side}", (3, 3)))
            except InvalidValue as exc:
                raise InvalidValue(f"K_{side}", exc.reason) from None
            object.__setattr__(self, f"K_{side}", K)
            try:
                object.__setattr__(self, f"dist_{side}", as_distortion(getattr(self, f"dist_{side}")))
            except InvalidValue as exc:
                raise InvalidValue(f"dist_{side}", exc.reason) from None
        R = _matrix(self.R, "R", (3, 3))
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise InvalidValue("R", "is not a rotation matrix (R R^T = I, det R = +1)")
        object.__setattr__(self, "R", nearest_rotation(R))
        T = _matrix(self.T, "T", (3,))
        if np.linalg.norm(T) == 0.0:
            raise InvalidValue("T", "the baseline is zero: both cameras sit at the same place, so depth "
                                    "cannot be triangulated")
        object.__setattr__(self, "T", T)

    @property
    def baseline(self) -> float:
        """Distance between the camera centres, ``|T|`` (metres)."""
        return float(np.linalg.norm(self.T))

    @classmethod
    def rectified(cls, K: np.ndarray, baseline: float, *, disparity_offset: float = 0.0) -> StereoCalibration:
        """The calibration of a pair that is rectified already (Middlebury's ``calib.txt``).

        Both cameras share ``K`` except the right principal point, ``disparity_offset`` pixels to
        the right (Middlebury's ``doffs``), and the right camera sits ``baseline`` metres along the
        left's x axis: ``R = I``, ``T = (-baseline, 0, 0)``, no distortion.
        """
        K = as_intrinsics(K)
        baseline = float(baseline)
        if not np.isfinite(baseline) or baseline <= 0.0:
            raise InvalidValue("baseline", f"must be a positive distance in metres, got {baseline!r}")
        if not np.isfinite(disparity_offset):
            raise InvalidValue("disparity_offset", f"must be finite, got {disparity_offset!r}")
        K_right = K.copy()
        K_right[0, 2] += float(disparity_offset)
        return cls(K, np.zeros(5), K_right, np.zeros(5), np.eye(3), np.array([-baseline, 0.0, 0.0]))

    def is_rectified(self, *, tolerance: float = 1e-9) -> bool:
        """True when the images are rectified already: no rotation between the cameras, the right one
        straight to the right of the left (``T = (-B, 0, 0)``), no distortion, and equal focal
        lengths, skew and ``cy`` (the principal points may differ along x: see :meth:`rectified`)."""
        T = self.T
        B = np.linalg.norm(T)
        return bool(np.allclose(self.R, np.eye(3), atol=tolerance) and T[0] < 0
                    and abs(T[1]) <= tolerance * B and abs(T[2]) <= tolerance * B
                    and not np.any(self.dist_left) and not np.any(self.dist_right)
                    and np.allclose(self.K_left[:2, :2], self.K_right[:2, :2], rtol=tolerance, atol=0.0)
                    and abs(self.K_left[1, 2] - self.K_right[1, 2])
                    <= tolerance * max(1.0, abs(self.K_left[1, 2])))


@dataclass(frozen=True, eq=False)
class StereoRectification:
    """What :func:`stereo_rectify` returns (the outputs of ``cv2.stereoRectify``).

    ``R_left``, ``R_right`` ``(3, 3)``: rectifying rotations, camera frame -> rectified frame;
    ``P_left``, ``P_right`` ``(3, 4)``: projections of the rectified cameras, in the rectified
    left frame; ``Q`` ``(4, 4)``: ``(x, y, d, 1) -> (X, Y, Z, W)``; ``vertical``: True when the
    baseline is mostly vertical (the images are rectified to share columns, not rows).
    """

    R_left: np.ndarray
    R_right: np.ndarray
    P_left: np.ndarray
    P_right: np.ndarray
    Q: np.ndarray
    vertical: bool = False

    @property
    def K(self) -> np.ndarray:
        """The rectified left camera matrix ``P_left[:, :3]``."""
        return self.P_left[:, :3].copy()

    @property
    def K_right(self) -> np.ndarray:
        return self.P_right[:, :3].copy()

    @property
    def baseline(self) -> float:
        """Distance between the camera centres (metres), from ``P_right``."""
        axis = 1 if self.vertical else 0
        return float(abs(self.P_right[axis, 3] / self.P_right[axis, axis]))

    @property
    def disparity_offset(self) -> float:
        """``cx_right - cx_left`` (or ``cy`` for a vertical pair): 0 with zero-disparity rectification."""
        axis = 1 if self.vertical else 0
        return float(self.P_right[axis, 2] - self.P_left[axis, 2])


def relative_pose(R_a: np.ndarray, t_a: np.ndarray, R_b: np.ndarray,
                  t_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, T)`` with ``X_b = R X_a + T`` for two world-to-camera poses ``X_a = R_a X + t_a``,
    ``X_b = R_b X + t_b``.

    ``R = R_b R_a^T``, ``T = t_b - R t_a`` (what ``cv2.stereoCalibrate`` returns for a pair).
    """
    R_a, R_b = _matrix(R_a, "R_a", (3, 3)), _matrix(R_b, "R_b", (3, 3))
    t_a, t_b = _matrix(t_a, "t_a", (3,)), _matrix(t_b, "t_b", (3,))
    R = R_b @ R_a.T
    return R, t_b - R @ t_a


def stereo_rectify(K_left: np.ndarray, dist_left: np.ndarray | None, K_right: np.ndarray,
                   dist_right: np.ndarray | None, size: tuple[int, int], R: np.ndarray, T: np.ndarray, *,
                   zero_disparity: bool = True) -> StereoRectification:
    """Rectifying rotations and projections of a calibrated pair (Bouguet's algorithm, module docstring).

    ``size`` is ``(width, height)`` of both images; ``R``, ``T`` as in :class:`StereoCalibration`.
    Corresponds to ``cv2.stereoRectify(K_left, dist_left, K_right, dist_right, size, R, T,
    flags=cv2.CALIB_ZERO_DISPARITY if zero_disparity else 0, alpha=-1)``; the image corners are
    undistorted by Newton's method (:func:`lab.geometry.camera.undistort`) where OpenCV runs five
    fixed-point iterations, so the principal points differ slightly under strong distortion.
    """
    K_left, K_right = as_intrinsics(K_left), as_intrinsics(K_right)
    dists = (as_distortion(dist_left), as_distortion(dist_right))
    R = _matrix(R, "R", (3, 3))
    T = _matrix(T, "T", (3,))
    width, height = int(size[0]), int(size[1])
    if width < 2 or height < 2:
        raise InvalidValue("size", f"must be a (width, height) of at least 2 x 2 pixels, got {size}")
    if np.linalg.norm(T) == 0.0:
        raise InvalidValue("T", "the baseline is zero: the cameras coincide and cannot be rectified")

    half = rotvec_to_matrix(-0.5 * matrix_to_rotvec(R))  # r: turns the right camera half-way back
    t = half @ T
    axis = 0 if abs(t[0]) > abs(t[1]) else 1
    target = np.zeros(3)
    target[axis] = 1.0 if t[axis] > 0 else -1.0
    cross = np.cross(t, target)
    norm = np.linalg.norm(cross)
    turn = np.eye(3)
    if norm > 0.0:
        angle = np.arccos(np.clip(abs(t[axis]) / np.linalg.norm(t), -1.0, 1.0))
        turn = rotvec_to_matrix(cross * (angle / norm))
    R_left = turn @ half.T
    R_right = turn @ half
    t_new = R_right @ T

    other = 1 - axis  # the focal length along the common rows (columns for a vertical pair)
    focal = 0.5 * (K_left[other, other] + K_right[other, other])
    corners = np.array([[0.0, 0.0], [width - 1.0, 0.0], [0.0, height - 1.0], [width - 1.0, height - 1.0]])
    centres = []
    for K, dist, rotation in ((K_left, dists[0], R_left), (K_right, dists[1], R_right)):
        rays = np.concatenate([undistort(pixels_to_normalized(corners, K), dist), np.ones((4, 1))], axis=1)
        turned = rays @ rotation.T
        projected = focal * turned[:, :2] / turned[:, 2:3]
        centres.append(np.array([(width - 1) / 2.0, (height - 1) / 2.0]) - projected.mean(axis=0))
    if zero_disparity:
        centres = [0.5 * (centres[0] + centres[1])] * 2
    else:
        shared = 0.5 * (centres[0][other] + centres[1][other])
        for c in centres:
            c[other] = shared

    P_left = np.array([[focal, 0.0, centres[0][0], 0.0], [0.0, focal, centres[0][1], 0.0],
                       [0.0, 0.0, 1.0, 0.0]])
    P_right = np.array([[focal, 0.0, centres[1][0], 0.0], [0.0, focal, centres[1][1], 0.0],
                        [0.0, 0.0, 1.0, 0.0]])
    P_right[axis, 3] = t_new[axis] * focal
    Q = np.array([[1.0, 0.0, 0.0, -centres[0][0]],
                  [0.0, 1.0, 0.0, -centres[0][1]],
                  [0.0, 0.0, 0.0, focal],
                  [0.0, 0.0, -1.0 / t_new[axis], (centres[0][axis] - centres[1][axis]) / t_new[axis]]])
    return StereoRectification(R_left, R_right, P_left, P_right, Q, vertical=axis == 1)


def rectify_pixels(pixels: np.ndarray, K: np.ndarray, dist: np.ndarray | None, R_rect: np.ndarray,
                   P: np.ndarray) -> np.ndarray:
    """Where pixels ``(..., 2)`` of a photo land in its rectified image: undistort, turn by ``R_rect``, apply
    ``P[:, :3]``.

    Corresponds to ``cv2.undistortPoints(pixels, K, dist, R=R_rect, P=P)``.
    """
    normalized = undistort(pixels_to_normalized(pixels, K), dist)
    rays = np.concatenate([normalized, np.ones((*normalized.shape[:-1], 1))], axis=-1) @ np.asarray(R_rect).T
    with np.errstate(divide="ignore", invalid="ignore"):
        turned = rays[..., :2] / rays[..., 2:3]
    return normalized_to_pixels(turned, np.asarray(P, dtype=np.float64)[:, :3])


def rectification_map(K: np.ndarray, dist: np.ndarray | None, R_rect: np.ndarray, P: np.ndarray,
                      size: tuple[int, int]) -> np.ndarray:
    """For every pixel of the rectified image, the pixel of the photo to sample, ``(height, width, 2)``.

    :func:`lab.geometry.camera.undistortion_map` with ``K_new = P[:, :3]`` and the rectifying
    rotation; corresponds to ``cv2.initUndistortRectifyMap(K, dist, R_rect, P, size, cv2.CV_32FC1)``.
    """
    return undistortion_map(K, dist, size, K_new=np.asarray(P, dtype=np.float64)[:, :3], R=R_rect)


__all__ = ["StereoCalibration", "StereoRectification", "rectification_map", "rectify_pixels", "relative_pose",
           "stereo_rectify"]
