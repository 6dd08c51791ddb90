"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the
hint of tasks.toml when the student's result is what the mistake computes. Each takes the step's
parameters. Where the mistake is a change of input or of output it is the lab's own step
(:mod:`lab.modules.sfm_basics`) with that change, so it is exact by construction; the two PnP
mistakes inside the DLT share :func:`_dlt_matrices`, which with Hartley's normalization is the lab's
own DLT (tests/lessons/test_sfm_lesson.py checks that it gives the reference's poses).
"""

import numpy as np

from lab.core import Points2D
from lab.geometry.camera import pixels_to_normalized
from lab.geometry.pnp import dlt_projection_matrices
from lab.geometry.rotations import nearest_rotation
from lab.geometry.triangulation import projection_matrix, triangulate_dlt
from lab.modules import sfm_basics


# --- task 1: linear PnP ---------------------------------------------------------------------------
def _dlt_matrices(points3d, observations, K, *, hartley):
    """``(V, 3, 4)``: every camera's DLT matrix ``P`` for normalized coordinates ``K^-1 x``, its sign
    chosen so that the points it sees have positive depth (lesson.md, task 1, steps 1 to 4): the lab's
    :func:`lab.geometry.pnp.dlt_projection_matrices`.

    ``hartley=False`` solves the system on the coordinates as they are (``T2``, ``T3`` the identity).
    """
    world = np.asarray(points3d, dtype=np.float64)
    matrices = []
    for view in range(int(observations.view.max()) + 1):
        seen = observations.view == view
        x = pixels_to_normalized(observations.xy[seen], K)
        matrices.append(dlt_projection_matrices(world[observations.ids[seen]][None], x[None], hartley=hartley)[0][0])
    return np.array(matrices)


def _poses_from(matrices, *, project_onto_so3):
    """``[R | t]`` from ``P = lambda [R | t]``: ``t = P[:, 3] / mean(S)``; ``R`` the nearest rotation to
    ``P[:, :3]`` or, without ``project_onto_so3``, ``P[:, :3] / mean(S)`` (``U S W^T = svd(P[:, :3])``)."""
    blocks = matrices[:, :, :3]
    scale = np.linalg.svd(blocks, compute_uv=False).mean(axis=1)[:, None, None]
    rotations = nearest_rotation(blocks) if project_onto_so3 else blocks / scale
    return np.concatenate([rotations, matrices[:, :, 3:] / scale], axis=2)


def pnp_without_normalization(points3d, observations, K):
    """The DLT solved without Hartley's normalization of either point set; the rest as the lesson says."""
    return _poses_from(_dlt_matrices(points3d, observations, K, hartley=False), project_onto_so3=True)


def pnp_without_orthonormalization(points3d, observations, K):
    """``R = P[:, :3] / mean(S)``: the block divided by its scale, not projected onto SO(3)."""
    return _poses_from(_dlt_matrices(points3d, observations, K, hartley=True), project_onto_so3=False)


def pnp_sign_from_last_entry(points3d, observations, K):
    """``P`` scaled so that ``P[2, 3] = 1`` instead of signed by the depths, then ``R = U W^T``.

    ``P[2, 3] = lambda t_z``: where ``t_z < 0`` (the world origin behind the camera) this negates
    the right ``P``, whose block's nearest orthogonal matrix is then ``-R``: that camera comes out
    as ``-[R | t]``, the others as the reference's.
    """
    poses = sfm_basics.estimate_poses_linear(points3d, observations, K)
    return poses * np.where(poses[:, 2, 3] < 0, -1.0, 1.0)[:, None, None]


def pnp_in_pixels(points3d, observations, K):
    """The DLT solved on the pixels as they are (``K^-1 x`` forgotten): ``P`` is ``K [R | t]`` up to scale, the
    rest as the lesson says (the lab's DLT given ``K = I``)."""
    return _poses_from(_dlt_matrices(points3d, observations, np.eye(3), hartley=True), project_onto_so3=True)


def pnp_t_over_largest_singular_value(points3d, observations, K):
    """``t = P[:, 3] / S[0]``, the largest singular value of ``P[:, :3]``, instead of their mean."""
    matrices = _dlt_matrices(points3d, observations, K, hartley=True)
    blocks = matrices[:, :, :3]
    largest = np.linalg.svd(blocks, compute_uv=False)[:, :1, None]
    return np.concatenate([nearest_rotation(blocks), matrices[:, :, 3:] / largest], axis=2)


# --- task 2: linear triangulation ------------------------------------------------------------------
def triangulation_from_two_views(observations, poses, K):
    """Each point from the first two observations of it (in the order of ``observations``), not from all."""
    order = np.argsort(observations.ids, kind="stable")
    ids = observations.ids[order]
    starts = np.searchsorted(ids, ids)  # where each point's run of observations begins
    keep = np.zeros(len(ids), dtype=bool)
    keep[order[np.arange(len(ids)) - starts < 2]] = True
    first_two = Points2D(observations.xy[keep], view=observations.view[keep], ids=observations.ids[keep],
                         image=observations.image)
    return sfm_basics.triangulate_points_linear(first_two, poses, K)


def triangulation_without_K(observations, poses, K):
    """``P_v = [R_v | t_v]`` with the pixels as they are: the lab's triangulation given ``K = I``."""
    return sfm_basics.triangulate_points_linear(observations, poses, np.eye(3))


def triangulation_y_row_uses_x(observations, poses, K):
    """Each view's second row built with ``x``: ``x p3 - p2`` (a typo for ``y p3 - p2``): the lab's DLT of the
    pixels ``(x, x)``."""
    xx = Points2D(np.repeat(observations.xy[:, :1], 2, axis=1), view=observations.view, ids=observations.ids,
                  image=observations.image)
    return sfm_basics.triangulate_points_linear(xx, poses, K)


def triangulation_p1_p2_swapped(observations, poses, K):
    """The rows ``x p3 - p2`` and ``y p3 - p1``: the lab's DLT with the first two rows of every ``P`` swapped."""
    poses = np.asarray(poses, dtype=np.float64)
    P = projection_matrix(np.asarray(K, dtype=np.float64), poses[:, :, :3], poses[:, :, 3])[:, [1, 0, 2]]
    count = int(observations.ids.max()) + 1
    x = np.zeros((len(poses), count, 2))
    seen = np.zeros((len(poses), count), dtype=bool)
    x[observations.view, observations.ids] = observations.xy
    seen[observations.view, observations.ids] = True
    return triangulate_dlt(P, x, seen)


# --- task 3: the sparsity pattern --------------------------------------------------------------------
def sparsity_without_point_blocks(camera_indices, point_indices, num_cameras, num_points):
    """Each observation's camera columns marked, its point's 3 columns not."""
    pattern = sfm_basics.jacobian_sparsity(camera_indices, point_indices, num_cameras, num_points)
    pattern[:, sfm_basics.CAMERA_PARAMS * num_cameras:] = False
    return pattern


def sparsity_points_without_camera_offset(camera_indices, point_indices, num_cameras, num_points):
    """Point ``p``'s columns at ``3 p .. 3 p + 2``, over the camera blocks: the cameras' ``6 V`` columns not skipped."""
    pattern = sfm_basics.jacobian_sparsity(camera_indices, point_indices, num_cameras, num_points)
    cameras = sfm_basics.CAMERA_PARAMS * num_cameras
    shifted = pattern.copy()
    shifted[:, cameras:] = False
    shifted[:, :3 * num_points] |= pattern[:, cameras:]
    return shifted


def sparsity_u_rows_only(camera_indices, point_indices, num_cameras, num_points):
    """Only row ``2 i`` (the u residual) of each observation marked; rows ``2 i + 1`` empty."""
    pattern = sfm_basics.jacobian_sparsity(camera_indices, point_indices, num_cameras, num_points)
    pattern[1::2] = False
    return pattern


def sparsity_u_then_v_blocks(camera_indices, point_indices, num_cameras, num_points):
    """Observation ``i``'s rows at ``i`` (u) and ``M + i`` (v): all u residuals, then all v."""
    pattern = sfm_basics.jacobian_sparsity(camera_indices, point_indices, num_cameras, num_points)
    return np.concatenate([pattern[0::2], pattern[1::2]])


def sparsity_points_before_cameras(camera_indices, point_indices, num_cameras, num_points):
    """The points' ``3 N`` columns first, then the cameras' ``6 V``: the parameter blocks in the other order."""
    pattern = sfm_basics.jacobian_sparsity(camera_indices, point_indices, num_cameras, num_points)
    cameras = sfm_basics.CAMERA_PARAMS * num_cameras
    return np.concatenate([pattern[:, cameras:], pattern[:, :cameras]], axis=1)
