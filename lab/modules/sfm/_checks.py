"""Checks of the SfM steps' inputs: each returns the value in the form the math uses or raises
:class:`~lab.core.InvalidValue` naming the input."""

from __future__ import annotations

from typing import Any

import numpy as np

from lab.core import ImageSet, InvalidValue, Points2D
from lab.data.reconstruction import SparseModel


def check_images(images: Any) -> ImageSet:
    """An :class:`ImageSet` of at least two images."""
    if not isinstance(images, ImageSet):
        raise InvalidValue("images", f"expected an ImageSet, got {type(images).__name__}")
    if len(images) < 2:
        raise InvalidValue("images", f"structure from motion needs at least two images, got {len(images)}")
    return images


def check_keypoints(keypoints: Any, views: int | None = None) -> Points2D:
    """:class:`Points2D` with a view per keypoint, the views in ``[0, views)`` when given."""
    if not isinstance(keypoints, Points2D) or keypoints.view is None:
        raise InvalidValue("keypoints", "expected Points2D with a view per keypoint")
    if views is not None and len(keypoints) and (keypoints.view.min() < 0 or keypoints.view.max() >= views):
        raise InvalidValue("keypoints", f"keypoint views must lie in [0, {views})")
    return keypoints


def keypoint_views(keypoints: Points2D) -> np.ndarray:
    """The view of every keypoint ``(N,)`` (checked keypoints always have one)."""
    assert keypoints.view is not None
    return keypoints.view


def check_matches(value: Any, name: str, keypoints: Points2D) -> np.ndarray:
    """``(M, 4)`` int64 rows ``(view a, view b, keypoint a, keypoint b)`` with keypoints in range."""
    m = np.asarray(value)
    if m.ndim != 2 or m.shape[1] != 4 or (len(m) and not np.issubdtype(m.dtype, np.integer)):
        raise InvalidValue(name,
                           f"expected (M, 4) integer rows (view a, view b, keypoint a, keypoint b), got "
                           f"{m.shape} {m.dtype}")
    m = m.astype(np.int64)
    if len(m) and (m[:, 2:].min() < 0 or m[:, 2:].max() >= len(keypoints)):
        raise InvalidValue(name, f"keypoint indices must lie in [0, {len(keypoints)})")
    return m


def check_pair(initial_pair: Any, views: int) -> tuple[int, int]:
    """The two different views ``(a, b)`` of ``initial_pair``."""
    pair = np.asarray(initial_pair).reshape(-1)
    if pair.shape != (2,) or not np.issubdtype(pair.dtype, np.integer) or pair.min() < 0 \
            or pair.max() >= views \
            or pair[0] == pair[1]:
        raise InvalidValue("initial_pair",
                           f"expected two different image indices in [0, {views}), got {pair}")
    return int(pair[0]), int(pair[1])


def check_track_of(value: Any, keypoints: Points2D, name: str = "track_of") -> np.ndarray:
    """``(N,)`` int64 track ids, one per keypoint."""
    track_of = np.asarray(value)
    if track_of.shape != (len(keypoints),) or not np.issubdtype(track_of.dtype, np.integer):
        raise InvalidValue(name, f"expected ({len(keypoints)},) integer track ids, got {track_of.shape}")
    return track_of.astype(np.int64)


def check_descriptors(descriptors: Any, keypoints: Points2D) -> np.ndarray:
    """``(N, D)`` descriptors, one row per keypoint."""
    descriptors = np.asarray(descriptors)
    if descriptors.ndim != 2 or len(descriptors) != len(keypoints):
        raise InvalidValue("descriptors",
                           f"expected one row per keypoint ({len(keypoints)}), got {descriptors.shape}")
    return descriptors


def check_model(model: Any, name: str) -> SparseModel:
    """A :class:`SparseModel` with at least one registered view."""
    if not isinstance(model, SparseModel):
        raise InvalidValue(name, f"expected a SparseModel, got {type(model).__name__}")
    if not model.registered.any():
        raise InvalidValue(name, "the model has no registered view")
    return model
