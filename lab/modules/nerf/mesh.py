"""A trained radiance field as a coloured triangle mesh: density sampled on a lattice, marching cubes at a
density level, vertices coloured by what a ray along the surface normal sees (Mildenhall et al. 2020,
section 6 and their supplement's mesh figure; the extraction of nerfstudio's ``ns-export marching-cubes``
and instant-ngp's "marching cubes" button).

- The lattice: ``resolution^3`` points spanning the normalized scene box ``[-1, 1]^3`` of the model's
  :class:`~lab.modules.nerf.values.SceneBounds` (world ``center + radius [-1, 1]^3``). The MLP's density
  depends on position only (the direction is not looked at); a grid's is its raw table resampled
  trilinearly, then the same softplus as when it renders.
- The surface: ``skimage.measure.marching_cubes`` (Lorensen & Cline 1987; Lewiner et al. 2003's
  topology-correct tables) on the lattice at ``level`` (sigma, per scene unit), in world units.
- The colour: a field's colour is defined along rays, and at the level set itself it can still be the
  colour of empty space. So each vertex gets the volume-rendered colour of a short ray that ends it seen
  head on: from ``reach`` outside the surface along ``-n`` to ``reach`` inside, ``n`` the density's
  gradient direction (into the object), divided by that ray's opacity (the background left out).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from lab.core import InvalidControl, Mesh
from lab.modules.nerf.grid import GridCheckpoint, grid_density
from lab.modules.nerf.model import network_from
from lab.modules.nerf.values import NerfCheckpoint, SceneBounds

#: Points per MLP batch when the lattice is sampled.
CHUNK = 65536


def lattice_points(bounds: SceneBounds, resolution: int) -> np.ndarray:
    """The world positions ``(R, R, R, 3)`` of the lattice (axis order x, y, z), spanning the scene box."""
    axis = np.linspace(-1.0, 1.0, resolution)
    unit = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1)
    return bounds.center + bounds.radius * unit


def density_lattice(model: NerfCheckpoint | GridCheckpoint, resolution: int, *,
                    device: str = "cpu") -> np.ndarray:
    """The model's density sigma ``(R, R, R)`` float32 at the :func:`lattice_points` (axis order x, y, z)."""
    if isinstance(model, GridCheckpoint):
        raw = torch.as_tensor(model.density, device=device)[None, None]
        resampled = torch.nn.functional.interpolate(raw, size=(resolution,) * 3, mode="trilinear",
                                                    align_corners=True)[0, 0]
        return grid_density(resampled).cpu().numpy()
    net = network_from(model, device)
    axis = torch.linspace(-1.0, 1.0, resolution, device=device)
    x = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    sigma = []
    with torch.no_grad():
        for start in range(0, len(x), CHUNK):
            part = x[start:start + CHUNK]
            sigma.append(net(part, torch.zeros_like(part))[0])  # density reads the position only
    return torch.cat(sigma).reshape((resolution,) * 3).cpu().numpy()


@dataclass(frozen=True, eq=False)
class Surface:
    """Marching cubes' output in world units: ``vertices`` ``(V, 3)``, ``faces`` ``(F, 3)`` and the unit
    density gradient ``inward`` ``(V, 3)`` at each vertex (pointing into the object)."""

    vertices: np.ndarray
    faces: np.ndarray
    inward: np.ndarray


def iso_surface(sigma: np.ndarray, level: float, bounds: SceneBounds) -> Surface:
    """``skimage.measure.marching_cubes(sigma, level)`` on the lattice of ``bounds`` (lattice indices to
    world: ``center + radius (2 i / (R - 1) - 1)``); :class:`InvalidControl` on ``level`` when the density
    never crosses it."""
    from scipy.ndimage import map_coordinates
    from skimage.measure import marching_cubes

    low, high = float(sigma.min()), float(sigma.max())
    if not low < level < high:
        advice = "train longer or pick a level inside it" if high <= level else "pick a level inside it"
        raise InvalidControl("level", f"the density never crosses {level:g}: it lies in [{low:.3g}, "
                                      f"{high:.3g}] over the scene box ({advice})")
    spacing = 2.0 * bounds.radius / (sigma.shape[0] - 1)
    index, faces, _, _ = marching_cubes(sigma, level=level, allow_degenerate=False)
    gradient = [np.asarray(g) for g in np.gradient(sigma.astype(np.float64))]             # 3 x (R, R, R)
    inward = np.stack([map_coordinates(g, index.T, order=1) for g in gradient], axis=1)
    length = np.linalg.norm(inward, axis=1, keepdims=True)
    inward = np.where(length > 0, inward / np.maximum(length, 1e-30), np.array([0.0, 0.0, -1.0]))
    vertices = bounds.center - bounds.radius + spacing * index
    return Surface(vertices, faces.astype(np.int64), inward)


def head_on_rays(surface: Surface, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Origins ``(V, 3)`` ``reach`` outside each vertex and unit directions ``(V, 3)`` into the surface: rays
    of parameter ``t`` in ``[0, 2 reach]`` that cross it head on at ``t = reach``."""
    return surface.vertices - reach * surface.inward, surface.inward


def coloured_mesh(surface: Surface, colors: np.ndarray) -> Mesh:
    """The lab's :class:`~lab.core.values.Mesh` of a surface with vertex colours ``(V, 3)`` in [0, 1]."""
    return Mesh(surface.vertices, surface.faces, np.clip(colors, 0.0, 1.0))


def mesh_trimesh(mesh: Mesh):  # -> trimesh.Trimesh (imported lazily)
    """A ``trimesh.Trimesh`` of ``mesh`` with its vertex colours as RGBA uint8 (for PLY and GLB)."""
    import trimesh

    colors = None
    if mesh.vertex_colors is not None:
        rgb = np.round(np.clip(mesh.vertex_colors, 0, 1) * 255).astype(np.uint8)
        colors = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)
    return trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_colors=colors, process=False)


__all__ = ["CHUNK", "Surface", "coloured_mesh", "density_lattice", "head_on_rays", "iso_surface",
           "lattice_points", "mesh_trimesh"]
