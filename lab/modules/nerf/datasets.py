"""The datasets of NeRF: a synthetic object rendered with exact depth, and a folder in the NeRF-synthetic
layout.

Each gives the state ``images`` (:class:`ImageSet`, the training views), ``cameras`` (their
:class:`Cameras`, OpenCV convention, carrying the images), ``test_cameras`` (the held-out poses: a
novel view is rendered from a pose, so poses are inputs) and ``bounds``
(:class:`~lab.modules.nerf.values.SceneBounds`) and ``pixel_supersample`` (an int: how many rays per
pixel along each axis each image's pixel is the mean of, so that ``render_held_out`` renders pixels the
same way); the held-out images (``test_images`` ``(V, H, W, 3)``)
and, for the synthetic object, their exact depths (``test_depths`` ``(V, H, W)``, inf where the ray
misses) are truth.
"""

from __future__ import annotations

import json
import math
import os
from typing import Annotated, Literal

import cv2
import numpy as np

from lab.core import Cameras, Image, ImageSet, InvalidValue, Loaded, Range
from lab.data.files import check_folder, read_image_file
from lab.data.scenes import (Box, MeshObject, Scene, Sphere, atlas, intrinsics, noise_texture, photo, render,
                             shapes_texture, wood_texture)
from lab.data.transforms_json import camera_to_world_opengl, read_transforms_json
from lab.geometry.rotations import look_at
from lab.modules.nerf.values import SceneBounds

WHITE = (1.0, 1.0, 1.0)

#: Horizontal field of view of the synthetic object's cameras (NeRF-synthetic's camera_angle_x is 0.69 rad).
OBJECT_FOV_DEG = 40.0
#: Distance of the synthetic object's cameras from its centre.
OBJECT_DISTANCE = 3.0
#: Rays per pixel along each axis with which the synthetic object's images are rendered (each pixel the
#: mean of 2 x 2): its ``pixel_supersample``, which held-out renders follow.
OBJECT_SUPERSAMPLE = 2


def object_scene(seed: int = 0) -> Scene:
    """A small textured object on a white background: a cube, a ball and a ring (vertex colours), z up,
    about 1.1 m across, centred at the origin; unlit-from-behind Lambert shading as every lab scene."""
    import trimesh

    s = 1000 + 17 * seed
    cube = atlas([shapes_texture(128, 128, seed=s + k, count=12, max_size=0.25) for k in range(6)], cell=128)
    ball = noise_texture(256, 128, seed=s + 7, octaves=3, coarsest=3, saturation=0.9)
    ring = trimesh.creation.torus(major_radius=0.32, minor_radius=0.07, major_sections=48, minor_sections=16)
    ring.apply_transform(trimesh.transformations.translation_matrix((0.05, 0.0, -0.28)))
    colours = noise_texture(32, 32, seed=s + 9, octaves=2, coarsest=2, saturation=1.0)
    lookup = np.clip((ring.vertices[:, :2] / 0.8 + 0.5) * 31, 0, 31).astype(int)
    ring.visual = trimesh.visual.ColorVisuals(
        ring, vertex_colors=np.round(colours[lookup[:, 1], lookup[:, 0]] * 255).astype(np.uint8))
    objects = (Box((-0.15, 0.1, -0.05), (0.4, 0.4, 0.4), texture=cube, name="cube"),
               Sphere((0.22, -0.12, 0.12), 0.2, ball, name="ball"),
               MeshObject(ring, name="ring"))
    return Scene(objects, background=WHITE, center=(0.0, 0.0, 0.0), home=(0.0, -3.0, 1.2), name="object")


def untuned_scene(seed: int = 0) -> Scene:
    """A second object that none of the grid's settings were tuned on (issue 17: "a scene in the
    NeRF-synthetic layout that it was not tuned on"): a wood-grained box turned 30 degrees about z, a ball
    wrapped in a photograph (scikit-image's "chelsea") and a cone coloured per vertex by noise, about
    1.9 m across (the Blender scenes' size: within their 1.5 m of the origin), on white."""
    import trimesh

    s = 5000 + 31 * seed
    turn = math.radians(30.0)
    rotation = np.array([[math.cos(turn), -math.sin(turn), 0.0], [math.sin(turn), math.cos(turn), 0.0],
                         [0.0, 0.0, 1.0]])
    box = Box((-0.35, 0.25, -0.2), (0.7, 0.5, 0.6), rotation=rotation,
              texture=atlas([wood_texture(128, 128, seed=s + k) for k in range(6)], cell=128), name="box")
    ball = Sphere((0.45, -0.3, 0.05), 0.42, photo("chelsea"), name="ball")
    cone = trimesh.creation.cone(radius=0.3, height=0.8, sections=48)
    cone.apply_transform(trimesh.transformations.translation_matrix((-0.3, -0.55, -0.5)))
    colours = noise_texture(32, 32, seed=s + 3, octaves=3, coarsest=2, saturation=1.0)
    lookup = np.clip((cone.vertices[:, :2] + 1.0) / 2.0 * 31, 0, 31).astype(int)
    cone.visual = trimesh.visual.ColorVisuals(
        cone, vertex_colors=np.round(colours[lookup[:, 1], lookup[:, 0]] * 255).astype(np.uint8))
    return Scene((box, ball, MeshObject(cone, name="cone")), background=WHITE, center=(0.0, 0.0, 0.0),
                 home=(0.0, -4.0, 1.5), name="untuned object")


