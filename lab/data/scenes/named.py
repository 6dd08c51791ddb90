"""Named scenes: a room, objects on a table, a building facade. Deterministic per seed.

The world is metric with z up (``Scene.up``); floors lie at z = 0. Each scene sets ``center`` (what
cameras look at by default) and ``home`` (a good first viewpoint), which the camera path
generators of :mod:`lab.data.scenes.cameras` use.

- ``room``: an 8 x 8 x 3 m room (floor, four walls, ceiling; posters on the walls) with crates and
  balls on the floor. Every pixel from inside sees a surface (full mask). The general-position
  scene for two-view geometry and SfM.
- ``table``: a table with a cereal box, a ball, a can (a trimesh mesh with UV coordinates), a ring
  (a trimesh torus with vertex colours) and a cube on it, in front of a wall, on a 6 x 6 m floor;
  the background shows around it.
- ``facade``: a 14 x 9 m wall of a building with windows (photos) and shallow sills: almost a
  plane, so two views of it are nearly related by a homography (the degenerate case of the
  fundamental matrix). The sky shows around it.

Textures are scikit-image's offline photos (astronaut, coffee, chelsea, rocket, brick, grass,
...) and procedural patterns (:mod:`lab.data.scenes.textures`) chosen so that SIFT finds
thousands of features on a 640 x 480 view. The seed changes the procedural textures, the poster
layout and the objects' placement (by up to about 0.15 m and 20 degrees).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from lab.core.errors import InvalidValue, UnknownName
from lab.data.scenes.objects import Box, MeshObject, Plane, Scene, SceneObject, Sphere
from lab.data.scenes.textures import (Texture, atlas, fit, noise_texture, photo, shapes_texture, tinted,
                                      wood_texture)
from lab.geometry.rotations import rotvec_to_matrix

#: Names :func:`named_scene` knows.
SCENE_NAMES: tuple[str, ...] = ("room", "table", "facade")

_DOWN = (0.0, 0.0, -1.0)


def named_scene(name: str, *, seed: int = 0) -> Scene:
    """The scene called ``name`` (one of :data:`SCENE_NAMES`), built deterministically from ``seed``.

    Scenes are cached (the same name and seed return the same object; treat it as read-only).
    Raises :class:`UnknownName` for an unknown name and :class:`InvalidValue` for a seed that is
    not a non-negative integer.
    """
    if not isinstance(name, str) or name not in SCENE_NAMES:
        raise UnknownName("scene", f"unknown scene {name!r}; scenes are {list(SCENE_NAMES)}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InvalidValue("seed", f"must be a non-negative integer, got {seed!r}")
    return _build(name, int(seed))


@lru_cache(maxsize=4)
def _build(name: str, seed: int) -> Scene:
    return {"room": _room, "table": _table, "facade": _facade}[name](np.random.default_rng([seed, 4]), seed)


# --- texture helpers ----------------------------------------------------------------------------------------
def _modulated(image: np.ndarray, seed: int, strength: float = 0.35) -> np.ndarray:
    """``image`` times coloured large-scale noise, so that repeated photo tiles no longer look alike."""
    h, w = image.shape[:2]
    noise = noise_texture(w, h, seed=seed, octaves=4, coarsest=3, saturation=0.8)
    return np.clip(image * (1.0 - strength + 2.0 * strength * noise), 0.0, 1.0).astype(np.float32)


def _bricks() -> np.ndarray:
    """scikit-image's brick photo turned a quarter turn, so that the courses run horizontally."""
    return np.ascontiguousarray(np.rot90(photo("brick")))


def _tiled(image: np.ndarray, columns: int, rows: int) -> np.ndarray:
    return np.tile(image, (rows, columns, 1))


