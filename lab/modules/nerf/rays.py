"""Rays from camera poses, and stratified samples along them (Mildenhall et al. 2020, sections 4 and 5.2).

Cameras follow the lab's OpenCV convention (x right, y down, z forward, ``X_c = R X_w + t``) with
pixel ``(0, 0)`` the *centre* of the top-left pixel, so pixel ``(column j, row i)`` has its centre at
``(u, v) = (j, i)``. Tools that put the top-left *corner* at (0, 0) (nerfstudio, instant-ngp, COLMAP)
write the same centre as ``(j + 0.5, i + 0.5)``: :func:`lab.data.transforms_json.read_transforms_json`
moves their principal point by -0.5 px at the edge, and nothing here converts again. (The original
NeRF code casts rays through ``(j, i)`` with ``cx = W / 2``: half a pixel off the centres.) The OpenGL
``transform_matrix`` of a ``transforms.json`` is likewise turned into ``R, t`` by that reader only.

The ray through pixel ``(u, v)`` starts at the camera centre ``o = -R^T t`` and runs along
``d = R^T K^-1 (u, v, 1)^T``, whose camera-frame z is 1: the ray parameter of a point is its depth Z,
the same depth :func:`lab.data.scenes.render` returns, and ``near``/``far`` are depths.
"""

from __future__ import annotations

import numpy as np
import torch

from lab.core import Cameras, InvalidValue
from lab.modules.nerf.values import check_near_far


def pixel_centres(width: int, height: int, *, device: str | torch.device = "cpu") -> torch.Tensor:
    """The centre of every pixel, ``(H * W, 2)`` float64 ``(u, v) = (column, row)`` in row-major order
    (the lab's convention: the top-left pixel's centre is (0, 0); corner-origin tools call it (0.5, 0.5))."""
    rows, columns = torch.meshgrid(torch.arange(height, dtype=torch.float64, device=device),
                                   torch.arange(width, dtype=torch.float64, device=device), indexing="ij")
    return torch.stack([columns.reshape(-1), rows.reshape(-1)], dim=1)


def check_poses(K: np.ndarray, R: np.ndarray, t: np.ndarray, field: str = "cameras") -> None:
    """Raise :class:`InvalidValue` on ``field`` for NaN or infinite poses, a singular ``K`` or a ``R``
    that is not a rotation (shapes ``(V, 3, 3)``, ``(V, 3, 3)``, ``(V, 3)``)."""
    K, R, t = (np.asarray(a, dtype=np.float64) for a in (K, R, t))
    if K.ndim != 3 or K.shape[1:] != (3, 3) or R.shape != K.shape or t.shape != (len(K), 3):
        raise InvalidValue(field, f"expected K (V, 3, 3), R (V, 3, 3), t (V, 3), got {K.shape}, {R.shape}, "
                                  f"{t.shape}")
    for name, array in (("K", K), ("R", R), ("t", t)):
        bad = ~np.all(np.isfinite(array.reshape(len(array), -1)), axis=1)
        if bad.any():
            raise InvalidValue(field, f"camera {int(np.flatnonzero(bad)[0])} has NaN or infinite entries in "
                                      f"{name}: its pose is unknown")
    if np.any(np.abs(np.linalg.det(K)) < 1e-12):
        raise InvalidValue(field, "a camera matrix K is singular")
    error = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
    if np.any(error > 1e-6) or np.any(np.linalg.det(R) < 0):
        raise InvalidValue(field, f"camera {int(np.argmax(error))}'s R is not a rotation")