#: Distance of the Blender scenes' cameras from the origin (NeRF-synthetic's lego: 4.03 m).
BLENDER_DISTANCE = 4.0311


def write_nerf_synthetic(folder: str, scene: Scene, *, size: int = 200,
                         views: tuple[int, int, int] = (100, 8, 25)) -> str:
    """Render ``scene`` into ``folder`` in the NeRF-synthetic layout: ``transforms_train.json``,
    ``transforms_val.json`` and ``transforms_test.json`` with ``camera_angle_x`` and one frame a view
    (``file_path`` ``./<split>/r_<i>`` without its ending, ``transform_matrix`` the OpenGL camera-to-world),
    and ``size x size`` RGBA PNGs (8 bit, alpha the object's coverage, colour where it is seen).

    ``views`` = (train, val, test) cameras on the upper hemisphere at :data:`BLENDER_DISTANCE` looking at
    the origin (:func:`hemisphere_cameras`; the splits interleaved). One ray per pixel: read with
    ``nerf_synthetic(downscale=f)``, each pixel is the mean of ``f x f`` of them, as the shared renderer's
    ``supersample=f``. Returns ``folder``."""
    os.makedirs(folder, exist_ok=True)
    for split, count, offset in zip(("train", "val", "test"), views, (0.0, 0.25, 0.5), strict=True):
        cameras = hemisphere_cameras(count, size=size, distance=BLENDER_DISTANCE, offset=offset,
                                     center=np.zeros(3))
        os.makedirs(os.path.join(folder, split), exist_ok=True)
        frames = []
        for i, c2w in enumerate(camera_to_world_opengl(cameras.R, cameras.t)):
            view = render(scene, cameras, i, supersample=1)
            rgba = np.concatenate([view.image.pixels * view.mask[..., None], view.mask[..., None]], axis=2)
            bgra = np.round(np.clip(rgba, 0.0, 1.0) * 255).astype(np.uint8)[:, :, [2, 1, 0, 3]]
            if not cv2.imwrite(os.path.join(folder, split, f"r_{i}.png"), bgra):
                raise InvalidValue("folder", f"could not write an image into {folder!r}")
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        angle = 2.0 * math.atan(size / (2.0 * float(cameras.K[0, 0, 0])))
        with open(os.path.join(folder, f"transforms_{split}.json"), "w") as stream:
            json.dump({"camera_angle_x": angle, "frames": frames}, stream, indent=1)
    return folder


