"""Homogeneous coordinates, homographies and Hartley's normalization.

Every function is batched over leading dimensions: points are ``(..., N, d)``, transforms
``(..., d + 1, d + 1)``. Geometry is float64 (DESIGN.md section 3).
"""

from __future__ import annotations

import numpy as np

from lab.core.errors import InvalidValue


def _points(value: object, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim < 2 or array.shape[-1] < 1:
        raise InvalidValue(name, f"expected points of shape (..., N, d), got {array.shape}")
    return array


def to_homogeneous(points: np.ndarray) -> np.ndarray:
    """Append a coordinate 1: ``(..., N, d)`` -> ``(..., N, d + 1)`` (``cv2.convertPointsToHomogeneous``)."""
    p = _points(points, "points")
    return np.concatenate([p, np.ones((*p.shape[:-1], 1))], axis=-1)


def from_homogeneous(points: np.ndarray) -> np.ndarray:
    """Divide by the last coordinate: ``(..., N, d + 1)`` -> ``(..., N, d)``
    (``cv2.convertPointsFromHomogeneous``).

    Points at infinity (last coordinate 0) become infinite, as in OpenCV.
    """
    p = _points(points, "points")
    if p.shape[-1] < 2:
        raise InvalidValue("points", f"homogeneous points need at least 2 coordinates, got {p.shape[-1]}")
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[..., :-1] / p[..., -1:]


def apply_homography(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map points ``(..., N, d)`` by projective transforms ``(..., d + 1, d + 1)``: ``x' ~ H x``.

    ``H`` broadcasts against the leading dimensions of ``points`` (``cv2.perspectiveTransform``).
    """
    H = np.asarray(H, dtype=np.float64)
    p = _points(points, "points")
    d = p.shape[-1]
    if H.shape[-2:] != (d + 1, d + 1):
        raise InvalidValue("H", f"expected shape (..., {d + 1}, {d + 1}) for {d}-D points, got {H.shape}")
    mapped = np.einsum("...ij,...nj->...ni", H[..., :, :d], p) + H[..., None, :, d]
    with np.errstate(divide="ignore", invalid="ignore"):
        return mapped[..., :d] / mapped[..., d:]


def hartley_normalization(points: np.ndarray,
                          mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Similarity ``T`` moving the centroid to the origin and the mean distance to ``sqrt(d)``.

    Args:
        points: ``(..., N, d)`` points (d = 2 for image points: mean distance sqrt(2)).
        mask: optional ``(..., N)`` booleans; only the points marked True define ``T`` (padding
            rows of a batch of point sets with different sizes are left out this way).

    Returns:
        ``T`` ``(..., d + 1, d + 1)`` and the normalized points ``(..., N, d)`` (``T`` applied to all).

    Reference: Hartley & Zisserman, Multiple View Geometry (2nd ed.), section 4.4.4 and
    algorithm 4.2; R. Hartley, "In defense of the eight-point algorithm", TPAMI 19(6), 1997.
    """
    p = _points(points, "points")
    d = p.shape[-1]
    weights = np.ones(p.shape[:-1]) if mask is None else np.asarray(mask, dtype=np.float64)
    if weights.shape != p.shape[:-1]:
        raise InvalidValue("mask", f"expected shape {p.shape[:-1]}, got {weights.shape}")
    count = weights.sum(axis=-1)
    if np.any(count < 1):
        raise InvalidValue("points", "cannot normalize an empty point set")
    centroid = np.einsum("...n,...nd->...d", weights, p) / count[..., None]
    centred = p - centroid[..., None, :]
    mean_distance = np.einsum("...n,...n->...", weights, np.linalg.norm(centred, axis=-1)) / count
    if np.any(mean_distance <= 1e-300):
        raise InvalidValue("points", "all points coincide: they cannot be normalized")
    scale = np.sqrt(d) / mean_distance
    T = np.zeros((*p.shape[:-2], d + 1, d + 1))
    idx = np.arange(d)
    T[..., idx, idx] = scale[..., None]
    T[..., :d, d] = -scale[..., None] * centroid
    T[..., d, d] = 1.0
    return T, centred * scale[..., None, None]


__all__ = ["apply_homography", "from_homogeneous", "hartley_normalization", "to_homogeneous"]