def camera_rays(K: np.ndarray, R: np.ndarray, t: np.ndarray, pixels: torch.Tensor | np.ndarray, *,
                device: str | torch.device = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through ``pixels`` ``(M, 2)`` (lab convention, see the module docstring) of ``V`` cameras.

    ``K``, ``R`` ``(V, 3, 3)`` and ``t`` ``(V, 3)`` world to camera (``X_c = R X_w + t``). Returns
    origins ``(V, M, 3)`` (each camera's centre ``-R^T t``) and directions ``(V, M, 3)``
    ``R^T K^-1 (u, v, 1)`` (camera-frame z = 1, not unit length), float32 on ``device``, computed in
    float64. Pinhole cameras only (no distortion). :func:`camera_rays_reference` is the oracle.
    """
    check_poses(K, R, t)
    K64 = torch.as_tensor(np.asarray(K, dtype=np.float64), device=device)
    R64 = torch.as_tensor(np.asarray(R, dtype=np.float64), device=device)
    t64 = torch.as_tensor(np.asarray(t, dtype=np.float64), device=device)
    uv = torch.as_tensor(pixels, dtype=torch.float64, device=device)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise InvalidValue("pixels", f"expected (M, 2) pixel coordinates, got {tuple(uv.shape)}")
    homogeneous = torch.cat([uv, torch.ones_like(uv[:, :1])], dim=1)          # (M, 3)
    camera = homogeneous @ torch.linalg.inv(K64).transpose(1, 2)               # (V, M, 3): K^-1 x
    directions = camera @ R64                                                  # rows: R^T d_c
    centres = -torch.einsum("vji,vj->vi", R64, t64)                            # (V, 3)
    origins = centres[:, None, :].expand_as(directions)
    return origins.to(torch.float32).contiguous(), directions.to(torch.float32).contiguous()


def cameras_rays(cameras: Cameras, *,
                 device: str | torch.device = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`camera_rays` through every pixel centre of every camera: ``(V, H * W, 3)`` each, rows in
    row-major pixel order. Refuses cameras with lens distortion (undistort the images first)."""
    if cameras.dist is not None and np.any(cameras.dist):
        raise InvalidValue("cameras", "NeRF's rays are pinhole rays: these cameras have lens distortion "
                                      "(undistort the images first)")
    return camera_rays(cameras.K, cameras.R, cameras.t, pixel_centres(cameras.width, cameras.height),
                       device=device)


def scaled_cameras(cameras: Cameras, factor: float) -> Cameras:
    """``cameras`` seeing the same scene at ``factor`` times the resolution (``factor`` < 1: smaller).

    Pixel centres move with the scale: a corner-origin coordinate scales by ``factor``, so in the
    lab's centre-origin convention ``u' = (u + 0.5) factor - 0.5`` (``fx' = factor fx``,
    ``cx' = (cx + 0.5) factor - 0.5``); the image becomes ``round(factor W) x round(factor H)``.
    """
    if not factor > 0:
        raise InvalidValue("factor", f"must be positive, got {factor!r}")
    K = cameras.K.copy()
    K[:, :2, :] *= factor
    K[:, 0, 2] += 0.5 * factor - 0.5
    K[:, 1, 2] += 0.5 * factor - 0.5
    width, height = max(1, round(cameras.width * factor)), max(1, round(cameras.height * factor))
    return Cameras(K, cameras.R, cameras.t, width, height, dist=cameras.dist)


def stratified_samples(near: float, far: float, rays: int, count: int, *, jitter: bool = True,
                       generator: torch.Generator | None = None,
                       device: str | torch.device = "cpu") -> torch.Tensor:
    """Depths ``(rays, count)`` float32, one in each of ``count`` equal bins of ``[near, far]``.

    Mildenhall et al. 2020 eq. 2: ``t_i ~ U[near + (i - 1)/N (far - near), near + i/N (far - near)]``
    with ``jitter`` (a fresh uniform draw per ray and bin from ``generator``, drawn on the CPU so that a
    run is the same on every device); without jitter each bin's centre. Sorted along each ray.
    Raises :class:`InvalidValue` on ``near`` for ``near >= far``. Oracle:
    :func:`stratified_samples_reference`.
    """
    near, far = check_near_far(near, far, "near")
    if count < 1 or rays < 0:
        raise InvalidValue("samples", f"need at least one sample per ray, got {count}")
    if jitter:
        u = torch.rand((rays, count), generator=generator, dtype=torch.float32).to(device)
    else:
        u = torch.full((rays, count), 0.5, dtype=torch.float32, device=device)
    bins = torch.arange(count, dtype=torch.float32, device=device)
    return near + (far - near) * (bins + u) / count


__all__ = ["camera_rays", "cameras_rays", "check_poses", "pixel_centres", "scaled_cameras",
           "stratified_samples"]
