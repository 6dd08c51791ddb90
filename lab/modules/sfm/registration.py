"""The incremental loop: register the next image, triangulate what it completes, bundle adjust, grow the
tracks.

:class:`Incremental` holds the loop's state (the growing model, its tracks, what was tried and
measured); :meth:`Incremental.run` is the loop of :func:`~lab.modules.sfm.reconstruct_incrementally`
(Schönberger and Frahm, "Structure-from-Motion Revisited", CVPR 2016, sections 4.2-4.5). The
controls of that step come grouped: :class:`Registration`, :class:`Triangulation`,
:class:`Adjustment` and :class:`TrackGrowth`.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lab.core import Curve, InvalidValue, Points2D, Progress, StepFailed
from lab.geometry.bundle_adjustment import BundleResult, bundle_adjust_progress
from lab.geometry.pnp import pnp_ransac, refine_pnp, reprojection_errors
from lab.geometry.triangulation import point_depths, projection_matrix, refine_points, triangulate_dlt
from lab.modules.sfm._checks import keypoint_views
from lab.modules.sfm.model import GrowingModel, observation_errors, poses_matrix, ray_angles_deg
from lab.modules.sfm.tracks import (KeypointTrees, complete_and_merge, continue_tracks, correspondences_2d3d,
                                    drop_two_view_points)


class RegistrationFailed(StepFailed):
    """No image beyond the initial pair could be registered."""


@dataclass(frozen=True)
class Registration:
    """How an image is registered: PnP's RANSAC threshold (px) and the fewest 2D-3D correspondences."""

    pnp_threshold_px: float
    min_correspondences: int


@dataclass(frozen=True)
class Triangulation:
    """Which new points are kept: smallest triangulation angle (deg), largest reprojection error (px),
    fewest keypoints in the track."""

    min_angle_deg: float
    max_error_px: float
    min_track_length: int


@dataclass(frozen=True)
class Adjustment:
    """The bundle adjustments inside the loop: robust loss, most iterations (0: none), growth factor."""

    loss: str
    iterations: int
    growth: float


@dataclass(frozen=True)
class TrackGrowth:
    """Continue, complete and merge tracks (``complete``), drop two-view points (``ignore_two_view``), with
    the largest reprojection error and descriptor distance of an added observation."""

    complete: bool
    ignore_two_view: bool
    max_error_px: float
    max_descriptor_distance: float


def bundle(model: GrowingModel, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray, anchor: int, *,
           loss: str, f_scale: float, max_iterations: int, refine_intrinsics: bool = False,
           ) -> Generator[tuple[int, float], None, tuple[BundleResult, np.ndarray, np.ndarray]]:
    """Bundle adjustment of the model in place (yields ``(iteration, rms)``; returns the BundleResult, the
    registered views and their K)."""
    kp, views, point = model.observations(keypoints, track_of)
    cams = np.flatnonzero(model.registered)
    local = np.full(len(model.registered), -1)
    local[cams] = np.arange(len(cams))
    used = np.unique(point)
    point_local = np.full(len(model.points), -1)
    point_local[used] = np.arange(len(used))
    K_sub = K[cams]
    if refine_intrinsics and np.allclose(K_sub, K_sub[0]):
        K_sub = K_sub[0]
    result = yield from bundle_adjust_progress(
        K_sub, model.poses[cams, :, :3], model.poses[cams, :, 3], model.points[used], local[views],
        point_local[point], keypoints.xy[kp], loss=loss, f_scale=f_scale, refine_intrinsics=refine_intrinsics,
        fixed_cameras=(int(local[anchor]),), max_iterations=max_iterations)
    model.poses[cams] = poses_matrix(result.R, result.t)
    model.points[used] = result.points
    K_out = np.broadcast_to(result.K, (len(cams), 3, 3)) if result.K.ndim == 2 else result.K
    return result, cams, K_out


def reject_outliers(model: GrowingModel, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray,
                    max_error_px: float) -> int:
    """Stop using observations whose error exceeds ``max_error_px``; drop points left with < 2. Returns
    the observations dropped."""
    kp, views, point = model.observations(keypoints, track_of)
    errors = observation_errors(model, K, keypoints, kp, views, point)
    bad = errors > max_error_px
    model.observed[kp[bad]] = False
    counts = np.bincount(point[~bad], minlength=len(model.points))
    keep = counts >= 2
    if not keep.all():
        model.points = model.points[keep]
        model.point_tracks = model.point_tracks[keep]
    return int(bad.sum())