def _paste_posters(canvas: np.ndarray, names: list[str], rng: np.random.Generator, *, rows: int = 1,
                   fill: float = 0.55, frame: int = 6) -> np.ndarray:
    """Photos in dark frames at jittered places on a row-major grid of ``len(names) / rows`` columns."""
    out = canvas.copy()
    h, w = out.shape[:2]
    columns = -(-len(names) // rows)
    cell_w, cell_h = w / columns, h / rows
    for k, name in enumerate(names):
        r, c = divmod(k, columns)
        pw = int(cell_w * fill * rng.uniform(0.8, 1.1))
        ph = int(min(cell_h * 0.8, pw * rng.uniform(0.6, 1.2)))
        x = int(c * cell_w + rng.uniform(0.05, 0.95) * (cell_w - pw))
        y = int(r * cell_h + rng.uniform(0.1, 0.9) * (cell_h - ph))
        out[max(0, y - frame):y + ph + frame, max(0, x - frame):x + pw + frame] = 0.08
        out[y:y + ph, x:x + pw] = fit(photo(name), pw, ph)
    return out


def _textured_cylinder(radius: float, height: float, sections: int = 48):
    """A closed cylinder along z, base at z = 0, as a trimesh and its per-vertex UVs ``(V, 2)``.

    The side carries the whole texture round it (the seam's vertices are duplicated so that u runs
    from 0 to 1); the caps map to small discs of it.
    """
    import trimesh

    angle = np.linspace(0.0, 2.0 * np.pi, sections + 1)
    ring = np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)
    side = np.concatenate([np.c_[ring, np.zeros(sections + 1)], np.c_[ring, np.full(sections + 1, height)]])
    side_uv = np.concatenate([np.c_[angle / (2 * np.pi), np.zeros(sections + 1)],
                              np.c_[angle / (2 * np.pi), np.ones(sections + 1)]])
    i = np.arange(sections)
    faces = [np.c_[i, i + 1, i + sections + 2], np.c_[i, i + sections + 2, i + sections + 1]]
    vertices, uv = [side], [side_uv]
    offset = len(side)
    for z, flip in ((0.0, True), (height, False)):  # caps: a centre vertex and a ring, UV a small disc
        cap = np.r_[[[0.0, 0.0, z]], np.c_[ring[:-1], np.full(sections, z)]]
        cap_uv = np.r_[[[0.5, 0.5]], 0.5 + 0.05 * ring[:-1] / radius]
        j = np.arange(sections)
        tri = np.c_[np.zeros(sections, int), 1 + j, 1 + (j + 1) % sections] + offset
        faces.append(tri[:, ::-1] if flip else tri)
        vertices.append(cap)
        uv.append(cap_uv)
        offset += len(cap)
    mesh = trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), process=False)
    return mesh, np.concatenate(uv)


def _yaw(degrees: float) -> np.ndarray:
    return rotvec_to_matrix(np.array([0.0, 0.0, np.radians(degrees)]))