def hemisphere_cameras(count: int, *, size: int, distance: float, offset: float,
                       center: np.ndarray) -> Cameras:
    """``count`` cameras on the upper hemisphere about ``center`` (a spiral: elevations 10 to 60 degrees,
    azimuths by the golden angle, turned by ``offset`` of a step so held-out views fall between), all
    looking at the centre, ``size x size`` pixels with :data:`OBJECT_FOV_DEG`."""
    k = np.arange(count) + offset
    elevation = np.radians(10.0 + 50.0 * ((k * 0.618034) % 1.0))
    azimuth = k * math.radians(137.50776)
    eyes = center + distance * np.stack([np.cos(elevation) * np.cos(azimuth),
                                         np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=1)
    R, t = look_at(eyes, np.broadcast_to(center, eyes.shape), (0.0, 0.0, 1.0))
    fx = size / (2.0 * math.tan(math.radians(OBJECT_FOV_DEG) / 2.0))
    K = intrinsics(width=size, height=size, fx=fx)
    return Cameras(np.broadcast_to(K, (count, 3, 3)).copy(), R, t, size, size)


def synthetic_object(*, size: Literal[100, 200] = 100, train_views: Annotated[int, Range(2, 200)] = 40,
                     test_views: Annotated[int, Range(1, 50)] = 8, seed: int = 0) -> Loaded:
    """A textured object (cube, ball, ring) rendered by the shared ray caster on white, with exact depth.

    Training and held-out cameras lie on the upper hemisphere at 3 m, looking at the object (the
    NeRF-synthetic setup); held-out views sit between training views. Each view is rendered with 2 x 2
    supersampling (``pixel_supersample`` 2); depths are exact at pixel centres. ``bounds``: near and far
    at 3 m minus and plus the object's bounding radius, which also normalizes positions.

    Args:
        size: image width and height in pixels.
        train_views: views to train on.
        test_views: held-out views to evaluate on.
        seed: seed of the textures.
    """
    scene = object_scene(int(seed))
    lower, upper = scene.bounds()
    center = 0.5 * (lower + upper)
    radius = float(0.5 * np.linalg.norm(upper - lower))
    train = hemisphere_cameras(train_views, size=size, distance=OBJECT_DISTANCE, offset=0.0, center=center)
    test = hemisphere_cameras(test_views, size=size, distance=OBJECT_DISTANCE, offset=0.5, center=center)
    train_renders = [render(scene, train, i, supersample=OBJECT_SUPERSAMPLE) for i in range(train_views)]
    test_renders = [render(scene, test, i, supersample=OBJECT_SUPERSAMPLE) for i in range(test_views)]
    images = ImageSet(tuple(Image(r.image.pixels, name=f"train {i}") for i, r in enumerate(train_renders)))
    reach = 1.05 * radius
    bounds = SceneBounds(OBJECT_DISTANCE - reach, OBJECT_DISTANCE + reach, center, reach)
    state = {"images": images, "cameras": _carrying(train, "images"), "test_cameras": test, "bounds": bounds,
             "pixel_supersample": OBJECT_SUPERSAMPLE}
    truth = {"test_images": np.stack([r.image.pixels for r in test_renders]),
             "test_depths": np.stack([r.depth for r in test_renders]),
             "train_depths": np.stack([r.depth for r in train_renders])}
    return Loaded(state, truth, f"a synthetic object, {train_views} training and {test_views} held-out "
                                f"{size}x{size} views on white, exact depth")


def _carrying(cameras: Cameras, image: str) -> Cameras:
    return Cameras(cameras.K, cameras.R, cameras.t, cameras.width, cameras.height, dist=cameras.dist,
                   image=image)


# --- the NeRF-synthetic layout ----------------------------------------------------------------------------
def _split_file(folder: str, split: str) -> str:
    file = os.path.join(folder, f"transforms_{split}.json")
    if not os.path.isfile(file):
        raise InvalidValue("path", f"{folder!r} has no transforms_{split}.json (the NeRF-synthetic layout: "
                                   "transforms_train.json, transforms_val.json, transforms_test.json)")
    return file


def _image_path(folder: str, file_path: str, where: str) -> str:
    """The image a frame names: as written, or with ``.png`` added (NeRF-synthetic omits the ending)."""
    base = os.path.normpath(os.path.join(folder, file_path))
    for candidate in (base, base + ".png"):
        if os.path.isfile(candidate):
            return candidate
    raise InvalidValue(where, f"the image {file_path!r} is missing (looked for {base!r} and "
                              f"{base + '.png'!r})")


def _composited(decoded: np.ndarray, where: str) -> np.ndarray:
    """RGB float32 ``(H, W, 3)`` of a decoded BGR(A) image, alpha composited on white."""
    scale = float(np.iinfo(decoded.dtype).max) if decoded.dtype.kind in "ui" else 1.0
    pixels = decoded.astype(np.float32) / scale
    if pixels.ndim != 3 or pixels.shape[2] not in (3, 4):
        raise InvalidValue(where, f"expected an RGB or RGBA image, got shape {decoded.shape}")
    rgb = pixels[:, :, 2::-1]
    if pixels.shape[2] == 4:
        alpha = pixels[:, :, 3:4]
        rgb = rgb * alpha + (1.0 - alpha)
    return np.ascontiguousarray(np.clip(rgb, 0.0, 1.0))


def _read_split(folder: str, split: str, limit: int, downscale: int) -> tuple[list[np.ndarray], Cameras]:
    """The first ``limit`` frames of one split: images on white, shrunk ``downscale`` times, and cameras."""
    file = _split_file(folder, split)
    K, sizes, R, t, names = _read_frames(file, folder)
    count = min(limit, len(names))
    images: list[np.ndarray] = []
    for i in range(count):
        where = f"transforms_{split}.json frames[{i}]"
        pixels = _composited(read_image_file(_image_path(folder, names[i], where)), where)
        if (pixels.shape[1], pixels.shape[0]) != tuple(sizes[i]):
            raise InvalidValue(where, f"the image is {pixels.shape[1]}x{pixels.shape[0]} but the file says "
                                      f"{sizes[i][0]}x{sizes[i][1]}")
        if images and pixels.shape[:2] != images[0].shape[:2]:
            raise InvalidValue(where, f"the image is {pixels.shape[1]}x{pixels.shape[0]}, the first one "
                                      f"{images[0].shape[1]}x{images[0].shape[0]}: every view must have "
                                      "one size")
        images.append(pixels)
    height, width = images[0].shape[:2]
    if width % downscale or height % downscale:
        raise InvalidValue("downscale", f"{width}x{height} images do not divide by {downscale}")
    if downscale > 1:
        images = [cv2.resize(im, (width // downscale, height // downscale), interpolation=cv2.INTER_AREA)
                  for im in images]
    Ks = K[:count].copy()
    Ks[:, :2, :] /= downscale                      # corner-origin coordinates scale; centres move by 0.5 px
    Ks[:, 0, 2] += 0.5 / downscale - 0.5
    Ks[:, 1, 2] += 0.5 / downscale - 0.5
    return images, Cameras(Ks, R[:count], t[:count], width // downscale, height // downscale)


def _read_frames(file: str,
                 folder: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[str, ...]]:
    """:func:`read_transforms_json` of a NeRF-synthetic file, which gives ``camera_angle_x`` but no image
    size: the size of the first frame's image is the default (a size in the file still wins)."""
    try:
        with open(file) as stream:
            data = json.loads(stream.read())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        data = None
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or not frames or not isinstance(frames[0], dict) \
            or "file_path" not in frames[0]:
        return read_transforms_json(file)          # it names what is wrong with the file
    first = read_image_file(_image_path(folder, str(frames[0]["file_path"]), "frames[0]"))
    return read_transforms_json(file, default_size=(int(first.shape[1]), int(first.shape[0])))


def nerf_synthetic(*, path: str, downscale: Annotated[int, Range(1, 16)] = 8,
                   train_views: Annotated[int, Range(1, 400)] = 100,
                   test_views: Annotated[int, Range(1, 400)] = 25,
                   near: Annotated[float, Range(0.0, 100.0)] = 2.0,
                   far: Annotated[float, Range(0.0, 1000.0)] = 6.0,
                   radius: Annotated[float, Range(1e-3, 1000.0)] = 1.5) -> Loaded:
    """A scene in the NeRF-synthetic layout (Mildenhall et al. 2020's Blender scenes):
    ``transforms_train.json`` and ``transforms_test.json`` with ``camera_angle_x`` and frames naming RGBA
    images beside them.

    The files are read by the lab's one ``transforms.json`` reader (OpenGL camera-to-world turned into
    OpenCV world-to-camera, the principal point moved to the lab's pixel centres); images are
    composited on white and shrunk ``downscale`` times by area averaging (800 px / 8 = 100 px), so each
    pixel is the mean of ``downscale x downscale`` of the file's (``pixel_supersample``). The held-out
    images are the test split. The scene lies within ``radius`` of the origin.

    Args:
        path: the folder holding the transforms files.
        downscale: integer factor the images are shrunk by.
        train_views: at most this many training views (the first ones).
        test_views: at most this many held-out views (the first ones).
        near: nearest depth sampled (the Blender scenes: 2).
        far: farthest depth sampled (the Blender scenes: 6).
        radius: radius about the origin that holds the scene (normalizes positions).
    """
    folder = check_folder(path)
    train_images, train = _read_split(folder, "train", train_views, downscale)
    test_images, test = _read_split(folder, "test", test_views, downscale)
    if (test.width, test.height) != (train.width, train.height):
        raise InvalidValue("path", f"test views are {test.width}x{test.height}, training views "
                                   f"{train.width}x{train.height}")
    bounds = SceneBounds(near, far, np.zeros(3), radius)
    images = ImageSet(tuple(Image(im, name=f"train {i}") for i, im in enumerate(train_images)))
    state = {"images": images, "cameras": _carrying(train, "images"), "test_cameras": test, "bounds": bounds,
             "pixel_supersample": int(downscale)}
    return Loaded(state, {"test_images": np.stack(test_images)},
                  f"{len(train_images)} training and {len(test_images)} held-out "
                  f"{train.width}x{train.height} views from {folder}")


__all__ = ["BLENDER_DISTANCE", "OBJECT_DISTANCE", "OBJECT_FOV_DEG", "OBJECT_SUPERSAMPLE", "WHITE",
           "hemisphere_cameras", "nerf_synthetic", "object_scene", "synthetic_object", "untuned_scene",
           "write_nerf_synthetic"]
