"""Click a pixel, drag a point: the epipolar explorer of the epipolar module.

A click on camera 1's (or 2's) image, drawn as a plane in its frustum in the 3D scene (viser scene
images are clickable, GUI images are not), or a pixel typed in: its epipolar line in the other
image, its ray from the camera's centre, and the epipolar plane through both centres cutting the
other image plane along that line. A 3D point dragged with a gizmo (or typed): its projections in
both images, its epipolar plane, and both of its lines. The math is in
:mod:`lab.viewer.interactions.epipolar.geometry`; this class wires it to viser.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np

from lab.core.errors import LabError, MissingInput
from lab.core.values import ImageSet
from lab.geometry.camera_views import camera_centre, click_to_pixel, image_placement, lift_pixels
from lab.viewer.drawing import draw_overlays, frustum_segments
from lab.viewer.interactions import Interaction, InteractionContext, LegendEntry, NamedHandles, Swatch
from lab.viewer.interactions.epipolar.geometry import (GEOMETRY_READS, PICK_COLOR, POINT_COLOR, PixelPick,
                                                       PointMove, TwoViewGeometry, explorer_overlays,
                                                       label_anchors, move, observed_pairs, pick,
                                                       scene_depths, two_view_geometry)
from lab.viewer.renderers import (FRUSTUM_MAX_SIDE, PANEL_MAX_SIDE, PANEL_MIN_SIDE, overlay_view,
                                  wxyz_from_matrix)

#: Colours (RGB, 0-255) of the two cameras' frustums.
CAMERA_COLORS = ((40, 90, 200), (230, 120, 20))
#: How far apart along the baseline the labels "camera 1" and "camera 2" are pushed, at least: a share of the
#: scene's extent (:func:`lab.viewer.interactions.epipolar.geometry.label_anchors`).
LABEL_SPREAD = 0.1


# ----------------------------------------------------------------------------------------------------
# Interaction 1: click a pixel, drag a point
# ----------------------------------------------------------------------------------------------------
class EpipolarExplorer(Interaction):
    """Click a pixel (in the 3D scene's image planes, or by number) to see its epipolar line and ray; drag a
    3D point to see its projections, its epipolar plane and both of its lines move."""

    title = "Epipolar explorer: click a pixel, drag a point"

    def __init__(self, ctx: InteractionContext) -> None:  # the viewer builds it inside ``with ctx.folder``
        super().__init__(ctx)
        self.lock = threading.RLock()
        self.nodes = NamedHandles()
        self.geometry: TwoViewGeometry | None = None
        self.images: ImageSet | None = None
        self.depth = 1.0  # depth of the image planes drawn in the frustums
        self.far = 8.0
        self.typical = 5.0
        self.last_pick: PixelPick | None = None
        self.last_point: PointMove | None = None
        self.textures: list[np.ndarray | None] = [None, None]  # what the image planes / panel images show
        self._key: tuple | None = None
        self._syncing = False
        self._handle: Any = None
        self._bases: dict[tuple[int, int, str], np.ndarray] = {}
        gui = ctx.gui
        self.source_md = self.track(gui.add_markdown("Open a two-image session."))
        self.image_choice = self.track(gui.add_dropdown("pixel in", ("image 1", "image 2"),
                                                        initial_value="image 1",
                                                        hint="which image the pixel (u, v) is in"))
        self.pixel_input = self.track(gui.add_vector2("pixel (u, v)", (0.0, 0.0), step=1.0,
                                                      hint="a pixel: its epipolar line in the other image "
                                                           "and its ray in 3D (or click an image plane in "
                                                           "the scene)"))
        self.pick_button = self.track(gui.add_button("Show epipolar line", hint="use the pixel above"))
        self.pick_md = self.track(gui.add_markdown(""))
        self.point_input = self.track(gui.add_vector3("3D point (x, y, z)", (0.0, 0.0, 5.0), step=0.01,
                                                      hint="a point in camera 1's frame (or drag the gizmo)"))
        self.point_md = self.track(gui.add_markdown(""))
        with ctx.images:
            self.panel_folder = self.track(gui.add_folder("Epipolar explorer", order=1000.0))
            with self.panel_folder:
                self.panel_images = [self.track(gui.add_image(np.zeros((8, 8, 3), np.uint8),
                                                              label=f"image {i}",
                                                              format="jpeg")) for i in (1, 2)]
        self.pick_button.on_click(lambda _: ctx.guarded(self._pick_from_inputs)())
        self.pixel_input.on_update(lambda _: None if self._syncing else ctx.guarded(self._pick_from_inputs)())
        self.point_input.on_update(lambda _: None if self._syncing else
                                   ctx.guarded(lambda: self._move(self.point_input.value,
                                                                  from_handle=False))())

    # --- public actions (what a click, a drag or a test does) --------------------------------------
    def pick_pixel(self, u: float, v: float, *, image: Literal[1, 2] = 1) -> PixelPick | None:
        """Show the epipolar line and ray of pixel ``(u, v)`` of image ``image``; None (error shown) when
        invalid."""
        return self.ctx.attempt(lambda: self._pick((u, v), image))

    def click_image(self, image: Literal[1, 2], ray_origin: Any, ray_direction: Any) -> PixelPick | None:
        """A click on the image plane of camera ``image`` (its ray in world coordinates): pick that pixel."""
        return self.ctx.attempt(lambda: self._click(image, ray_origin, ray_direction))

    def pixel_clicked(self, image_name: str, view: int, pixel: np.ndarray) -> bool:
        """A click on the picture of a camera frustum the session draws (its ``images``, view 0 or 1): pick
        that pixel, as a click on the explorer's own image planes does."""
        if image_name != "images" or view not in (0, 1) or self.geometry is None:
            return False
        self.pick_pixel(float(pixel[0]), float(pixel[1]), image=1 if view == 0 else 2)
        return True

    def move_point(self, xyz: Any) -> PointMove | None:
        """Move the 3D point to ``xyz`` (camera 1 frame); None (error shown) when invalid."""
        return self.ctx.attempt(lambda: self._move(xyz, from_handle=False))

    def scene_nodes(self) -> list[str]:
        """Names of the scene nodes drawn now."""
        with self.lock:
            return self.nodes.names()

    def legend(self) -> list[LegendEntry]:
        """The two cameras with their image planes, and the pick and the point when there are some."""
        with self.lock:
            if self.geometry is None or not self.nodes.names():
                return []
            rig = (Swatch(CAMERA_COLORS[0], "camera 1"), Swatch(CAMERA_COLORS[1], "camera 2"))
            entries = [LegendEntry("explorer cameras", "cameras", 2, rig,
                                   "each with its image as a plane: click one to pick a pixel")]
            if self.last_pick is not None:
                entries.append(LegendEntry("picked pixel", "ray", 1, (Swatch(
                    PICK_COLOR, "its ray, epipolar plane and epipolar line in the other image"),)))
            if self.last_point is not None:
                entries.append(LegendEntry("3D point", "point", 1, (Swatch(
                    POINT_COLOR, "its rays to both cameras, its epipolar plane and lines (drag it)"),)))
            return entries

    def bounds(self) -> np.ndarray | None:
        """``(2, 3)`` min and max corner of what the explorer draws (both cameras, the ray, the point), or
        None: for framing the tab's camera before the session has 3D values of its own."""
        with self.lock:
            geometry = self.geometry
            camera = None if geometry is None else geometry.camera(1)
            if geometry is None or camera is None:
                return None
            corners = np.array([[0.0, 0.0], geometry.sizes[0]], dtype=np.float64)
            points = [np.zeros((1, 3)), lift_pixels(*camera, corners, self.typical)]
            if geometry.has_pose:
                points.append(geometry.centres())
            if self.last_point is not None:
                points.append(self.last_point.point.reshape(1, 3))
            every = np.concatenate(points)
            return np.stack([every.min(axis=0), every.max(axis=0)])

    # --- viser wiring -------------------------------------------------------------------------------
    def _pick_from_inputs(self) -> None:
        image = 2 if self.image_choice.value == "image 2" else 1
        self._pick(self.pixel_input.value, image)

    def _click(self, image: int, ray_origin: Any, ray_direction: Any) -> PixelPick:
        with self.lock:
            camera = self._require_geometry().require_camera(image)
            pixel = click_to_pixel(ray_origin, ray_direction, *camera, self.depth)
            return self._pick(pixel, image)

    def _require_geometry(self) -> TwoViewGeometry:
        if self.geometry is None:
            raise MissingInput("images", "the session has no pair of images")
        return self.geometry

    def _pick(self, pixel: Any, image: int) -> PixelPick:
        with self.lock:
            result = pick(self._require_geometry(), pixel, image=image, far=self.far)
            self.last_pick = result
            self._sync_inputs(pixel=result.pixel, image=image)
            self._draw_pick()
            self._draw_textures()
            return result

    def _move(self, xyz: Any, *, from_handle: bool, panels: bool = True) -> PointMove:
        """Move the point; ``panels`` False (while the gizmo is dragged) redraws only the scene's image
        planes."""
        with self.lock:
            result = move(self._require_geometry(), xyz)
            self.last_point = result
            self._sync_inputs(point=result.point)
            if not from_handle and self._handle is not None:
                self._handle.position = tuple(float(v) for v in result.point)
            self._draw_point()
            self._draw_textures(panels=panels)
            return result

    def _sync_inputs(self, *, pixel: np.ndarray | None = None, image: int | None = None,
                     point: np.ndarray | None = None) -> None:
        self._syncing = True
        try:
            if pixel is not None:
                self.pixel_input.value = (float(pixel[0]), float(pixel[1]))
            if image is not None:
                self.image_choice.value = f"image {image}"
            if point is not None:
                self.point_input.value = tuple(float(v) for v in point)
        finally:
            self._syncing = False

    # --- redraw on new state --------------------------------------------------------------------------
    def update(self, state: Mapping[str, Any]) -> None:
        state = self.ctx.values(GEOMETRY_READS, state)
        truth = self.ctx.session.truth
        names = ("images", "K1", "K2", "F", "R", "t", "pose", "x1", "inliers")
        key = tuple(id(state.get(name)) for name in names)
        with self.lock:
            if key == self._key:
                return
            self._key = key
            self.geometry = geometry = two_view_geometry(state, truth)
            self.images = state.get("images") if geometry is not None else None
            self.nodes.clear()
            self._handle = None
            if geometry is None:
                self.last_pick = self.last_point = None
                self.source_md.content = "This session has no pair of images."
                return
            self.typical, self.far = scene_depths(geometry, observed_pairs(state, truth))
            pose = geometry.pose
            baseline = float(np.linalg.norm(pose.t)) if pose is not None else self.typical / 5.0
            self.depth = max(min(0.35 * baseline, 0.25 * self.typical), 1e-3 * self.typical)
            self.source_md.content = self._sources()
            self._draw_rig()
            # redo the last pick and point with the new geometry (drop them when no longer possible)
            for redo in (self._redo_pick, self._redo_point):
                with contextlib.suppress(LabError):
                    redo()
            self._draw_textures()

    def _redo_pick(self) -> None:
        old, self.last_pick = self.last_pick, None
        self.pick_md.content = ""
        if old is not None:
            self.last_pick = pick(self._require_geometry(), old.pixel, image=old.image, far=self.far)
            self._draw_pick()

    def _redo_point(self) -> None:
        old, self.last_point = self.last_point, None
        self.point_md.content = ""
        geometry = self._require_geometry()
        pose = geometry.pose
        if pose is None:
            return
        (width, height), _ = geometry.sizes
        start = old.point if old is not None else lift_pixels(
            pose.K1, np.eye(3), np.zeros(3), np.array([[(width - 1) / 2, (height - 1) / 2]]), self.typical)[0]
        self.last_point = move(geometry, start)
        self._sync_inputs(point=self.last_point.point)
        self._add_handle(self.last_point.point)
        self._draw_point()

    def _sources(self) -> str:
        g = self._require_geometry()
        units = " (units of the truth)." if g.pose_source == "the ground truth" else " (baseline = 1)."
        lines = [f"**F** from {g.f_source}." if g.F is not None else
                 "**F**: none yet (run the 8-point or RANSAC step; this dataset has no ground truth).",
                 f"**Pose** from {g.pose_source}{units}" if g.R is not None else
                 "**Pose**: none yet (run recover_pose): no camera 2 in 3D.",
                 "Click an image plane in the scene (camera 1 or 2) or type a pixel; drag the gizmo to move "
                 "the 3D point."]
        if g.K1 is None:
            lines.append("No K: the rays cannot be drawn in 3D.")
        return "  \n".join(lines)

    # --- scene drawing -------------------------------------------------------------------------------------
    def _draw_rig(self) -> None:
        """Both cameras: a frustum and the image as a clickable plane at ``self.depth``."""
        geometry = self._require_geometry()
        placed: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # image -> (centre, plane corners)
        for image in (1, 2):
            camera = geometry.camera(image)
            if camera is None:
                continue
            width, height = geometry.sizes[image - 1]
            placed[image] = (camera_centre(camera[1], camera[2]),
                             image_placement(*camera, width, height, self.depth).corners)
        if not placed:
            return
        centres = np.stack([centre for centre, _ in placed.values()])
        baseline = float(np.linalg.norm(centres[-1] - centres[0]))
        anchors = label_anchors(centres, [corners for _, corners in placed.values()],
                                spread=max(0.5 * baseline, LABEL_SPREAD * self.ctx.extent()))
        for (image, (centre, corners)), anchor in zip(placed.items(), anchors, strict=True):
            self._draw_camera(image, frustum_segments(centre, corners), anchor)

    def _draw_camera(self, image: int, segments: np.ndarray, label_at: np.ndarray) -> None:
        scene, node = self.ctx.scene, self.ctx.node
        self.nodes.put(f"rig/camera{image}/frustum", lambda: scene.add_line_segments(
            node("rig", f"camera{image}", "frustum"), points=segments, colors=CAMERA_COLORS[image - 1],
            thickness=2.0, thickness_units="screen"))
        self.nodes.put(f"rig/camera{image}/label", lambda: scene.add_label(
            node("rig", f"camera{image}", "label"), f"camera {image}", position=tuple(label_at)))

    def _image_plane(self, image: int, texture: np.ndarray) -> None:
        geometry = self._require_geometry()
        camera = geometry.camera(image)
        if camera is None:
            return
        width, height = geometry.sizes[image - 1]
        placement = image_placement(*camera, width, height, self.depth)
        name = f"rig/camera{image}/image"
        handle = self.nodes.handles.get(name)
        if handle is not None:
            handle.image = texture
            return
        handle = self.nodes.put(name, lambda: self.ctx.scene.add_image(
            self.ctx.node("rig", f"camera{image}", "image"), texture, placement.render_width,
            placement.render_height, format="jpeg", jpeg_quality=85,
            wxyz=wxyz_from_matrix(placement.rotation), position=placement.position, cast_shadow=False,
            receive_shadow=False))
        handle.on_click(lambda event, image=image: self.ctx.guarded(
            lambda: self._click(image, event.ray_origin, event.ray_direction))())

    def _draw_textures(self, *, panels: bool = True) -> None:
        """Both images with the current overlays: on the image planes in 3D and (``panels``) in the Images
        panel."""
        images = self.images
        if self.geometry is None or images is None:
            return
        overlays = explorer_overlays(self.geometry, self.last_pick, self.last_point)
        for index in (0, 1):
            image = images[index]
            texture = draw_overlays(image, overlays[index], base=self._base(images, index, "plane"))
            self.textures[index] = texture
            self._image_plane(index + 1, texture)
            if not panels:
                continue
            panel = draw_overlays(image, overlays[index], base=self._base(images, index, "panel"))
            self.panel_images[index].image = panel
            self.panel_images[index].label = f"image {index + 1}: " + ", ".join(
                ["yellow: picked pixel / its epipolar line"] * (self.last_pick is not None)
                + ["magenta: the 3D point's projection and epipolar line"] * (self.last_point is not None)
                + ["white: epipole"])

    def _base(self, images: ImageSet, index: int, kind: Literal["plane", "panel"]) -> np.ndarray:
        """Image ``index`` resized for a scene plane or the panel, without overlays (made once per image
        set)."""
        key = (id(images), index, kind)
        if key not in self._bases:
            sides = {"plane": (FRUSTUM_MAX_SIDE, None), "panel": (PANEL_MAX_SIDE, PANEL_MIN_SIDE)}[kind]
            self._bases = {k: v for k, v in self._bases.items() if k[0] == id(images)}
            self._bases[key] = overlay_view(images[index], [], max_side=sides[0], min_side=sides[1])
        return self._bases[key]

    def _segments(self, name: str, points: np.ndarray, color: tuple[int, int, int]) -> None:
        self.nodes.put(name, lambda: self.ctx.scene.add_line_segments(
            self.ctx.node(*name.split("/")), points=np.asarray(points, dtype=np.float32).reshape(-1, 2, 3),
            colors=color, thickness=3.0, thickness_units="screen"))

    def _mesh(self, name: str, vertices: np.ndarray, faces: np.ndarray, color: tuple[int, int, int]) -> None:
        self.nodes.put(name, lambda: self.ctx.scene.add_mesh_simple(
            self.ctx.node(*name.split("/")), np.asarray(vertices, dtype=np.float32),
            np.asarray(faces, dtype=np.uint32), color=color, opacity=0.35, side="double", cast_shadow=False,
            receive_shadow=False))

    def _lifted(self, image: int, segment: np.ndarray | None) -> np.ndarray | None:
        """A 2D segment of image ``image`` on its plane in 3D, ``(1, 2, 3)`` (just in front of the
        texture)."""
        camera = self._require_geometry().camera(image)
        if camera is None or segment is None:
            return None
        return lift_pixels(*camera, segment, 0.995 * self.depth).reshape(1, 2, 3)

    def _draw_pick(self) -> None:
        self.nodes.drop("pick")
        result = self.last_pick
        if result is None:
            return
        marker = None
        if result.ray is not None:
            self._segments("pick/ray", result.ray, PICK_COLOR)
            camera = self._require_geometry().require_camera(result.image)
            marker = lift_pixels(*camera, result.pixel.reshape(1, 2), self.depth)[0]
            self.nodes.put("pick/pixel", lambda: self.ctx.scene.add_icosphere(
                self.ctx.node("pick", "pixel"), radius=0.02 * self.depth, color=PICK_COLOR,
                position=tuple(marker)))
        if result.plane is not None:
            self._mesh("pick/plane", result.plane, np.array([[0, 1, 2]]), PICK_COLOR)
            self._segments("pick/baseline", result.plane[:2], (80, 80, 80))
        lifted = self._lifted(3 - result.image, result.segment)
        if lifted is not None:
            self._segments("pick/line", lifted, PICK_COLOR)
        text = [f"Pixel ({result.pixel[0]:.1f}, {result.pixel[1]:.1f}) of image {result.image} → epipolar "
                f"line {result.line[0]:.4f} u {result.line[1]:+.4f} v {result.line[2]:+.1f} = 0 in image "
                f"{3 - result.image}"
                + ("" if result.segment is not None else " (it misses the image)") + "."]
        if result.ray is not None:
            direction = (result.ray[1] - result.ray[0]) / np.linalg.norm(result.ray[1] - result.ray[0])
            text.append(f"Its ray leaves camera {result.image}'s centre along "
                        f"({', '.join(f'{v:.3f}' for v in direction)});"
                        + (" the epipolar plane (yellow) holds it and both centres, and cuts image "
                           f"{3 - result.image} along the line." if result.plane is not None else ""))
        self.pick_md.content = "  \n".join(text)

    def _add_handle(self, point: np.ndarray) -> None:
        handle = self.nodes.put("point/handle", lambda: self.ctx.scene.add_transform_controls(
            self.ctx.node("point", "handle"), scale=max(0.15 * self.typical, 1e-3), disable_rotations=True,
            depth_test=False, position=tuple(float(v) for v in point)))
        self._handle = handle

        def dragged(event: Any) -> None:  # the panel images wait for the end of the drag
            self._move(np.asarray(event.target.position, dtype=np.float64), from_handle=True,
                       panels=getattr(event, "phase", "end") != "update")

        handle.on_update(lambda event: self.ctx.guarded(dragged)(event))

    def _draw_point(self) -> None:
        for name in [n for n in self.nodes.names() if n.startswith("point/") and n != "point/handle"]:
            self.nodes.drop_exact(name)
        result = self.last_point
        if result is None:
            return
        c1, c2 = self._require_geometry().centres()
        X = result.point
        self._segments("point/rays", np.array([[c1, X], [c2, X]]), POINT_COLOR)
        self._mesh("point/plane", result.plane, np.array([[0, 1, 2], [0, 2, 3]]), POINT_COLOR)
        self._segments("point/baseline", np.array([[c1, c2]]), (80, 80, 80))
        self.nodes.put("point/marker", lambda: self.ctx.scene.add_icosphere(
            self.ctx.node("point", "marker"), radius=0.015 * self.far, color=POINT_COLOR, position=tuple(X)))
        for image in (1, 2):
            lifted = self._lifted(image, result.segments[image - 1])
            if lifted is not None:
                self._segments(f"point/line{image}", lifted, POINT_COLOR)
        rows = []
        for index in (0, 1):
            where = "behind the camera!" if result.depths[index] <= 0 else f"depth {result.depths[index]:.3g}"
            rows.append(f"image {index + 1}: ({result.pixels[index, 0]:.1f}, {result.pixels[index, 1]:.1f}), "
                        f"{where}")
        self.point_md.content = ("Point (" + ", ".join(f"{v:.3g}" for v in X) + ") projects to  \n"
                                 + "  \n".join(rows)
                                 + "  \nIts epipolar plane (magenta) holds both centres; it cuts each image "
                                   "along the point's epipolar line, through the projection and the epipole.")

    def close(self) -> None:
        with self.lock:
            self.nodes.clear()
            self._handle = None
        super().close()


__all__ = ["CAMERA_COLORS", "EpipolarExplorer"]
