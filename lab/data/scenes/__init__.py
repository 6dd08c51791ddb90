"""Synthetic scenes shared by every module that needs photographs of a 3D world.

A :class:`Scene` holds textured planes, boxes, spheres and trimesh meshes; :func:`render` casts
one ray per pixel sample through an OpenCV camera (``K``, distortion, ``X_c = R X_w + t``) and
returns the image, the exact depth and a mask; :func:`named_scene` builds "room", "table" and
"facade"; :func:`orbit_cameras`, :func:`forward_cameras` and :func:`stereo_rig` make camera paths.

    from lab.data.scenes import named_scene, orbit_cameras, render
    scene = named_scene("room", seed=0)
    cameras = orbit_cameras(scene, num_views=2, arc_deg=10.0)
    view = render(scene, cameras, 0)          # view.image, view.depth, view.mask
"""

from lab.data.scenes.cameras import DEFAULT_FOV_DEG, forward_cameras, intrinsics, orbit_cameras, stereo_rig
from lab.data.scenes.named import SCENE_NAMES, named_scene
from lab.data.scenes.objects import NEAR, Box, MeshObject, Plane, Scene, SceneObject, Sphere, moller_trumbore
from lab.data.scenes.render import MAX_SUPERSAMPLE, Rendering, pixel_rays, render, render_views
from lab.data.scenes.textures import (PHOTO_NAMES, Texture, atlas, noise_texture, photo, shapes_texture,
                                      tinted, wood_texture)

__all__ = ["DEFAULT_FOV_DEG", "MAX_SUPERSAMPLE", "NEAR", "PHOTO_NAMES", "SCENE_NAMES", "Box", "MeshObject",
           "Plane", "Rendering", "Scene", "SceneObject", "Sphere", "Texture", "atlas", "forward_cameras",
           "intrinsics", "moller_trumbore", "named_scene", "noise_texture", "orbit_cameras", "photo",
           "pixel_rays", "render", "render_views", "shapes_texture", "stereo_rig", "tinted", "wood_texture"]
