"""Interactions of the texture module: watch a texture grow, ask a pixel why, see the cuts, wrap it on a mesh.

* **Efros–Leung growth**: the fill order colour-mapped (early blue, late red) and a slider that
  replays the growth pixel by pixel. **Click an output pixel** (on the texture shown as a plane in
  the scene, or with the row/column inputs): its window as it was when the pixel was filled (known
  pixels only), its distances to every sample window, the candidates within (1 + epsilon) of the
  best (yellow) and the window it copied (green), marked on the sample beside the texture.
* **Quilting cuts**: for a block (slider, or a click on the quilt), its overlap error surface
  colour-mapped with the minimum-error cut drawn on it, and the block outlined on the quilt.
* **Texture on a mesh**: until step ``wrap_on_mesh`` has run, a preview of a texture on a plane, cylinder
  or torus as an image map through its UVs (``trimesh.visual.TextureVisuals``); once it has, the scene shows
  the step's own ``textured_mesh`` (one mesh, where the preview was) and the folder shows the controls it
  ran with.

The scene is laid out in rows (y down): the mesh at the origin, the Efros–Leung texture and its sample
above it, the quilt above those, each labelled in the scene and listed in the legend (:meth:`legend`).

The math lives in pure functions (tested directly): :func:`plane_pixel`, :func:`fill_order_image`,
:func:`growth_frame`, :func:`match_panel`, :func:`window_panel`, :func:`block_at`,
:func:`overlap_panel`; the classes wire them to viser. What the synthesis computed is replayed with
:func:`lab.modules.texture.efros_leung_pixel_matches` (the same integer distances).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from lab.core.errors import InvalidValue, MissingInput
from lab.core.values import Image, Mesh
from lab.modules.texture import (EfrosLeungTrace, PixelMatches, QuiltLayout, efros_leung_pixel_matches,
                                 parametric_surface, textured_trimesh)
from lab.viewer.interactions import Interaction, InteractionContext, LegendEntry, NamedHandles, Swatch
from lab.viewer.renderers import to_rgb8

CANDIDATE_COLOR = (255, 210, 0)
CHOSEN_COLOR = (30, 200, 60)
WINDOW_COLOR = (255, 60, 200)
CUT_COLOR = (255, 40, 40)
UNKNOWN_COLOR = (70, 70, 90)

#: Side of the planes the texture and the sample are drawn on in the scene (scene units per output side).
PLANE_SIDE = 2.0
#: Where the rows of the scene are (y, up is -y): the Efros–Leung texture and sample above the mesh at the
#: origin (a torus of radius 1.4), the quilt above them.
GROWTH_ROW_Y = -2.75
QUILT_ROW_Y = -5.35
#: Panels are scaled up to at least this many pixels on their longer side.
PANEL_SIDE = 240
#: The state values each interaction reads (through ``ctx.values``; each one of the pipeline's views):
#: the Efros–Leung texture, its trace and the sample (:class:`GrowthExplorer`), the quilt and its layout
#: (:class:`QuiltExplorer`); the mesh viewer reads the textures of :data:`TEXTURES`.
GROWTH_READS = ("efros_leung", "efros_leung_trace", "sample")
QUILT_READS = ("quilting_layout", "quilting")


# ----------------------------------------------------------------------------------------------------
# Pure functions
# ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Plane:
    """An image of ``width x height`` pixels drawn flat in the scene's z = ``position[2]`` plane, centred at
    ``position``, ``scale`` scene units per pixel; u (columns) along +x, v (rows) along +y (viser's image
    axes)."""

    position: tuple[float, float, float]
    width: int
    height: int
    scale: float

    def point(self, row: float, col: float) -> np.ndarray:
        """The scene point ``(3,)`` of pixel centre ``(row, col)``."""
        x = self.position[0] + (col - (self.width - 1) / 2.0) * self.scale
        y = self.position[1] + (row - (self.height - 1) / 2.0) * self.scale
        return np.array([x, y, self.position[2]])


def label_position(plane: Plane) -> tuple[float, float, float]:
    """Where a scene label naming ``plane`` goes: just above its top edge's middle (up is -y)."""
    x, y, z = plane.point(-0.5, (plane.width - 1) / 2) - np.array([0.0, 0.12, 0.0])
    return float(x), float(y), float(z)


