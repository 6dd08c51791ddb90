"""Rectification helpers: resample a calibrated pair, and measure how far the rows of a pair disagree.

The rectifying rotations come from :func:`lab.geometry.rectification.stereo_rectify` (Bouguet's
algorithm); :func:`lab.modules.stereo.rectify_pair` is the step.
"""

from __future__ import annotations

import numpy as np

from lab.core import Image, InvalidValue
from lab.geometry.rectification import StereoCalibration, StereoRectification, rectification_map
from lab.modules.stereo._checks import check_pair


def remap_pair(left_raw: Image, right_raw: Image, calibration: StereoCalibration,
               rect: StereoRectification) -> tuple[Image, Image]:
    """Both photos resampled into the rectified cameras: each rectified pixel mapped back through the rotation
    and the lens distortion (:func:`rectification_map`, as ``cv2.initUndistortRectifyMap``) and sampled
    bilinearly (``cv2.remap``, black outside)."""
    import cv2

    width, height = left_raw.width, left_raw.height
    images = []
    for image, K, dist, R_rect, P in ((left_raw, calibration.K_left, calibration.dist_left, rect.R_left,
                                       rect.P_left),
                                      (right_raw, calibration.K_right, calibration.dist_right, rect.R_right,
                                       rect.P_right)):
        mapping = rectification_map(K, dist, R_rect, P, (width, height)).astype(np.float32)
        pixels = cv2.remap(image.pixels, mapping[..., 0], mapping[..., 1], interpolation=cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        images.append(Image(np.clip(pixels, 0.0, 1.0), name=f"{image.name or 'image'} (rectified)"))
    return images[0], images[1]


def check_rows(left: Image, right: Image, max_row_error: float) -> tuple[float, tuple[str, ...]]:
    """A pair declared rectified: its rows' disagreement (:func:`row_misalignment`) and the warnings;
    refuses (:class:`InvalidValue` on ``calibration``) a pair whose rows disagree by more than
    ``max_row_error`` px."""
    error, count = row_misalignment(left, right)
    if error > max_row_error:
        raise InvalidValue("calibration", f"the pair is not rectified: its rows disagree by up to "
                                          f"{error:.1f} px (more than {max_row_error} px, fitted to {count} "
                                          "matched features), but its calibration says it is rectified; give "
                                          "the full stereo calibration (K, distortion, R, T of both cameras) "
                                          "so the pair can be rectified")
    return error, () if error >= 0 else ("too few features to check that the rows of the pair agree",)


def row_misalignment(left: Image, right: Image, *, max_features: int = 3000) -> tuple[float, int]:
    """How far rows of the pair disagree: ``(largest vertical offset over the image in px, matches)``.

    ORB features (``cv2.ORB.create``, away from the black borders a rectification leaves) are
    matched by Hamming distance with a cross check; the
    vertical offsets ``y_right - y_left`` of the matches are fitted (least squares, outliers
    trimmed) by ``a + b u + c v + e u v`` over normalized image coordinates, which captures a
    shift, a rotation, a scale and the keystone of verged cameras; the result is the largest
    offset that model predicts at the centre and the corners of the region the features cover
    (5 % to 95 % of them along each axis). A rectified pair gives a fraction of a pixel. Returns
    ``(-1.0, matches)`` when fewer than 50 matches fit (too little texture to tell).
    """
    import cv2

    left, right = check_pair(left, right)
    orb = cv2.ORB.create(nfeatures=int(max_features))
    found = []
    for image in (left, right):
        gray = np.clip(image.gray() * 255.0 + 0.5, 0, 255).astype(np.uint8)
        inside = cv2.erode((gray > 0).astype(np.uint8), np.ones((31, 31), np.uint8))  # not at black borders
        found.append(orb.detectAndCompute(gray, inside))
    (points_l, descriptors_l), (points_r, descriptors_r) = found
    if descriptors_l is None or descriptors_r is None:
        return -1.0, 0
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(descriptors_l, descriptors_r)
    if len(matches) < 20:
        return -1.0, len(matches)
    xy_l = np.array([points_l[m.queryIdx].pt for m in matches])
    xy_r = np.array([points_r[m.trainIdx].pt for m in matches])
    half_w, half_h = (left.width - 1) / 2.0, (left.height - 1) / 2.0
    u, v = (xy_l[:, 0] - half_w) / left.width, (xy_l[:, 1] - half_h) / left.height
    design = np.stack([np.ones_like(u), u, v, u * v], axis=1)
    offsets = xy_r[:, 1] - xy_l[:, 1]
    keep = np.abs(offsets) < 0.1 * left.height  # a wrong match lands anywhere
    coefficients = np.zeros(4)
    for _ in range(5):
        if keep.sum() < 10:
            return -1.0, len(matches)
        coefficients = np.linalg.lstsq(design[keep], offsets[keep], rcond=None)[0]
        residual = np.abs(design @ coefficients - offsets)
        keep = residual < max(1.0, 3.0 * 1.4826 * float(np.median(residual[keep])))
    if keep.sum() < 50:
        return -1.0, len(matches)
    (u0, u1), (v0, v1) = np.quantile(u[keep], [0.05, 0.95]), np.quantile(v[keep], [0.05, 0.95])
    probes = np.array([[1.0, 0.5 * (u0 + u1), 0.5 * (v0 + v1), 0.25 * (u0 + u1) * (v0 + v1)]]
                      + [[1.0, a, b, a * b] for a in (u0, u1) for b in (v0, v1)])  # no extrapolation
    return float(np.abs(probes @ coefficients).max()), len(matches)
