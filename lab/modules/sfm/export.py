"""The session's reconstruction in the interchange form of :mod:`lab.data.reconstruction` (COLMAP, transforms.json)."""

from __future__ import annotations

from typing import Any

import numpy as np

from lab.core import ImageSet, InvalidValue
from lab.data.reconstruction import Reconstruction
from lab.modules.sfm._checks import check_images, check_keypoints, check_track_of, keypoint_views
from lab.modules.sfm.model import model_from, observation_errors, point_colors


def reconstruction_from_state(state: dict[str, Any]) -> Reconstruction:
    """The session's reconstruction as a :class:`lab.data.reconstruction.Reconstruction` (for COLMAP, PLY ...).

    Uses the most refined stage present: bundle-adjusted, else filtered, else incremental, else the
    two-view model. Only registered images are exported; keypoint indices are per image.
    """
    images: ImageSet = check_images(state.get("images"))
    keypoints = check_keypoints(state.get("keypoints"), len(images))
    view = keypoint_views(keypoints)
    track_of = check_track_of(state.get("track_of"), keypoints)
    if "model_track_of" in state and "points" in state:  # every stage after the incremental one
        track_of = check_track_of(state["model_track_of"], keypoints)
    K = np.asarray(state["K"], dtype=np.float64)
    if "adjusted_points" in state:
        model = model_from(state["adjusted_poses"], state["registered"], state["adjusted_points"],
                           state["filtered_point_tracks"], len(images), keypoints, state["filtered_observed"])
        K = state["adjusted_K"]
    elif "filtered_points" in state:
        model = model_from(state["poses"], state["registered"], state["filtered_points"],
                           state["filtered_point_tracks"], len(images), keypoints, state["filtered_observed"])
    elif "points" in state:
        model = model_from(state["poses"], state["registered"], state["points"], state["point_tracks"], len(images),
                           keypoints, state["observed"])
    elif "initial_points" in state:
        model = model_from(state["initial_poses"], state["initial_registered"], state["initial_points"],
                           state["initial_point_tracks"], len(images), keypoints)
    else:
        raise InvalidValue("state", "no reconstruction yet: run refine_initial_points or a later step first")
    K = np.asarray(K, dtype=np.float64)
    reg = np.flatnonzero(model.registered)
    new_index = np.full(len(images), -1)
    new_index[reg] = np.arange(len(reg))
    offsets = np.concatenate([[0], np.cumsum(np.bincount(view, minlength=len(images)))])
    order = np.argsort(view, kind="stable")
    local = np.empty(len(keypoints), dtype=np.int64)
    local[order] = np.arange(len(keypoints)) - offsets[view[order]]
    kp, views, point = model.observations(keypoints, track_of)
    errors = observation_errors(model, K, keypoints, kp, views, point)
    sort = np.lexsort((views, point))
    kp, views, point, errors = kp[sort], views[sort], point[sort], errors[sort]
    bounds = np.searchsorted(point, np.arange(len(model.points) + 1))
    tracks = tuple(np.column_stack([new_index[views[s:e]], local[kp[s:e]]]) for s, e in zip(bounds[:-1], bounds[1:]))
    point_errors = np.array([errors[s:e].mean() if e > s else 0.0 for s, e in zip(bounds[:-1], bounds[1:])])
    colors = np.round(255 * np.clip(point_colors(keypoints, model, track_of), 0, 1)).astype(np.uint8)
    names: list[str] = []
    for v in reg:
        name = "".join(c if not c.isspace() else "_" for c in (images[v].name or f"image_{v:03d}.png"))
        names.append(name if name not in names else f"{v:03d}_{name}")
    xy_by_view = [keypoints.xy[order[offsets[v]:offsets[v + 1]]] for v in reg]
    return Reconstruction(K=K[reg], sizes=np.array([[images[v].width, images[v].height] for v in reg]),
                          R=model.poses[reg, :, :3], t=model.poses[reg, :, 3], names=tuple(names),
                          keypoints=tuple(xy_by_view), xyz=model.points, colors=colors,
                          errors=np.where(np.isfinite(point_errors), point_errors, 0.0), tracks=tracks)