# --- the scenes ---------------------------------------------------------------------------------------------
def _room(rng: np.random.Generator, seed: int) -> Scene:
    s = seed * 101
    half, tall = 4.0, 3.0
    floor = 0.55 * tinted(fit(photo("gravel"), 1024, 1024), (0.85, 0.8, 0.7), contrast=1.2) \
        + 0.45 * shapes_texture(1024, 1024, seed=s + 1, count=900, max_size=0.03, opacity=0.7)
    brick = _modulated(_tiled(tinted(_bricks(), (0.75, 0.4, 0.3), contrast=1.3), 2, 1), s + 2)
    brick = _paste_posters(fit(brick, 1024, 384), ["astronaut", "coffee", "rocket"], rng)
    shapes = shapes_texture(1024, 384, seed=s + 3, count=500)
    grass = _modulated(fit(tinted(photo("grass"), (0.45, 0.7, 0.35), contrast=1.3), 1024, 384), s + 4)
    grass = _paste_posters(grass, ["chelsea", "hubble_deep_field"], rng, fill=0.45)
    panels = _paste_posters(wood_texture(1024, 384, seed=s + 5), ["immunohistochemistry", "cat"], rng,
                            fill=0.4)
    ceiling = noise_texture(512, 512, seed=s + 6, saturation=0.2,
                            colors=np.array([[0.6, 0.6, 0.58], [0.95, 0.95, 0.9]]))
    objects: list[SceneObject] = [
        Plane((-half, -half, 0.0), (1, 0, 0), (0, 1, 0), (2 * half, 2 * half), texture=floor, name="floor"),
        Plane((-half, half, tall), (1, 0, 0), _DOWN, (2 * half, tall), texture=brick, name="north wall"),
        Plane((half, half, tall), (0, -1, 0), _DOWN, (2 * half, tall), texture=grass, name="east wall"),
        Plane((half, -half, tall), (-1, 0, 0), _DOWN, (2 * half, tall), texture=shapes, name="south wall"),
        Plane((-half, -half, tall), (0, 1, 0), _DOWN, (2 * half, tall), texture=panels, name="west wall"),
        Plane((-half, -half, tall), (1, 0, 0), (0, 1, 0), (2 * half, 2 * half), texture=ceiling,
              name="ceiling"),
    ]
    jitter = lambda: rng.uniform(-0.15, 0.15, 3) * (1, 1, 0)  # noqa: E731
    crate = Texture(atlas([photo("astronaut"), photo("coffee"), photo("chelsea"), photo("rocket"),
                           shapes_texture(256, 256, seed=s + 7, count=60), photo("coins")]), "crate")
    tall_box = Texture(atlas([shapes_texture(256, 256, seed=s + 8 + k, count=80) for k in range(6)]),
                       "tall box")
    small_box = Texture(atlas([wood_texture(256, 256, seed=s + 20 + k) for k in range(6)]), "small box")
    objects += [
        Box(np.array([1.3, 1.0, 0.4]) + jitter(), (0.8, 0.8, 0.8), _yaw(25 + rng.uniform(-20, 20)), crate,
            name="crate"),
        Box(np.array([-1.6, 1.2, 0.7]) + jitter(), (0.5, 0.6, 1.4), _yaw(-15 + rng.uniform(-20, 20)),
            tall_box, name="tall box"),
        Box(np.array([0.4, -1.3, 0.2]) + jitter(), (0.5, 0.35, 0.4), _yaw(40 + rng.uniform(-20, 20)),
            small_box, name="small box"),
        Sphere(np.array([-1.0, -0.5, 0.45]) + jitter(), 0.45, fit(photo("hubble_deep_field"), 1024, 512),
               rotation=_yaw(rng.uniform(0, 360)), name="globe"),
        Sphere(np.array([1.7, -0.8, 0.3]) + jitter(), 0.3, shapes_texture(512, 256, seed=s + 9, count=150),
               name="ball"),
    ]
    return Scene(tuple(objects), background=(0.0, 0.0, 0.0), center=(0.0, 0.0, 0.6), home=(0.0, -3.3, 1.6),
                 name="room")


def _table(rng: np.random.Generator, seed: int) -> Scene:
    import trimesh

    s = seed * 101 + 50
    top_z, thickness = 0.75, 0.04
    wood = wood_texture(1024, 640, seed=s)
    leg_wood = Texture(atlas([wood_texture(256, 256, seed=s + 1 + k, rings=4.0) for k in range(6)]), "leg")
    floor = 0.5 * tinted(fit(photo("gravel"), 1024, 1024), (0.7, 0.72, 0.75), contrast=1.3) \
        + 0.5 * shapes_texture(1024, 1024, seed=s + 10, count=700, max_size=0.03, opacity=0.6)
    wall = _paste_posters(_modulated(shapes_texture(1024, 512, seed=s + 11, count=300), s + 12),
                          ["astronaut", "rocket", "chelsea"], rng, fill=0.6)
    objects: list[SceneObject] = [
        Plane((-3.0, -3.0, 0.0), (1, 0, 0), (0, 1, 0), (6.0, 6.0), texture=floor, name="floor"),
        Plane((-3.0, 2.0, 2.0), (1, 0, 0), _DOWN, (6.0, 2.0), texture=wall, name="wall"),
        Box((0.0, 0.0, top_z - thickness / 2), (1.6, 1.0, thickness), texture=leg_wood, name="table body"),
        Plane((-0.8, 0.5, top_z + 1e-4), (1, 0, 0), (0, -1, 0), (1.6, 1.0), texture=wood, name="table top"),
    ]
    for k, (x, y) in enumerate(((-0.72, -0.42), (0.72, -0.42), (-0.72, 0.42), (0.72, 0.42))):
        objects.append(Box((x, y, (top_z - thickness) / 2), (0.06, 0.06, top_z - thickness), texture=leg_wood,
                           name=f"leg {k}"))
    place = lambda x, y: np.array([x, y]) + rng.uniform(-0.06, 0.06, 2)  # noqa: E731
    cereal = Texture(atlas([photo("rocket"), photo("coffee"), photo("astronaut"), photo("chelsea"),
                            shapes_texture(256, 256, seed=s + 2, count=60), photo("coins")]), "cereal box")
    x, y = place(-0.45, 0.15)
    objects.append(Box((x, y, top_z + 0.16), (0.3, 0.1, 0.32), _yaw(rng.uniform(-30, 10)), cereal,
                       name="cereal box"))
    x, y = place(0.05, -0.2)
    objects.append(Sphere((x, y, top_z + 0.11), 0.11, shapes_texture(512, 256, seed=s + 3, count=200),
                          rotation=_yaw(rng.uniform(0, 360)), name="ball"))
    cube = Texture(atlas([shapes_texture(128, 128, seed=s + 30 + k, count=25) for k in range(6)], cell=128),
                   "cube")
    x, y = place(-0.1, 0.3)
    objects.append(Box((x, y, top_z + 0.06), (0.12, 0.12, 0.12), _yaw(rng.uniform(0, 90)), cube, name="cube"))
    can, can_uv = _textured_cylinder(0.05, 0.17)
    x, y = place(0.45, 0.1)
    can.apply_transform(trimesh.transformations.translation_matrix((x, y, top_z)))
    label = np.concatenate([fit(photo("coffee"), 512, 256), fit(photo("astronaut"), 256, 256)], axis=1)
    objects.append(MeshObject(can, texture=label, uv=can_uv, name="can"))
    ring = trimesh.creation.torus(major_radius=0.09, minor_radius=0.03, major_sections=48, minor_sections=16)
    x, y = place(0.45, -0.25)
    ring.apply_transform(trimesh.transformations.translation_matrix((x, y, top_z + 0.03)))
    colours = noise_texture(64, 64, seed=s + 4, saturation=1.0)
    lookup = np.clip(((ring.vertices[:, :2] - (x, y)) / 0.25 + 0.5) * 63, 0, 63).astype(int)
    vertex_colours = np.round(colours[lookup[:, 1], lookup[:, 0]] * 255).astype(np.uint8)
    ring.visual = trimesh.visual.ColorVisuals(ring, vertex_colors=vertex_colours)
    objects.append(MeshObject(ring, name="ring"))
    return Scene(tuple(objects), background=(0.55, 0.7, 0.9), center=(0.0, 0.0, 0.85), home=(0.0, -2.0, 1.6),
                 name="table")


