"""A texture on a 3D surface: UV-parametrized plane, cylinder and torus, colours looked up through UVs."""

from __future__ import annotations

from typing import Any

import numpy as np

from lab.core import InvalidControl, Mesh
from lab.modules.texture._common import as_hwc


def parametric_surface(shape: str, resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A plane, cylinder or torus as a ``(resolution + 1)^2`` grid of vertices with UVs in [0, 1].

    Returns ``vertices`` ``(V, 3)``, ``faces`` ``(F, 3)`` (two triangles per grid cell, consistent
    winding) and ``uv`` ``(V, 2)``. The seam column (u = 0 and u = 1) is duplicated so the UVs do not
    wrap inside a triangle. Plane: 2 x 2 in z = 0; cylinder: radius 1 / pi (circumference 2),
    height 2; torus: radii 1 and 0.4.
    """
    n = int(resolution)
    u, v = np.meshgrid(np.linspace(0.0, 1.0, n + 1), np.linspace(0.0, 1.0, n + 1))
    if shape == "plane":
        xyz = np.stack([2 * u - 1, 1 - 2 * v, np.zeros_like(u)], axis=-1)
    elif shape == "cylinder":
        angle = 2 * np.pi * u
        radius = 1.0 / np.pi
        xyz = np.stack([radius * np.cos(angle), radius * np.sin(angle), 1 - 2 * v], axis=-1)
    elif shape == "torus":
        angle, tube = 2 * np.pi * u, 2 * np.pi * v
        major, minor = 1.0, 0.4
        xyz = np.stack([(major + minor * np.cos(tube)) * np.cos(angle),
                        (major + minor * np.cos(tube)) * np.sin(angle), minor * np.sin(tube)], axis=-1)
    else:
        raise InvalidControl("shape", f"must be plane, cylinder or torus, got {shape!r}")
    index = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, 1:].ravel(), index[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, d, b], axis=1), np.stack([b, d, c], axis=1)])
    return xyz.reshape(-1, 3), faces.astype(np.int64), np.stack([u.ravel(), v.ravel()], axis=1)


def sample_texture(texture: np.ndarray, uv: np.ndarray, *, repeats: float = 1.0) -> np.ndarray:
    """RGB ``(V, 3)`` of a texture at UVs (u right, v down, wrapping: the texture tiles ``repeats`` times),
    bilinear (``scipy.ndimage.map_coordinates`` with ``mode="grid-wrap"``)."""
    from scipy.ndimage import map_coordinates

    pixels = as_hwc(texture)
    height, width = pixels.shape[:2]
    cols = (uv[:, 0] * repeats * width - 0.5)
    rows = (uv[:, 1] * repeats * height - 0.5)
    channels = [map_coordinates(pixels[:, :, c], [rows, cols], order=1, mode="grid-wrap")
                for c in range(pixels.shape[2])]
    rgb = np.stack(channels, axis=1)
    if rgb.shape[1] == 1:
        rgb = np.repeat(rgb, 3, axis=1)
    return np.clip(rgb, 0.0, 1.0)


def textured_trimesh(mesh: Mesh, uv: np.ndarray, texture: np.ndarray, *, repeats: float = 1.0) -> Any:
    """A ``trimesh.Trimesh`` with the texture as an image map (``TextureVisuals``), for GLB export and the
    viewer.

    trimesh's UV origin is the bottom-left (OpenGL): ``v`` is flipped. The texture is tiled
    ``repeats`` times into the image instead of relying on the renderer's wrap mode.
    """
    import trimesh
    from PIL import Image as PILImage

    pixels = as_hwc(texture)
    if pixels.shape[2] == 1:
        pixels = np.repeat(pixels, 3, axis=2)
    reps = max(1, round(repeats))
    tiled = np.tile(pixels, (reps, reps, 1))
    picture = PILImage.fromarray(np.clip(tiled * 255 + 0.5, 0, 255).astype(np.uint8))
    uv_gl = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
    visual = trimesh.visual.TextureVisuals(uv=uv_gl, image=picture)
    return trimesh.Trimesh(mesh.vertices, mesh.faces, visual=visual, process=False)
