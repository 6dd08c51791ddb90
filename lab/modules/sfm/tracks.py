"""Tracks: verified matches joined into tracks, then continued, completed and merged as the model grows.

:func:`connected_tracks` builds the tracks of :func:`~lab.modules.sfm.build_tracks` (connected
components of the match graph, inconsistent ones split by :func:`split_inconsistent`). The rest is
COLMAP's incremental triangulator (Schönberger and Frahm, "Structure-from-Motion Revisited", CVPR
2016, section 4.5; ``IncrementalTriangulator`` in ``src/colmap/sfm/incremental_triangulator.cc``):
:func:`continue_tracks`, :func:`complete_and_merge` (:func:`complete_tracks`, :func:`merge_tracks`
on the candidates of the guided search :func:`guided_candidates`) and :func:`drop_two_view_points`.
They change a :class:`~lab.modules.sfm.model.GrowingModel` and ``track_of`` in place.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lab.core import Points2D
from lab.modules import epipolar
from lab.modules.sfm._checks import check_descriptors, keypoint_views
from lab.modules.sfm.model import GrowingModel, observation_errors, project

#: Per image, a k-d tree over its keypoints and their global indices (with a trailing -1 for "no neighbour").
KeypointTrees = dict[int, tuple[Any, np.ndarray]]
#: Rows ``(point, keypoint, error px)`` of the guided search.
Candidates = tuple[np.ndarray, np.ndarray, np.ndarray]


def unit_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """Descriptors scaled to unit length ``(N, D)`` float64 (SIFT's L2 normalization; zero rows stay zero)."""
    d = np.asarray(descriptors, dtype=np.float64)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def unit_descriptors_of(descriptors: Any, keypoints: Points2D) -> np.ndarray | None:
    """:func:`unit_descriptors` of an optional input, checked to have one row per keypoint (None stays
    None)."""
    if descriptors is None:
        return None
    return unit_descriptors(check_descriptors(descriptors, keypoints))


def split_inconsistent(edges: np.ndarray, view: np.ndarray, order: np.ndarray | None = None) -> np.ndarray:
    """Cut an inconsistent match graph into consistent tracks: a union-find that never joins two sets sharing
    a view.

    ``edges`` ``(E, 2)`` keypoint indices (local, ``0 .. n-1``), ``view`` ``(n,)`` the image of each
    keypoint, ``order`` the order in which the edges are tried (best first, e.g. by descriptor
    distance; default: as given). An edge whose two sets already see a common image is cut: it is
    the one that would put two keypoints of one image into one track. Every consistent part of the
    component survives (a plain chain through the component keeps all its edges); only the
    conflicting, weakest edges go. Returns ``(n,)`` labels ``0 .. n-1`` (the root of each set).

    This sequential loop runs on the keypoints of inconsistent components only (a few hundred
    edges). COLMAP reaches the same end by never adding a second observation of one image to a
    track (``IncrementalTriangulator``); Moulon and Monasse build tracks with the same union-find
    but drop a track that sees an image twice (what :func:`~lab.modules.sfm.build_tracks` did before).

    Reference: Schönberger and Frahm, "Structure-from-Motion Revisited", CVPR 2016, section 4.5;
    Moulon and Monasse, "Unordered feature tracking made fast and easy", CVMP 2012.
    """
    n = len(view)
    parent = list(range(n))
    seen = [1 << int(v) for v in view]  # views of each set as a bit mask (any number of views)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    order = np.arange(len(edges)) if order is None else np.asarray(order)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in edges[order].tolist():
        ra, rb = find(a), find(b)
        if ra == rb or seen[ra] & seen[rb]:
            continue
        parent[rb] = ra
        seen[ra] |= seen[rb]
    return np.array([find(i) for i in range(n)], dtype=np.int64)


def connected_tracks(keypoints: Points2D, m: np.ndarray,
                     unit: np.ndarray | None) -> tuple[np.ndarray, int, tuple[int, int, int, int]]:
    """The tracks of matches ``m`` (non-empty ``(M, 4)`` rows): ``track_of`` ``(N,)``, the number of
    tracks and the counts ``(inconsistent components, consistent tracks split from them, matches cut,
    keypoints dropped)``.

    Connected components of the match graph (``scipy.sparse.csgraph.connected_components``); the
    inconsistent ones (two keypoints in one image) are split best edge first (:func:`split_inconsistent`,
    by distance of the unit descriptors ``unit`` when given). Tracks are numbered 0 ..
    """
    import scipy.sparse
    from scipy.sparse.csgraph import connected_components

    view = keypoint_views(keypoints)
    n = len(keypoints)
    track_of = np.full(n, -1, dtype=np.int64)
    graph = scipy.sparse.coo_matrix((np.ones(len(m)), (m[:, 2], m[:, 3])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels)
    candidate = sizes[labels] >= 2
    # a component is consistent when its keypoints lie in distinct views
    stride = int(view.max()) + 1
    key = labels.astype(np.int64) * stride + view
    distinct = np.unique(key[candidate])
    views_per_label = np.bincount(distinct // stride, minlength=len(sizes))
    bad_label = (sizes >= 2) & (views_per_label < sizes)
    consistent = candidate & ~bad_label[labels]
    labels = labels.astype(np.int64)
    inconsistent = int(bad_label.sum())
    split, cut, dropped = 0, 0, 0
    if inconsistent:
        members = np.flatnonzero(bad_label[labels])
        local = np.full(n, -1, dtype=np.int64)
        local[members] = np.arange(len(members))
        edges = m[bad_label[labels[m[:, 2]]]][:, 2:]
        order = None
        if unit is not None:
            order = np.argsort(np.linalg.norm(unit[edges[:, 0]] - unit[edges[:, 1]], axis=1), kind="stable")
        root = split_inconsistent(local[edges], view[members], order)
        part = members[root]  # a keypoint index names each part, distinct from every component label
        part_sizes = np.bincount(root, minlength=len(members))
        keep = part_sizes[root] >= 2
        labels[members] = len(sizes) + part  # new labels beyond the components'
        consistent[members[keep]] = True
        split = len(np.unique(root[keep]))
        cut = int(np.sum(root[local[edges[:, 0]]] != root[local[edges[:, 1]]]))
        dropped = int(np.sum(~keep))
    kept, renumbered = np.unique(labels[consistent], return_inverse=True)
    track_of[consistent] = renumbered.reshape(-1)
    return track_of, len(kept), (inconsistent, split, cut, dropped)


def track_lengths(track_of: np.ndarray) -> np.ndarray:
    """Keypoints (images) in each track ``(T,)``."""
    return np.bincount(track_of[track_of >= 0], minlength=int(track_of.max()) + 1 if len(track_of) else 0)


def pair_observations(keypoints: Points2D, track_of: np.ndarray, a: int, b: int) -> tuple[np.ndarray, ...]:
    """Tracks seen in views ``a`` and ``b``: ``(tracks, keypoint in a, keypoint in b)``."""
    view = keypoint_views(keypoints)
    in_a = np.flatnonzero((view == a) & (track_of >= 0))
    in_b = np.flatnonzero((view == b) & (track_of >= 0))
    common, ia, ib = np.intersect1d(track_of[in_a], track_of[in_b], return_indices=True)
    return common, in_a[ia], in_b[ib]


def keypoint_trees(keypoints: Points2D, views: int) -> KeypointTrees:
    """One k-d tree per image over its keypoint locations (a location SIFT gave several keypoints is in it
    once: :func:`lab.modules.epipolar.keypoint_locations`, the keypoint matching uses), with their global
    indices: ``{view: (tree, index)}``."""
    from scipy.spatial import cKDTree

    view = keypoint_views(keypoints)
    location = epipolar.keypoint_locations(keypoints)
    trees = {}
    for v in range(views):
        index = np.flatnonzero((view == v) & (location == np.arange(len(location))))
        trees[v] = (cKDTree(keypoints.xy[index] if len(index) else np.zeros((0, 2))), np.append(index, -1))
    return trees


def correspondences_2d3d(model: GrowingModel, keypoints: Points2D, track_of: np.ndarray, view: int, *,
                         all_keypoints: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(keypoints, points)`` of ``view`` whose tracks have a point (the still-used ones, all if
    ``all_keypoints``)."""
    of_track = model.point_of_track(max(len(track_of) and int(track_of.max()) + 1, 1))
    used = model.observed | all_keypoints
    kp = np.flatnonzero((keypoint_views(keypoints) == view) & (track_of >= 0) & used)
    point = of_track[track_of[kp]] if len(kp) else np.zeros(0, dtype=np.int64)
    kp, point = kp[point >= 0], point[point >= 0]
    return kp, point


def continue_tracks(model: GrowingModel, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray, view: int,
                    *, max_error_px: float) -> int:
    """Track continuation: the new image's keypoints whose tracks already have a point become observations
    when they reproject within ``max_error_px`` under its refined pose (PnP outliers that fit it come back).

    Returns the observations the image adds. COLMAP's ``IncrementalTriangulator::Continue``.
    """
    kp, point = correspondences_2d3d(model, keypoints, track_of, view, all_keypoints=True)
    if not len(kp):
        return 0
    good = observation_errors(model, K, keypoints, kp, np.full(len(kp), view), point) <= max_error_px
    model.observed[kp] = good
    return int(good.sum())


def guided_candidates(model: GrowingModel, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray,
                      unit: np.ndarray | None, trees: KeypointTrees, sizes: np.ndarray, *,
                      max_error_px: float, max_descriptor_distance: float) -> Candidates:
    """Keypoints that may observe a point in a registered image where it has no observation yet.

    Every point is projected into every registered image its track does not observe; the keypoints
    within ``max_error_px`` of the projection (a k-d tree per image, ``scipy.spatial.cKDTree``)
    whose unit descriptor lies within ``max_descriptor_distance`` of one of the point's observations
    (compare COLMAP's matcher ``max_distance``) are candidates; without descriptors only a keypoint
    alone in that radius is. This is the guided search of H&Z algorithm 11.4 step (v) with the
    projection of the point as the search region: the correspondences the ratio test missed.

    Returns ``(point, keypoint, error px)`` rows, several per point possible.
    """
    empty = (np.zeros(0, dtype=np.int64),) * 2 + (np.zeros(0),)
    if not len(model.points):
        return empty
    kp, views, point = model.observations(keypoints, track_of)
    V = len(model.registered)
    seen = np.zeros((len(model.points), V), dtype=bool)
    seen[point, views] = True
    cams = np.flatnonzero(model.registered)
    pp, column = np.nonzero(~seen[:, cams])
    vv = cams[column]
    uv, depth = project(model, K, vv, pp)
    inside = (depth > 0) & np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= -0.5) & (uv[:, 1] >= -0.5) \
        & (uv[:, 0] <= sizes[vv, 0] - 0.5) & (uv[:, 1] <= sizes[vv, 1] - 0.5)
    pp, vv, uv = pp[inside], vv[inside], uv[inside]
    neighbours = 3 if unit is not None else 2
    found_p, found_k, found_e = [], [], []
    for v in np.unique(vv):
        rows = np.flatnonzero(vv == v)
        tree, index = trees[int(v)]
        if tree.n == 0:
            continue
        distance, nearest = tree.query(uv[rows], k=neighbours, distance_upper_bound=max_error_px)
        if unit is None:  # no descriptors: only an unambiguous keypoint
            alone = np.isfinite(distance[:, 0]) & ~np.isfinite(distance[:, 1])
            distance, nearest, rows = distance[alone, :1], nearest[alone, :1], rows[alone]
        hit = np.isfinite(distance)
        found_p.append(np.broadcast_to(pp[rows, None], hit.shape)[hit])
        found_k.append(index[nearest[hit]])
        found_e.append(distance[hit])
    if not found_p:
        return empty
    cp, ck, ce = np.concatenate(found_p), np.concatenate(found_k), np.concatenate(found_e)
    if unit is not None and len(cp):
        cp, ck, ce = _close_in_descriptor(cp, ck, ce, kp, point, unit, len(model.points),
                                          max_descriptor_distance)
    return cp, ck, ce


def _close_in_descriptor(cp: np.ndarray, ck: np.ndarray, ce: np.ndarray, kp: np.ndarray, point: np.ndarray,
                         unit: np.ndarray, num_points: int, max_distance: float) -> Candidates:
    """The candidates whose unit descriptor lies within ``max_distance`` of one of their point's
    observations."""
    order = np.argsort(point, kind="stable")
    obs_kp = kp[order]
    counts = np.bincount(point, minlength=num_points)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    n = counts[cp]
    has = n > 0
    cp, ck, ce, n = cp[has], ck[has], ce[has], n[has]
    pair = np.repeat(np.arange(len(cp)), n)
    offset = np.arange(len(pair)) - np.repeat(np.cumsum(n) - n, n)
    distance = np.linalg.norm(unit[ck[pair]] - unit[obs_kp[starts[cp][pair] + offset]], axis=1)
    best = np.minimum.reduceat(distance, np.cumsum(n) - n) if len(pair) else np.zeros(0)
    close = best <= max_distance
    return cp[close], ck[close], ce[close]


def complete_tracks(model: GrowingModel, keypoints: Points2D, track_of: np.ndarray,
                    candidates: Candidates) -> int:
    """Track completion: attach to each point the free keypoints of :func:`guided_candidates` (in place).

    A keypoint is free when it observes no point. Each keypoint goes to the point it fits best and
    each point takes at most one keypoint per image (the smallest error); the keypoint joins the
    point's track (``track_of`` changes), and an unused keypoint the track had in that image leaves
    it, so a track still sees each image once. Returns the observations added. COLMAP's
    ``IncrementalTriangulator::Complete``.
    """
    view = keypoint_views(keypoints)
    cp, ck, ce = candidates
    kp, _, point = model.observations(keypoints, track_of)
    point_of = np.full(len(keypoints), -1, dtype=np.int64)
    point_of[kp] = point
    free = point_of[ck] < 0
    cp, ck, ce = cp[free], ck[free], ce[free]
    if not len(cp):
        return 0
    order = np.argsort(ce, kind="stable")
    cp, ck = cp[order], ck[order]
    _, first = np.unique(ck, return_index=True)
    cp, ck = cp[np.sort(first)], ck[np.sort(first)]
    V = len(model.registered)
    slot = cp * V + view[ck]
    _, first = np.unique(slot, return_index=True)
    cp, ck = cp[np.sort(first)], ck[np.sort(first)]
    target = model.point_tracks[cp]
    labelled = np.flatnonzero(track_of >= 0)
    stale = labelled[np.isin(track_of[labelled] * V + view[labelled], target * V + view[ck])]
    track_of[stale] = -1
    track_of[ck] = target
    model.observed[ck] = True
    return len(ck)


def merge_tracks(model: GrowingModel, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray,
                 candidates: Candidates, *, max_error_px: float) -> int:
    """Track merging: two points whose projections land on each other's observations become one (in place).

    A candidate of :func:`guided_candidates` that already observes another point links the two.
    They merge when their tracks see no image in common and every observation of both lies within
    ``max_error_px`` of the merged point, the mean of the two weighted by their observation counts
    (COLMAP's ``IncrementalTriangulator::Merge``). Each point takes part in at most one merge per
    call (best first). Returns the merges made.
    """
    pairs = _mergeable_pairs(model, keypoints, track_of, candidates)
    if not len(pairs):
        return 0
    kp, views, point = model.observations(keypoints, track_of)
    counts = np.bincount(point, minlength=len(model.points)).astype(np.float64)
    na, nb = counts[pairs[:, 0]], counts[pairs[:, 1]]
    merged = ((na[:, None] * model.points[pairs[:, 0]] + nb[:, None] * model.points[pairs[:, 1]])
              / (na + nb)[:, None])
    # worst reprojection error of the merged point over the observations of both points
    slot = np.full(len(model.points), -1, dtype=np.int64)
    worst = np.zeros(len(pairs))
    for side in (0, 1):
        slot[:] = -1
        slot[pairs[:, side]] = np.arange(len(pairs))
        rows = np.flatnonzero(slot[point] >= 0)
        error = observation_errors(model, K, keypoints, kp[rows], views[rows], point[rows],
                                   merged[slot[point[rows]]])
        np.maximum.at(worst, slot[point[rows]], error)
    good = worst <= max_error_px
    pairs, merged, worst = pairs[good], merged[good], worst[good]
    if not len(pairs):
        return 0
    order = np.argsort(worst, kind="stable")
    pairs, merged = pairs[order], merged[order]
    # a point may merge once per call: keep the pairs whose points appear first in the sequence
    sequence = pairs.reshape(-1)
    _, first = np.unique(sequence, return_index=True)
    first_of = np.full(len(model.points), -1)
    first_of[sequence[first]] = first
    rank = 2 * np.arange(len(pairs))
    alone = (first_of[pairs[:, 0]] == rank) & (first_of[pairs[:, 1]] == rank + 1)
    pairs, merged = pairs[alone], merged[alone]
    model.points[pairs[:, 0]] = merged
    remap = np.arange(max(int(track_of.max()) + 1, 1))
    remap[model.point_tracks[pairs[:, 1]]] = model.point_tracks[pairs[:, 0]]
    labelled = track_of >= 0
    track_of[labelled] = remap[track_of[labelled]]
    keep = np.ones(len(model.points), dtype=bool)
    keep[pairs[:, 1]] = False
    model.points, model.point_tracks = model.points[keep], model.point_tracks[keep]
    return len(pairs)


def _mergeable_pairs(model: GrowingModel, keypoints: Points2D, track_of: np.ndarray,
                     candidates: Candidates) -> np.ndarray:
    """Pairs ``(P', 2)`` of points linked by a candidate whose tracks see no image in common."""
    view = keypoint_views(keypoints)
    cp, ck, _ = candidates
    kp, _, point = model.observations(keypoints, track_of)
    point_of = np.full(len(keypoints), -1, dtype=np.int64)
    point_of[kp] = point
    other = point_of[ck]
    linked = (other >= 0) & (other != cp)
    if not linked.any():
        return np.zeros((0, 2), dtype=np.int64)
    pairs = np.unique(np.sort(np.column_stack([cp[linked], other[linked]]), axis=1), axis=0)
    V = len(model.registered)
    ta, tb = model.point_tracks[pairs[:, 0]], model.point_tracks[pairs[:, 1]]
    involved, local = np.unique(np.concatenate([ta, tb]), return_inverse=True)
    labelled = np.flatnonzero(np.isin(track_of, involved))
    sees = np.zeros((len(involved), V), dtype=bool)
    sees[np.searchsorted(involved, track_of[labelled]), view[labelled]] = True
    la, lb = local[:len(pairs)], local[len(pairs):]
    return pairs[~np.any(sees[la] & sees[lb], axis=1)]


def complete_and_merge(model: GrowingModel, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray,
                       unit: np.ndarray | None, trees: KeypointTrees, sizes: np.ndarray, *,
                       max_error_px: float,
                       max_descriptor_distance: float, rounds: int = 1) -> tuple[int, int]:
    """Complete, then merge tracks, ``rounds`` times or until nothing changes: ``(observations added,
    merges)``.

    COLMAP's ``IncrementalTriangulator::CompleteAndMergeTracks``.
    """
    completed = merged = 0
    for _ in range(rounds):
        options = dict(max_error_px=max_error_px, max_descriptor_distance=max_descriptor_distance)
        added = complete_tracks(model, keypoints, track_of,
                                guided_candidates(model, K, keypoints, track_of, unit, trees, sizes,
                                                  **options))
        joined = merge_tracks(model, K, keypoints, track_of,
                              guided_candidates(model, K, keypoints, track_of, unit, trees, sizes, **options),
                              max_error_px=max_error_px)
        completed, merged = completed + added, merged + joined
        if not added and not joined:
            break
    return completed, merged


def drop_two_view_points(model: GrowingModel, track_of: np.ndarray, tried: np.ndarray) -> int:
    """Drop the points whose tracks still have two keypoints after completion (in place); returns how many.

    With completion on, a two-view track is triangulated on trial: completion may find it in a
    third image (then it stays), else it goes, as COLMAP's ``ignore_two_view_tracks`` would never
    have made it; it is tried again after the next registration.
    """
    short = track_lengths(track_of)[model.point_tracks] < 3
    if short.any():
        tried[model.point_tracks[short]] = 0
        model.points, model.point_tracks = model.points[~short], model.point_tracks[~short]
    return int(short.sum())