def _facade(rng: np.random.Generator, seed: int) -> Scene:
    s = seed * 101 + 70
    width, height = 14.0, 9.0
    brick = _tiled(tinted(_bricks(), (0.95, 0.7, 0.55), contrast=1.4), 4, 3)
    wall = _modulated(fit(brick, 1400, 900), s + 1, strength=0.3)
    wall = shapes_texture(1400, 900, seed=s + 2, base=wall, count=3000, min_size=0.003, max_size=0.015,
                          opacity=0.6)
    names = ["astronaut", "coffee", "chelsea", "rocket", "cat", "hubble_deep_field", "immunohistochemistry",
             "coins", "camera", "moon", "grass", "gravel"]
    order = rng.permutation(len(names))
    windows = [names[k] for k in order]
    facade = np.array(wall)
    sills: list[SceneObject] = []
    columns, rows = 4, 3
    for k, name in enumerate(windows):
        r, c = divmod(k, columns)
        cx = -width / 2 + (c + 0.5) * width / columns
        top = height - 0.8 - r * height / rows
        ww, wh = 1.8, 1.6
        x0 = int((cx - ww / 2 + width / 2) * 100)
        y0 = int((height - top) * 100)
        facade[y0 - 6:y0 + int(wh * 100) + 6, x0 - 6:x0 + int(ww * 100) + 6] = 0.9
        facade[y0:y0 + int(wh * 100), x0:x0 + int(ww * 100)] = fit(photo(name), int(ww * 100), int(wh * 100))
        sills.append(Box((cx, -0.04, top - wh - 0.05), (ww + 0.2, 0.08, 0.06), color=(0.85, 0.85, 0.8),
                         name=f"sill {k}"))
    objects: list[SceneObject] = [Plane((-width / 2, 0.0, height), (1, 0, 0), _DOWN, (width, height),
                                        texture=facade, name="facade")]
    return Scene(tuple(objects + sills), background=(0.55, 0.72, 0.95), light=(0.25, -0.8, 0.55),
                 center=(0.0, 0.0, 3.5), home=(0.0, -9.0, 1.7), name="facade")


__all__ = ["SCENE_NAMES", "named_scene"]