def plane_pixel(plane: Plane, ray_origin: Any, ray_direction: Any) -> tuple[int, int]:
    """The pixel ``(row, col)`` of ``plane`` a click's ray hits (InvalidValue when it misses or runs
    parallel)."""
    origin = np.asarray(ray_origin, dtype=np.float64).reshape(3)
    direction = np.asarray(ray_direction, dtype=np.float64).reshape(3)
    if abs(direction[2]) < 1e-12:
        raise InvalidValue("click", "the click's ray runs parallel to the image plane")
    s = (plane.position[2] - origin[2]) / direction[2]
    if s <= 0:
        raise InvalidValue("click", "the image plane is behind the viewer along the click's ray")
    hit = origin + s * direction
    col = (hit[0] - plane.position[0]) / plane.scale + (plane.width - 1) / 2.0
    row = (hit[1] - plane.position[1]) / plane.scale + (plane.height - 1) / 2.0
    r, c = int(np.floor(row + 0.5)), int(np.floor(col + 0.5))
    if not (0 <= r < plane.height and 0 <= c < plane.width):
        raise InvalidValue("click", f"({r}, {c}) is outside the {plane.width} x {plane.height} image")
    return r, c


def _upscaled(pixels: np.ndarray, side: int = PANEL_SIDE) -> tuple[np.ndarray, int]:
    """``pixels`` (uint8 RGB) enlarged by an integer factor (nearest) to about ``side``: (image, factor)."""
    factor = max(1, side // max(pixels.shape[:2]))
    return np.repeat(np.repeat(pixels, factor, axis=0), factor, axis=1), factor


def _turbo(values: np.ndarray) -> np.ndarray:
    """``(H, W)`` values in [0, 1] -> uint8 RGB with OpenCV's turbo colour map."""
    levels = np.clip(np.nan_to_num(values) * 255 + 0.5, 0, 255).astype(np.uint8)
    return cv2.applyColorMap(levels, cv2.COLORMAP_TURBO)[:, :, ::-1].copy()


def fill_order_image(trace: EfrosLeungTrace, upto: int | None = None) -> np.ndarray:
    """The fill order colour-mapped (first blue to last red), uint8 ``(H, W, 3)``; pixels filled at or after
    ``upto`` (all when None) are dark."""
    order = trace.fill_order.astype(np.float64)
    rgb = _turbo(order / max(order.max(), 1.0))
    if upto is not None:
        rgb[trace.fill_order >= upto] = UNKNOWN_COLOR
    return rgb


def growth_frame(texture: Image, trace: EfrosLeungTrace, upto: int) -> np.ndarray:
    """The texture as it was after ``upto`` pixels were filled: uint8 ``(H, W, 3)``, the rest dark."""
    rgb = to_rgb8(texture.pixels)
    rgb = rgb.copy()
    rgb[trace.fill_order >= upto] = UNKNOWN_COLOR
    return rgb


def window_panel(matches: PixelMatches) -> np.ndarray:
    """The pixel's window as it was when it was filled, unknown pixels dark, the pixel itself outlined."""
    rgb = to_rgb8(matches.window).copy()
    rgb[~matches.known] = UNKNOWN_COLOR
    big, factor = _upscaled(rgb)
    c = matches.known.shape[0] // 2
    cv2.rectangle(big, (c * factor, c * factor), ((c + 1) * factor - 1, (c + 1) * factor - 1), WINDOW_COLOR,
                  2)
    return big


def match_panel(sample: Image, matches: PixelMatches, window: int) -> np.ndarray:
    """The sample with the candidate windows' centres (yellow) and the copied window (green box)."""
    big, factor = _upscaled(to_rgb8(sample.pixels).copy())
    half = window // 2
    for top, left in matches.candidates:
        centre = (int((left + half + 0.5) * factor), int((top + half + 0.5) * factor))
        cv2.circle(big, centre, max(2, factor // 2), CANDIDATE_COLOR, -1)
    top, left = (int(v) for v in matches.chosen)
    cv2.rectangle(big, (left * factor, top * factor),
                  ((left + window) * factor - 1, (top + window) * factor - 1),
                  CHOSEN_COLOR, 2)
    return big


def block_at(layout: QuiltLayout, row: int, col: int) -> int:
    """Index of the block whose pixel is on top at output pixel ``(row, col)`` (the last one that kept it)."""
    found = -1
    for k, ((y, x), kept) in enumerate(zip(layout.positions, layout.new_pixels, strict=True)):
        if y <= row < y + layout.block and x <= col < x + layout.block and kept[row - y, col - x]:
            found = k
    if found < 0:
        raise InvalidValue("pixel", f"({row}, {col}) is in no block of the quilt")
    return found


def cut_mask(layout: QuiltLayout, index: int) -> np.ndarray:
    """``(B, B)`` bool: the pixels of the overlap on the cut (kept pixels with a dropped 4-neighbour)."""
    kept = layout.new_pixels[index]
    overlap = layout.errors[index] > 0
    if not overlap.any():
        overlap = np.zeros_like(kept)
        y, x = layout.positions[index]
        if x > 0:
            overlap[:, :layout.overlap] = True
        if y > 0:
            overlap[:layout.overlap, :] = True
    padded = np.pad(kept, 1, constant_values=True)
    dropped_next = ~padded[:-2, 1:-1] | ~padded[2:, 1:-1] | ~padded[1:-1, :-2] | ~padded[1:-1, 2:]
    edge = kept & dropped_next
    y, x = layout.positions[index]
    if x > 0:  # a straight (uncut) left edge is a seam too
        edge[:, 0] |= kept[:, 0] & ~dropped_next[:, 0] & ~edge[:, :layout.overlap].any(axis=1)
    if y > 0:
        edge[0, :] |= kept[0, :] & ~dropped_next[0, :] & ~edge[:layout.overlap, :].any(axis=0)
    return edge & (overlap | (np.arange(kept.shape[0])[:, None] < layout.overlap)
                   | (np.arange(kept.shape[1])[None, :] < layout.overlap))


def overlap_panel(layout: QuiltLayout, index: int) -> np.ndarray:
    """Block ``index``'s overlap error surface colour-mapped (dark outside the overlap), its cut in red."""
    if not 0 <= index < len(layout.positions):
        raise InvalidValue("block", f"must be in [0, {len(layout.positions) - 1}], got {index}")
    errors = layout.errors[index]
    peak = errors.max()
    rgb = _turbo(errors / peak if peak > 0 else errors)
    y, x = layout.positions[index]
    inside = np.zeros(errors.shape, dtype=bool)
    if x > 0:
        inside[:, :layout.overlap] = True
    if y > 0:
        inside[:layout.overlap, :] = True
    rgb[~inside] = (25, 25, 35)
    rgb[cut_mask(layout, index) & inside] = CUT_COLOR
    return _upscaled(rgb)[0]


def _rectangle(plane: Plane, top: float, left: float, height: float, width: float) -> np.ndarray:
    """Segments ``(4, 2, 3)`` outlining pixels ``top .. top + height - 1`` x ``left .. left + width - 1``."""
    bottom, right = top + height - 0.5, left + width - 0.5
    corners = np.stack([plane.point(top - 0.5, left - 0.5), plane.point(top - 0.5, right),
                        plane.point(bottom, right), plane.point(bottom, left - 0.5)])
    corners[:, 2] += 0.002 * plane.scale * max(plane.width, plane.height)  # just above the image
    return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1).astype(np.float32)


# ----------------------------------------------------------------------------------------------------
# Interaction 1: Efros–Leung growth and a clicked pixel's matches
# ----------------------------------------------------------------------------------------------------
class GrowthExplorer(Interaction):
    """Replay an Efros–Leung texture's growth and explain one pixel's choice."""

    title = "Efros–Leung: growth and matches"

    def __init__(self, ctx: InteractionContext) -> None:
        super().__init__(ctx)
        gui = ctx.gui
        self.nodes = NamedHandles()
        self.texture: Image | None = None
        self.trace: EfrosLeungTrace | None = None
        self.sample: Image | None = None
        self.matches: PixelMatches | None = None
        self.pixel: tuple[int, int] | None = None
        self.output_plane: Plane | None = None
        self.sample_plane: Plane | None = None
        self.info = self.track(gui.add_markdown("Run **synthesize_efros_leung** to watch the texture grow."))
        self.grown = self.track(gui.add_slider("grown pixels", min=0, max=1, step=1, initial_value=1,
                                               disabled=True))
        self.pixel_input = self.track(gui.add_vector2("pixel (row, col)", (0.0, 0.0), step=1.0))
        self.explain = self.track(gui.add_button("Explain this pixel",
                                                 hint="its window, candidates and the copy"))
        self.syncing = False  # set while the code moves a slider (viser calls on_update for those too)
        self.grown.on_update(lambda _: None if self.syncing else ctx.guarded(
            lambda: self.show_growth(int(self.grown.value)))())
        self.explain.on_click(lambda _: ctx.guarded(
            lambda: self.pick_pixel(round(self.pixel_input.value[0]),
                                    round(self.pixel_input.value[1])))())
        with ctx.images:
            self.order_panel = self.track(gui.add_image(np.zeros((8, 8, 3), np.uint8),
                                                        label="Efros–Leung fill order",
                                                        visible=False))
            self.window_image = self.track(gui.add_image(np.zeros((8, 8, 3), np.uint8),
                                                         label="window when filled",
                                                         visible=False))
            self.match_image = self.track(gui.add_image(np.zeros((8, 8, 3), np.uint8),
                                                        label="candidates in the sample",
                                                        visible=False))

    # --- public: what a click or a test does ----------------------------------------------------------
    def show_growth(self, upto: int) -> np.ndarray:
        """Show the texture and the fill order after ``upto`` pixels; returns the frame."""
        texture, trace, _ = self._require()
        upto = int(np.clip(upto, 0, trace.fill_order.size))
        frame = growth_frame(texture, trace, upto)
        self.order_panel.image = _upscaled(fill_order_image(trace, upto))[0]
        self._output_plane(frame)
        return frame

    def pick_pixel(self, row: int, col: int) -> PixelMatches:
        """Explain output pixel ``(row, col)``: draw its window, its candidates and the copied window."""
        texture, trace, sample = self._require()
        matches = efros_leung_pixel_matches(sample, texture, trace, row, col)
        self.matches, self.pixel = matches, (row, col)
        self.pixel_input.value = (float(row), float(col))
        self._draw_matches()
        return matches

    def click_output(self, ray_origin: Any, ray_direction: Any) -> PixelMatches:
        """A click on the texture plane: the pixel it hits, explained."""
        if self.output_plane is None:
            raise MissingInput("efros_leung", "there is no Efros–Leung texture to click yet")
        return self.pick_pixel(*plane_pixel(self.output_plane, ray_origin, ray_direction))

    def scene_nodes(self) -> list[str]:
        return sorted(self.nodes.handles)

    # --- viewer hooks ----------------------------------------------------------------------------------
    def update(self, state: Mapping[str, Any]) -> None:
        state = self.ctx.values(GROWTH_READS, state)
        texture, trace, sample = state.get("efros_leung"), state.get("efros_leung_trace"), state.get("sample")
        if not isinstance(texture, Image) or not isinstance(trace, EfrosLeungTrace) or not isinstance(sample,
                                                                                                      Image):
            if self.trace is not None:
                self._forget()
            return
        if texture is self.texture and trace is self.trace and sample is self.sample:
            return
        self.texture, self.trace, self.sample = texture, trace, sample
        self.matches = self.pixel = None
        for name in ("window", "candidates", "chosen"):
            self.nodes.drop(name)
        total = trace.fill_order.size
        self.syncing = True
        try:
            self.grown.max = total
            self.grown.value = total
        finally:
            self.syncing = False
        self.grown.disabled = False
        self.info.content = (f"{texture.width} x {texture.height} grown in {trace.layers} onion layers from "
                             f"a {sample.width} x {sample.height} sample (window {trace.window}, epsilon "
                             f"{trace.epsilon:g}). Click a pixel of the texture in the scene, or type it, to "
                             "see why it got its value.")
        self.order_panel.visible = True
        self._place_planes()
        self.show_growth(total)
        self._sample_plane()

    def close(self) -> None:
        self.nodes.clear()
        super().close()

    def legend(self) -> list[LegendEntry]:
        if self.output_plane is None:
            return []
        marks = [Swatch(UNKNOWN_COLOR, "pixels not grown yet (slider 'grown pixels')")]
        if self.matches is not None:
            marks += [Swatch(WINDOW_COLOR, "the clicked pixel's window"),
                      Swatch(CANDIDATE_COLOR, "the sample's windows within (1 + epsilon) of the best"),
                      Swatch(CHOSEN_COLOR, "the window it copied")]
        return [LegendEntry("efros_leung plane", "picture", 1, tuple(marks),
                            "the Efros–Leung texture as it grew, labelled in the scene; click a pixel"),
                LegendEntry("sample plane", "picture", 1, (), "the sample it grew from, beside it")]

    # --- drawing ---------------------------------------------------------------------------------------
    def _require(self) -> tuple[Image, EfrosLeungTrace, Image]:
        """The texture, its trace and the sample shown; :class:`MissingInput` before there are any."""
        if self.texture is None or self.trace is None or self.sample is None:
            raise MissingInput("efros_leung", "run step 'synthesize_efros_leung' first")
        return self.texture, self.trace, self.sample

    def _planes(self) -> tuple[Plane, Plane]:
        """Where the texture and the sample are drawn (placed when a texture is shown)."""
        if self.output_plane is None or self.sample_plane is None:
            raise MissingInput("efros_leung", "run step 'synthesize_efros_leung' first")
        return self.output_plane, self.sample_plane

    def _forget(self) -> None:
        self.texture = self.trace = self.sample = self.matches = self.pixel = None
        self.output_plane = self.sample_plane = None
        self.nodes.clear()
        self.grown.disabled = True
        for panel in (self.order_panel, self.window_image, self.match_image):
            panel.visible = False
        self.info.content = "Run **synthesize_efros_leung** to watch the texture grow."

    def _place_planes(self) -> None:
        texture, _, sample = self._require()
        # one scale for both (a window is as big on each), the larger of them PLANE_SIDE: the row's height
        scale = PLANE_SIDE / max(texture.width, texture.height, sample.width, sample.height)
        gap = 0.15 * PLANE_SIDE
        width = texture.width * scale + gap + sample.width * scale
        left = -width / 2
        self.output_plane = Plane((left + texture.width * scale / 2, GROWTH_ROW_Y, 0.0), texture.width,
                                  texture.height, scale)
        self.sample_plane = Plane((left + width - sample.width * scale / 2, GROWTH_ROW_Y, 0.0), sample.width,
                                  sample.height, scale)
        self._label("texture_label", self.output_plane, "efros_leung (click a pixel)")
        self._label("sample_label", self.sample_plane, "sample")

    def _label(self, name: str, plane: Plane, text: str) -> None:
        above = label_position(plane)
        self.nodes.put(name, lambda: self.ctx.scene.add_label(self.ctx.node("efros_leung", name), text,
                                                              position=above, anchor="bottom-center"))

    def _image_node(self, name: str, plane: Plane, rgb: np.ndarray, *, clickable: bool) -> None:
        handle = self.nodes.handles.get(name)
        if handle is not None:
            handle.image = rgb
            return
        handle = self.nodes.put(name, lambda: self.ctx.scene.add_image(
            self.ctx.node("efros_leung", name), rgb, plane.width * plane.scale, plane.height * plane.scale,
            format="png", position=plane.position, cast_shadow=False, receive_shadow=False))
        if clickable:
            handle.on_click(lambda event: self.ctx.guarded(
                lambda: self.click_output(event.ray_origin, event.ray_direction))())

    def _output_plane(self, rgb: np.ndarray) -> None:
        self._image_node("texture", self._planes()[0], rgb, clickable=True)

    def _sample_plane(self) -> None:
        self._image_node("sample", self._planes()[1], to_rgb8(self._require()[2].pixels), clickable=False)

    def _draw_matches(self) -> None:
        _, trace, sample = self._require()
        output_plane, sample_plane = self._planes()
        matches, pixel = self.matches, self.pixel
        if matches is None or pixel is None:
            return
        row, col = pixel
        half = trace.window // 2
        scene = self.ctx.scene
        outline = _rectangle(output_plane, row - half, col - half, trace.window, trace.window)
        self.nodes.put("window", lambda: scene.add_line_segments(
            self.ctx.node("efros_leung", "window"), outline, WINDOW_COLOR, thickness=3.0,
            thickness_units="screen"))
        centres = np.array([sample_plane.point(top + half, left + half) for top, left in matches.candidates])
        centres[:, 2] += 0.01
        self.nodes.put("candidates", lambda: scene.add_point_cloud(
            self.ctx.node("efros_leung", "candidates"), centres.astype(np.float32), CANDIDATE_COLOR,
            point_size=0.6 * sample_plane.scale, point_shape="circle"))
        top, left = (int(v) for v in matches.chosen)
        box = _rectangle(sample_plane, top, left, trace.window, trace.window)
        self.nodes.put("chosen", lambda: scene.add_line_segments(
            self.ctx.node("efros_leung", "chosen"), box, CHOSEN_COLOR, thickness=3.0,
            thickness_units="screen"))
        self.window_image.image = window_panel(matches)
        self.match_image.image = match_panel(sample, matches, trace.window)
        self.window_image.visible = self.match_image.visible = True
        seeded = matches.order < trace.seed_pixels
        seed = " (a seed pixel: copied with the seed patch, not matched)" if seeded else ""
        self.info.content = (f"Pixel ({row}, {col}) was filled {matches.order + 1}th{seed}: "
                             f"{int(matches.known.sum())} of {matches.known.size} window pixels known, "
                             f"{len(matches.candidates)} candidate window(s) within (1 + {trace.epsilon:g}) "
                             f"of the best distance {float(matches.distances.min()):.4g}; it copied the "
                             f"centre of the window at ({top}, {left}) of the sample (green).")


# ----------------------------------------------------------------------------------------------------
# Interaction 2: quilting's overlap error surfaces and cuts
# ----------------------------------------------------------------------------------------------------
class QuiltExplorer(Interaction):
    """A quilt block's overlap error surface and its minimum-error cut."""

    title = "Quilting: overlaps and cuts"

    def __init__(self, ctx: InteractionContext) -> None:
        super().__init__(ctx)
        gui = ctx.gui
        self.nodes = NamedHandles()
        self.layout: QuiltLayout | None = None
        self.quilting: Image | None = None
        self.block: int | None = None
        self.plane: Plane | None = None
        self.info = self.track(gui.add_markdown("Run **quilt** to see each block's overlap and cut."))
        self.slider = self.track(gui.add_slider("block", min=0, max=1, step=1, initial_value=0,
                                                disabled=True))
        self.syncing = False
        self.slider.on_update(lambda _: None if self.syncing else ctx.guarded(
            lambda: self.pick_block(int(self.slider.value)))())
        with ctx.images:
            self.panel = self.track(gui.add_image(np.zeros((8, 8, 3), np.uint8),
                                                  label="overlap error and cut",
                                                  visible=False))

    def pick_block(self, index: int) -> np.ndarray:
        """Show block ``index``: its error surface with the cut (returned, uint8) and its outline on the
        quilt."""
        plane = self.plane
        if self.layout is None or plane is None:
            raise MissingInput("quilting", "run step 'quilt' first")
        panel = overlap_panel(self.layout, index)
        self.block = index
        self.syncing = True
        try:
            self.slider.value = index
        finally:
            self.syncing = False
        self.panel.image = panel
        self.panel.visible = True
        y, x = (int(v) for v in self.layout.positions[index])
        sy, sx = (int(v) for v in self.layout.sources[index])
        errors = self.layout.errors[index]
        cut = cut_mask(self.layout, index)
        self.info.content = (f"Block {index} at ({y}, {x}) of the quilt, copied from ({sy}, {sx}) of the "
                             "sample. Overlap error: mean "
                             f"{errors[errors > 0].mean() if (errors > 0).any() else 0.0:.4g}; along the cut "
                             f"{errors[cut].sum():.4g} over {int(cut.sum())} pixels (red).")
        b = self.layout.block
        outline = _rectangle(plane, y, x, b, b)
        self.nodes.put("block", lambda: self.ctx.scene.add_line_segments(
            self.ctx.node("quilting", "block"), outline, CUT_COLOR, thickness=3.0, thickness_units="screen"))
        return panel

    def pick_pixel(self, row: int, col: int) -> int:
        """Show the block on top at output pixel ``(row, col)``; returns its index."""
        if self.layout is None:
            raise MissingInput("quilting", "run step 'quilt' first")
        index = block_at(self.layout, row, col)
        self.pick_block(index)
        return index

    def scene_nodes(self) -> list[str]:
        return sorted(self.nodes.handles)

    def update(self, state: Mapping[str, Any]) -> None:
        state = self.ctx.values(QUILT_READS, state)
        layout, quilting = state.get("quilting_layout"), state.get("quilting")
        if not isinstance(layout, QuiltLayout) or not isinstance(quilting, Image):
            if self.layout is not None:
                self.layout = self.quilting = self.block = self.plane = None
                self.nodes.clear()
                self.panel.visible = False
                self.slider.disabled = True
                self.info.content = "Run **quilt** to see each block's overlap and cut."
            return
        if layout is self.layout and quilting is self.quilting:
            return
        self.layout, self.quilting = layout, quilting
        scale = PLANE_SIDE / max(quilting.width, quilting.height)
        self.plane = plane = Plane((0.0, QUILT_ROW_Y, 0.0), quilting.width, quilting.height, scale)
        above = label_position(plane)
        self.nodes.put("label", lambda: self.ctx.scene.add_label(self.ctx.node("quilting", "label"),
                                                                 "quilting (click a block)", position=above,
                                                                 anchor="bottom-center"))
        handle = self.nodes.put("quilt", lambda: self.ctx.scene.add_image(
            self.ctx.node("quilting", "image"), to_rgb8(quilting.pixels), quilting.width * scale,
            quilting.height * scale, format="png", position=plane.position, cast_shadow=False,
            receive_shadow=False))
        handle.on_click(lambda event: self.ctx.guarded(
            lambda: self.pick_pixel(*plane_pixel(plane, event.ray_origin, event.ray_direction)))())
        self.syncing = True
        try:
            self.slider.max = max(1, len(layout.positions) - 1)
        finally:
            self.syncing = False
        self.slider.disabled = False
        self.pick_block(min(1, len(layout.positions) - 1))

    def legend(self) -> list[LegendEntry]:
        if self.plane is None:
            return []
        return [LegendEntry("quilting plane", "picture", 1, (Swatch(CUT_COLOR, "the block shown (slider "
                                                                              "'block'; or click one)"),),
                            "the quilt, labelled in the scene, above the Efros–Leung row")]

    def close(self) -> None:
        self.nodes.clear()
        super().close()


# ----------------------------------------------------------------------------------------------------
# Interaction 3: the texture on a 3D mesh
# ----------------------------------------------------------------------------------------------------
TEXTURES = ("quilting", "efros_leung", "parametric", "transferred", "sample")


def available_textures(state: Mapping[str, Any]) -> list[str]:
    """The textures of ``state`` that can be wrapped, in :data:`TEXTURES` order."""
    return [name for name in TEXTURES if isinstance(state.get(name), Image)]


def mesh_for(state: Mapping[str, Any], texture: str, shape: str, repeats: int, *, resolution: int = 64):
    """A ``trimesh.Trimesh`` of ``shape`` carrying texture ``texture`` of ``state`` through its UVs, with a
    matte material (glTF's default is fully metallic, which three.js draws almost black without an
    environment map)."""
    from trimesh.visual.material import PBRMaterial

    image = state.get(texture)
    if not isinstance(image, Image):
        raise MissingInput(texture, f"there is no {texture!r} texture yet: run the step that makes it")
    vertices, faces, uv = parametric_surface(shape, resolution)
    mesh = textured_trimesh(Mesh(vertices, faces), uv, image.pixels, repeats=repeats)
    mesh.visual.material = PBRMaterial(baseColorTexture=mesh.visual.material.image, metallicFactor=0.0,
                                       roughnessFactor=1.0)
    return mesh


#: The step whose result the mesh viewer defers to, and its controls the viewer mirrors.
WRAP_STEP = "wrap_on_mesh"
WRAP_CONTROLS = ("texture", "shape", "repeats")


class MeshViewer(Interaction):
    """A texture wrapped on a plane, cylinder or torus (image map through UVs): a preview until step
    ``wrap_on_mesh`` has run; then the scene shows the step's ``textured_mesh`` alone and the inputs show
    the controls it ran with (one picture, never two meshes)."""

    title = "Texture on a mesh"

    def __init__(self, ctx: InteractionContext) -> None:
        super().__init__(ctx)
        gui = ctx.gui
        self.nodes = NamedHandles()
        self.state: Mapping[str, Any] = {}
        self.shown: tuple[str, str, int, int] | None = None
        self.triangles = 0
        self.box: np.ndarray | None = None
        self.texture = self.track(gui.add_dropdown("texture", TEXTURES, initial_value="sample"))
        self.shape = self.track(gui.add_dropdown("shape", ("torus", "cylinder", "plane"),
                                                 initial_value="torus"))
        self.repeats = self.track(gui.add_slider("repeats", min=1, max=6, step=1, initial_value=2))
        self.info = self.track(gui.add_markdown(""))
        self.note = self.track(gui.add_markdown(""))
        self.syncing = False
        for handle in (self.texture, self.shape, self.repeats):
            handle.on_update(lambda _: None if self.syncing else ctx.guarded(self._from_inputs)())

    def wrapped(self) -> dict[str, Any] | None:
        """The controls step ``wrap_on_mesh`` made the session's ``textured_mesh`` with, or None while it has
        not run (or was reset)."""
        return self.ctx.session.ran_with.get(WRAP_STEP)

    def show(self, texture: str, shape: str, repeats: int = 2) -> Any:
        """Draw ``texture`` on ``shape`` in the scene (a preview, where the step's mesh goes); returns the
        trimesh drawn."""
        if shape not in ("plane", "cylinder", "torus"):
            raise InvalidValue("shape", f"must be plane, cylinder or torus, got {shape!r}")
        if self.wrapped() is not None:
            raise InvalidValue(WRAP_STEP, "the scene shows step wrap_on_mesh's textured_mesh: change the "
                                          "step's texture, shape or repeats and run it (or reset it to "
                                          "preview)")
        mesh = mesh_for(self.state, texture, shape, int(repeats))
        image = self.state[texture]
        self.nodes.put("mesh", lambda: self.ctx.scene.add_mesh_trimesh(self.ctx.node("mesh", "surface"),
                                                                       mesh))
        self.shown = (texture, shape, int(repeats), id(image))
        self.triangles = len(mesh.faces)
        self.box = np.asarray(mesh.bounds, dtype=np.float64)
        self.info.content = (f"{texture} ({image.width} x {image.height}) on a {shape}, repeated "
                             f"{int(repeats)}x.")
        self.note.content = ("A preview drawn by this panel (the texture as an image map). Run step "
                             "**wrap_on_mesh** to make the session's `textured_mesh`: it then takes the "
                             "preview's place.")
        self._set_inputs(texture, shape, int(repeats), disabled=False)
        return mesh

    def _set_inputs(self, texture: str, shape: str, repeats: int, *, disabled: bool) -> None:
        self.syncing = True
        try:
            self.texture.value, self.shape.value, self.repeats.value = texture, shape, int(repeats)
            for handle in (self.texture, self.shape, self.repeats):
                handle.disabled = disabled
        finally:
            self.syncing = False

    def scene_nodes(self) -> list[str]:
        return sorted(self.nodes.handles)

    def update(self, state: Mapping[str, Any]) -> None:
        self.state = state = self.ctx.values(TEXTURES, state)
        wrapped = self.wrapped()
        if wrapped is not None:  # the step's mesh is the picture: mirror its controls, draw nothing
            self.nodes.clear()
            self.shown = None
            texture, shape, repeats = (str(wrapped[k]) for k in WRAP_CONTROLS)
            self.repeats.max = max(int(self.repeats.max), int(repeats))
            self._set_inputs(texture, shape, int(repeats), disabled=True)
            self.info.content = (f"The scene shows `textured_mesh` of step wrap_on_mesh: {texture} on a "
                                 f"{shape}, repeated {int(repeats)}x (vertex colours).")
            self.note.content = "Change the texture, shape or repeats in the step's own controls and run it."
            return
        available = available_textures(state)
        if not available:
            self.nodes.clear()
            self.shown = None
            return
        wanted = self.texture.value if self.texture.value in available else available[0]
        if self.shown is not None and self.shown[0] not in available:
            self.shown = None
        # prefer a synthesized texture as soon as one exists
        if self.shown is None or (self.shown[0] == "sample" and available[0] != "sample"):
            wanted = available[0]
        key = (wanted, str(self.shape.value), int(self.repeats.value), id(state[wanted]))
        if key != self.shown:
            self.show(wanted, str(self.shape.value), int(self.repeats.value))

    def bounds(self) -> np.ndarray | None:
        """The preview's box (a GLB node tells only its origin), None when none is drawn."""
        return self.box if "mesh" in self.nodes.handles else None

    def legend(self) -> list[LegendEntry]:
        if self.shown is None:
            return []
        texture, shape, repeats, _ = self.shown
        return [LegendEntry("preview mesh", "triangles", self.triangles, (),
                            f"{texture} on a {shape} ({repeats}x), image-mapped: a preview until "
                            "wrap_on_mesh runs")]

    def _from_inputs(self) -> None:
        if self.state:
            self.show(str(self.texture.value), str(self.shape.value), int(self.repeats.value))

    def close(self) -> None:
        self.nodes.clear()
        super().close()


INTERACTIONS = [GrowthExplorer, QuiltExplorer, MeshViewer]

__all__ = ["GROWTH_READS", "GROWTH_ROW_Y", "INTERACTIONS", "QUILT_READS", "QUILT_ROW_Y", "TEXTURES",
           "WRAP_STEP", "GrowthExplorer", "MeshViewer", "Plane", "QuiltExplorer", "available_textures",
           "block_at", "cut_mask", "fill_order_image", "growth_frame", "label_position", "match_panel",
           "mesh_for", "overlap_panel", "plane_pixel", "window_panel"]