def triangulate_new(model: GrowingModel, K: np.ndarray, keypoints: Points2D, track_of: np.ndarray,
                    tried: np.ndarray, *, min_angle_deg: float, max_error_px: float,
                    min_track_length: int = 2) -> tuple[int, float, float]:
    """Triangulate the tracks with two or more registered observations and no point yet (DLT, then LM).

    Only tracks of at least ``min_track_length`` keypoints (3: COLMAP's ``ignore_two_view_tracks``).

    Returns (new points, RMS before refinement, RMS after) over the new points' observations.
    """
    view = keypoint_views(keypoints)
    num_tracks = len(tried)
    has_point = np.zeros(num_tracks, dtype=bool)
    has_point[model.point_tracks] = True
    usable = (track_of >= 0) & model.registered[view] & model.observed
    kp = np.flatnonzero(usable)
    kp = kp[~has_point[track_of[kp]]]
    counts = np.bincount(track_of[kp], minlength=num_tracks)
    lengths = np.bincount(track_of[track_of >= 0], minlength=num_tracks)
    candidates = np.flatnonzero((counts >= 2) & (counts > tried) & (lengths >= min_track_length))
    if not len(candidates):
        return 0, 0.0, 0.0
    tried[candidates] = counts[candidates]
    cams = np.flatnonzero(model.registered)
    local = np.full(len(model.registered), -1)
    local[cams] = np.arange(len(cams))
    column = np.full(num_tracks, -1)
    column[candidates] = np.arange(len(candidates))
    kp = kp[column[track_of[kp]] >= 0]
    x = np.zeros((len(cams), len(candidates), 2))
    mask = np.zeros((len(cams), len(candidates)), dtype=bool)
    rows, cols = local[view[kp]], column[track_of[kp]]
    x[rows, cols] = keypoints.xy[kp]
    mask[rows, cols] = True
    P = projection_matrix(K[cams], model.poses[cams, :, :3], model.poses[cams, :, 3])
    X = triangulate_dlt(P, x, mask)
    finite = np.all(np.isfinite(X), axis=1)
    X = np.where(finite[:, None], X, 0.0)
    depths = point_depths(P, X)
    front = finite & np.all((depths > 0) | ~mask, axis=0)
    centers = -np.einsum("vji,vj->vi", model.poses[cams, :, :3], model.poses[cams, :, 3])
    wide = ray_angles_deg(centers, X, mask) >= min_angle_deg
    keep = front & wide
    if not keep.any():
        return 0, 0.0, 0.0
    X_refined, history = refine_points(P, x[:, keep], X[keep], mask[:, keep], iterations=10)
    projected = np.einsum("vij,nj->vni", P[:, :, :3], X_refined) + P[:, None, :, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        errors = np.linalg.norm(projected[..., :2] / projected[..., 2:] - x[:, keep], axis=2)
    errors = np.where(mask[:, keep], errors, 0.0)
    good = np.all(np.isfinite(errors) & (errors <= max_error_px), axis=0)
    good &= np.all((np.einsum("vij,nj->vni", P[:, 2:3, :3], X_refined)[..., 0] + P[:, None, 2, 3] > 0)
                   | ~mask[:, keep], axis=0)
    if not good.any():
        return 0, 0.0, 0.0
    chosen = candidates[keep][good]
    model.points = np.concatenate([model.points, X_refined[good]])
    model.point_tracks = np.concatenate([model.point_tracks, chosen])
    return int(good.sum()), float(history[0]), float(history[-1])


def weighted_rms(values: list[tuple[float, int]]) -> float:
    """RMS of several RMS values ``(rms, count)`` weighted by their counts (0 without any)."""
    total = sum(n for _, n in values)
    return float(np.sqrt(sum(r * r * n for r, n in values) / total)) if total else 0.0


@dataclass
class Incremental:
    """The state of the incremental loop over one growing model (its arrays change in place).

    ``track_of`` becomes the model's tracks (continued, completed, merged); ``names`` and ``sizes``
    ``(V, 2)`` are the images'; ``anchor`` the view held fixed in bundle adjustment.
    """

    model: GrowingModel
    K: np.ndarray
    keypoints: Points2D
    track_of: np.ndarray
    unit: np.ndarray | None
    names: tuple[str, ...]
    sizes: np.ndarray
    anchor: int
    registration: Registration
    triangulation: Triangulation
    adjustment: Adjustment
    track_growth: TrackGrowth
    trees: KeypointTrees = field(default_factory=dict)
    tried: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    order: list[int] = field(default_factory=list)
    reasons: dict[int, str] = field(default_factory=dict)
    linear_rms: list[float] = field(default_factory=list)
    nonlinear_rms: list[float] = field(default_factory=list)
    tri_before: list[tuple[float, int]] = field(default_factory=list)
    tri_after: list[tuple[float, int]] = field(default_factory=list)
    ba_before: list[float] = field(default_factory=list)
    ba_after: list[float] = field(default_factory=list)
    ba_ok: bool = True
    continued: int = 0
    completed: int = 0
    merged: int = 0
    step: int = 0

    def __post_init__(self) -> None:
        num_tracks = int(self.track_of.max()) + 1 if len(self.track_of) and self.track_of.max() >= 0 else 0
        # the observations each track had when it was last triangulated
        self.tried = np.zeros(num_tracks, dtype=np.int64)
        _, _, point = self.model.observations(self.keypoints, self.track_of)
        self.tried[self.model.point_tracks] = np.bincount(point, minlength=len(self.model.points))

    def run(self, rng: np.random.Generator,
            preview: Callable[[], dict[str, Any]]) -> Generator[Progress, None, None]:
        """Register images while one can be (yielding a preview after each and the adjustments' RMS), then
        complete and merge the tracks once more. Raises :class:`RegistrationFailed` when none could be."""
        failures = np.zeros(len(self.names), dtype=np.int64)
        adjusted_at = int(self.model.registered.sum())
        while True:
            best = self.next_view(failures)
            if best < 0:
                break
            registered = self.register(best, rng)
            if registered is None:
                failures[best] += 1  # try it again only once the model has grown
                continue
            failures[:] = 0
            added = self.triangulate()
            self.step += 1
            yield Progress(self.step, None, self.nonlinear_rms[-1],
                           f"registered {self.names[best]} (image {best}): "
                           f"{registered} PnP inliers, {added} new points",
                           values=preview())
            grown = self.model.registered.sum() >= self.adjustment.growth * adjusted_at
            if self.adjustment.iterations > 0 and grown:
                adjusted_at = int(self.model.registered.sum())
                yield from self.adjust(best)
            self.grow_tracks(rounds=1)
        if self.track_growth.complete and self.order:
            self.grow_tracks(rounds=3)
        if len(self.order) == 0 and not self.model.registered.all():
            names = "; ".join(f"{self.names[v]} (image {v}): {self.reasons.get(int(v), 'not connected')}"
                              for v in np.flatnonzero(~self.model.registered))
            raise RegistrationFailed("images",
                                     f"no image could be registered beyond the initial pair: {names}")

    def next_view(self, failures: np.ndarray) -> int:
        """The unregistered view that sees most reconstructed points through its tracks, at least
        ``min_correspondences`` (-1: none); the others' reasons are kept for the warnings."""
        best, best_count = -1, 0
        minimum = self.registration.min_correspondences
        for v in np.flatnonzero(~self.model.registered):
            if failures[v] >= 2:
                continue
            kp, _ = correspondences_2d3d(self.model, self.keypoints, self.track_of, int(v))
            if len(kp) < minimum:
                self.reasons[int(v)] = (f"sees only {len(kp)} reconstructed points through its tracks (at "
                                        f"least {minimum} are needed for PnP)")
                continue
            if len(kp) > best_count:
                best, best_count = int(v), len(kp)
        return best

    def register(self, view: int, rng: np.random.Generator) -> int | None:
        """Linear PnP in RANSAC, then non-linear PnP on the inliers: the view's pose. Returns the inliers,
        None when PnP failed (the reason is kept)."""
        kp, point = correspondences_2d3d(self.model, self.keypoints, self.track_of, view)
        X, x = self.model.points[point], self.keypoints.xy[kp]
        try:
            found = pnp_ransac(X, x, self.K[view], threshold_px=self.registration.pnp_threshold_px, rng=rng)
            if found.inliers.sum() < self.registration.min_correspondences:
                raise InvalidValue("points2d", f"only {int(found.inliers.sum())} PnP inliers")
        except InvalidValue as exc:
            self.reasons[view] = f"PnP failed: {exc.reason}"
            return None
        inl = found.inliers
        R, t = refine_pnp(found.R, found.t, X[inl], x[inl], self.K[view], loss="huber", f_scale=1.0)
        errors_after = reprojection_errors(R, t, X[inl], x[inl], self.K[view])
        self.linear_rms.append(found.rms_px)
        self.nonlinear_rms.append(float(np.sqrt(np.mean(errors_after**2))))
        self.model.poses[view] = poses_matrix(R, t)
        self.model.registered[view] = True
        self.model.observed[kp[~inl]] = False
        if self.track_growth.complete:
            self.continued += continue_tracks(self.model, self.K, self.keypoints, self.track_of, view,
                                              max_error_px=self.track_growth.max_error_px)
        self.order.append(view)
        self.reasons.pop(view, None)
        return int(inl.sum())

    def triangulate(self) -> int:
        """Triangulate the tracks the registration completed; returns the new points."""
        options = self.triangulation
        added, before, after = triangulate_new(self.model, self.K, self.keypoints, self.track_of, self.tried,
                                               min_angle_deg=options.min_angle_deg,
                                               max_error_px=options.max_error_px,
                                               min_track_length=options.min_track_length)
        if added:
            self.tri_before.append((before, added))
            self.tri_after.append((after, added))
        return added

    def adjust(self, after: int) -> Generator[Progress, None, None]:
        """Bundle adjust every registered camera and point, yielding the RMS at each iteration."""
        adjusting = bundle(self.model, self.K, self.keypoints, self.track_of, self.anchor,
                           loss=self.adjustment.loss, f_scale=1.0, max_iterations=self.adjustment.iterations)
        while True:
            try:
                iteration, rms = next(adjusting)
            except StopIteration as stop:
                result = stop.value[0]
                break
            self.step += 1
            yield Progress(self.step, None, rms,
                           f"bundle adjustment after image {after}: iteration {iteration}")
        self.ba_before.append(result.rms_before)
        self.ba_after.append(result.rms_after)
        self.ba_ok &= result.rms_after <= result.rms_before

    def grow_tracks(self, *, rounds: int) -> None:
        """Complete and merge the tracks (when on), drop two-view points, stop using outlier observations."""
        growth = self.track_growth
        if growth.complete:
            added, joined = complete_and_merge(self.model, self.K, self.keypoints, self.track_of, self.unit,
                                               self.trees, self.sizes, max_error_px=growth.max_error_px,
                                               max_descriptor_distance=growth.max_descriptor_distance,
                                               rounds=rounds)
            self.completed, self.merged = self.completed + added, self.merged + joined
            if growth.ignore_two_view:
                drop_two_view_points(self.model, self.track_of, self.tried)
        reject_outliers(self.model, self.K, self.keypoints, self.track_of, self.triangulation.max_error_px)

    def warnings(self) -> tuple[str, ...]:
        """Each image that could not be registered, and why."""
        return tuple(f"{self.names[v]} (image {v}) could not be registered: "
                     f"{self.reasons.get(int(v), 'it shares no verified tracks with the registered images')}"
                     for v in np.flatnonzero(~self.model.registered))

    def registration_chart(self) -> Curve:
        """The linear and non-linear PnP RMS of each registered image, as a bar chart."""
        return Curve(np.arange(len(self.order), dtype=np.float64),
                     np.array([self.linear_rms, self.nonlinear_rms], dtype=np.float64).reshape(2, -1),
                     kind="bar",
                     title="PnP reprojection RMS per registered image", xlabel="image", ylabel="RMS (px)",
                     labels=("linear PnP (DLT in RANSAC)", "non-linear PnP"),
                     categories=tuple(self.names[v] for v in self.order))
