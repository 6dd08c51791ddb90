"""One renderer per value type of :mod:`lab.core.values` (DESIGN.md section 4, "values that are drawn have a
type").

A renderer draws one named state value into a :class:`Canvas`: a viser scene (3D values:
point clouds, camera frustums carrying their image, 3D segments, meshes, Gaussian splats) and,
when the canvas has one, a GUI container (2D values: images, image sets with a view slider,
plots). 2D points and segments are not drawn on their own: they are overlays, composited with
OpenCV into the views of the image set they name (``Points2D.image`` / ``Segments2D.image``), in
the image panel and on the frustums of the cameras that carry that image set.

:class:`StateDrawer` keeps a canvas in step with a session's state: it draws new values, redraws
changed ones (values are immutable, so a changed value is a new object) and removes the ones
that were invalidated. The same drawer serves a browser tab, and :func:`lab.viewer.export_scene_html`
(a headless server's scene, saved as one HTML file).

A changed value's drawing is changed in place where it can be (:meth:`Renderer.redraw`): a GUI picture or
chart keeps its element for as long as its value is drawn, and is removed only when the value is gone (a
curve that turns from a line chart into bars, or back, hides one element and shows the other). viser's
browser client applies a frame's GUI updates after the frame's adds and removes, and viser's ``add_image``
is an add followed by an update (the picture travels as an update): an element removed and added again for
a new value, when two refreshes reach a slow page within one frame, gets its update after its removal, and
the browser logs "Tried to update non-existent component" (issue 16). Scene nodes are replaced under their
name (the client orders scene updates against removals itself).

Pure helpers (no viser): :func:`to_rgb8`, :func:`overlay_view` and :func:`curve_image` return
``uint8`` arrays, so reports and tests can use them directly.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from lab.core.values import (Cameras, Curve, GaussianSplats, Image, ImageSet, Mesh, PointCloud, Points2D,
                             Segments2D, Segments3D)
from lab.viewer.plots import chart_axes, set_uplot

#: Root of every node this module adds to a scene.
SCENE_ROOT = "/lab"

#: A camera frustum's size (viser's ``scale``) as a share of the scene's extent (:func:`scene_extent`).
FRUSTUM_SHARE = 0.06
#: Largest side, in pixels, of an image sent to the GUI panel / carried on a frustum.
PANEL_MAX_SIDE = 640
FRUSTUM_MAX_SIDE = 320
#: Smaller images are enlarged (nearest neighbour, so pixels stay visible) to this side in the panel.
PANEL_MIN_SIDE = 400

#: Default overlay colours (RGB), cycled per overlay: points in cool colours, segments in warm ones.
POINT_COLORS = ((40, 220, 60), (0, 200, 255), (255, 230, 0), (200, 120, 255))
SEGMENT_COLORS = ((255, 40, 40), (255, 0, 200), (255, 150, 0), (255, 255, 255))
DEFAULT_CAMERA_COLOR = (40, 90, 200)
DEFAULT_POINT_COLOR = (60, 60, 60)
DEFAULT_MESH_COLOR = (200, 200, 210)
#: How opaque a mesh without colours of its own is drawn: see-through, so the points on and in it show
#: (diffusion's target shape with the samples drawn on it).
PLAIN_MESH_OPACITY = 0.3
#: Colours of the point clouds that bring none, by the rank of their name among such clouds of the state
#: (:func:`default_cloud_colors`): the first grey, the others distinct from it and from each other.
CLOUD_COLORS = (DEFAULT_POINT_COLOR, (0, 150, 136), (200, 40, 160), (120, 80, 200), (150, 110, 40),
                (200, 170, 0))
BAR_COLOR = (90, 140, 210)
WORST_BAR_COLOR = (220, 40, 40)


# --- pure 2D helpers ----------------------------------------------------------------------------
def to_rgb8(pixels: np.ndarray) -> np.ndarray:
    """``(H, W)`` or ``(H, W, 3)`` float in [0, 1] (or uint8) -> ``(H, W, 3)`` uint8 RGB."""
    pixels = np.asarray(pixels)
    if pixels.dtype != np.uint8:
        pixels = (np.clip(pixels, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if pixels.ndim == 2:
        pixels = np.repeat(pixels[:, :, None], 3, axis=2)
    return np.ascontiguousarray(pixels)


def _color8(colors: np.ndarray | None, index: int, default: tuple[int, int, int]) -> tuple[int, int, int]:
    if colors is None:
        return default
    r, g, b = (np.clip(colors[index], 0.0, 1.0) * 255.0 + 0.5).astype(int)
    return int(r), int(g), int(b)


def overlays_of(state: Mapping[str, Any], image_name: str) -> list[tuple[str, Points2D | Segments2D]]:
    """The 2D points and segments in ``state`` drawn on the image (set) ``image_name``, by name."""
    return [(name, value) for name, value in sorted(state.items())
            if isinstance(value, (Points2D, Segments2D)) and value.image == image_name]


def _on_view(overlay: Points2D | Segments2D, view: int | None) -> np.ndarray:
    """Mask of the overlay's items on ``view`` (all items when either is None)."""
    n = len(overlay)
    if view is None or overlay.view is None:
        return np.ones(n, dtype=bool)
    return overlay.view == view


def overlay_view(image: Image, overlays: Iterable[Points2D | Segments2D] = (), *, view: int | None = None,
                 max_side: int | None = PANEL_MAX_SIDE, min_side: int | None = None) -> np.ndarray:
    """One view with its 2D overlays drawn in, as ``(H', W', 3)`` uint8 RGB.

    The image is first shrunk so its longer side is at most ``max_side`` (None: no limit), or
    enlarged with nearest-neighbour sampling to ``min_side`` (None: never), then the overlays are
    drawn at that size with sub-pixel accuracy (``cv2.circle`` / ``cv2.line``
    with a fixed-point shift), so thin residuals stay visible. Points are open circles in their
    ``colors`` (default: green, cyan, ... per overlay), segments are lines (default red, ...)
    with a dot at their start; only the items whose ``view`` equals ``view`` are drawn (all of
    them when either is None). Pixel (0, 0) is the centre of the top-left pixel (DESIGN.md 3).
    """
    rgb = to_rgb8(image.pixels)
    height, width = rgb.shape[:2]
    scale = 1.0 if max_side is None else min(1.0, max_side / max(height, width))
    if min_side is not None and max(height, width) < min_side:
        scale = float(max(1, min_side // max(height, width)))  # an integer factor: square pixels
    if scale != 1.0:
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST)
        scale_x, scale_y = size[0] / width, size[1] / height
    else:
        scale_x = scale_y = 1.0
    rgb = np.ascontiguousarray(rgb)
    shift = 4
    one = 1 << shift

    def fixed(xy: np.ndarray) -> np.ndarray:  # pixel centres stay pixel centres after scaling
        out = np.empty_like(xy)
        out[:, 0] = (xy[:, 0] + 0.5) * scale_x - 0.5
        out[:, 1] = (xy[:, 1] + 0.5) * scale_y - 0.5
        return np.round(out * one).astype(np.int64)

    radius = max(2.0, min(rgb.shape[:2]) / 120.0)
    n_points = n_segments = 0
    overlays = list(overlays)
    in_order: list[Points2D | Segments2D] = [*(o for o in overlays if isinstance(o, Points2D)),
                                             *(o for o in overlays if isinstance(o, Segments2D))]
    for overlay in in_order:  # segments (residuals) on top of points
        keep = _on_view(overlay, view)
        if isinstance(overlay, Points2D):
            default = POINT_COLORS[n_points % len(POINT_COLORS)]
            n_points += 1
            for i, (x, y) in zip(np.flatnonzero(keep), fixed(overlay.xy[keep]), strict=True):
                cv2.circle(rgb, (int(x), int(y)), round(radius * one),
                           _color8(overlay.colors, int(i), default),
                           1, cv2.LINE_AA, shift)
        else:
            default = SEGMENT_COLORS[n_segments % len(SEGMENT_COLORS)]
            n_segments += 1
            index = np.flatnonzero(keep)
            for i, (x0, y0), (x1, y1) in zip(index, fixed(overlay.start[keep]), fixed(overlay.end[keep]),
                                             strict=True):
                color = _color8(overlay.colors, int(i), default)
                cv2.line(rgb, (int(x0), int(y0)), (int(x1), int(y1)), color, 1, cv2.LINE_AA, shift)
                cv2.circle(rgb, (int(x0), int(y0)), one, color, -1, cv2.LINE_AA, shift)
    return rgb


def curve_image(curve: Curve, *, width: int = 480, height: int = 260) -> np.ndarray:
    """Draw a :class:`Curve` as a ``(height, width, 3)`` uint8 RGB chart with OpenCV.

    ``kind="bar"``: one bar per x (grouped when there are several series), labelled with
    ``categories``; the largest bar of the first series (the worst view, the worst image) is red
    and labelled with its value, the others blue, and a dashed line marks the mean. ``"line"`` and
    ``"scatter"`` draw each series over x. The viewer shows line plots with uPlot (interactive)
    and bar charts with this function; reports can use it for any curve.
    """
    img = np.full((height, width, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    left, right, top, bottom = 52, 10, 22 if curve.title else 10, 34
    plot_w, plot_h = width - left - right, height - top - bottom
    if curve.title:
        cv2.putText(img, curve.title[:70], (left, 15), font, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    y = curve.y
    n = len(curve.x)
    finite = y[np.isfinite(y)]
    y_min = 0.0 if curve.kind == "bar" else (float(finite.min()) if finite.size else 0.0)
    y_max = float(finite.max()) if finite.size else 1.0
    y_min = min(y_min, 0.0) if curve.kind == "bar" else y_min
    if y_max <= y_min:
        y_max = y_min + 1.0
    span = y_max - y_min
    y_max += 0.08 * span

    def py(value: float) -> int:
        return round(top + plot_h * (1.0 - (value - y_min) / (y_max - y_min)))

    # axes and a few horizontal grid lines with labels
    cv2.line(img, (left, top), (left, top + plot_h), (0, 0, 0), 1)
    cv2.line(img, (left, top + plot_h), (left + plot_w, top + plot_h), (0, 0, 0), 1)
    for k in range(5):
        value = y_min + (y_max - y_min) * k / 4
        yy = py(value)
        cv2.line(img, (left + 1, yy), (left + plot_w, yy), (225, 225, 225), 1)
        cv2.putText(img, f"{value:.3g}", (2, yy + 4), font, 0.33, (60, 60, 60), 1, cv2.LINE_AA)
    if curve.ylabel:
        cv2.putText(img, curve.ylabel[:20], (left + 4, top + 12), font, 0.35, (90, 90, 90), 1, cv2.LINE_AA)
    if n == 0:
        return img
    if curve.kind == "bar":
        series = len(y)
        slot = plot_w / n
        bar_w = max(1.0, 0.8 * slot / series)
        worst = int(np.nanargmax(y[0])) if np.isfinite(y[0]).any() else -1
        for s in range(series):
            for i in range(n):
                if not np.isfinite(y[s, i]):
                    continue
                x0 = left + slot * i + 0.1 * slot + bar_w * s
                color: tuple[int, ...] = WORST_BAR_COLOR if (s == 0 and i == worst) else BAR_COLOR
                if s > 0:
                    color = tuple(int(c * 0.6 + 255 * 0.4) for c in BAR_COLOR)
                cv2.rectangle(img, (round(x0), py(max(y[s, i], y_min))),
                              (round(x0 + bar_w) - 1, py(y_min)), color, -1)
        mean = float(np.nanmean(y[0]))
        for xx in range(left, left + plot_w, 8):
            cv2.line(img, (xx, py(mean)), (min(xx + 4, left + plot_w), py(mean)), (120, 120, 120), 1)
        labels = list(curve.categories) if len(curve.categories) == n else [f"{v:g}" for v in curve.x]
        ticks = short_labels(labels)
        step = max(1, math.ceil(n / max(1, plot_w // 30)))
        for i in range(0, n, step):
            text = ticks[i]
            size = cv2.getTextSize(text, font, 0.35, 1)[0][0]
            cx = int(left + slot * (i + 0.5) - size / 2)
            cv2.putText(img, text, (cx, top + plot_h + 13), font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
        if worst >= 0:
            text = f"worst: {labels[worst]} = {y[0, worst]:.3g}"
            cv2.putText(img, text[:60], (left, height - 6), font, 0.42, WORST_BAR_COLOR, 1, cv2.LINE_AA)
        return img
    x = curve.x
    x_min, x_max = float(x.min()), float(x.max())
    if x_max <= x_min:
        x_max = x_min + 1.0

    def px(value: float) -> int:
        return round(left + plot_w * (value - x_min) / (x_max - x_min))

    palette = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189))
    for s in range(len(y)):
        color = palette[s % len(palette)]
        pts = np.array([(px(a), py(b)) for a, b in zip(x, y[s], strict=True) if np.isfinite(b)], np.int32)
        if curve.kind == "line" and len(pts) > 1:
            cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, color, 2, cv2.LINE_AA)
        else:
            for p in pts:
                cv2.circle(img, (int(p[0]), int(p[1])), 3, color, -1, cv2.LINE_AA)
    for value in (x_min, x_max):
        cv2.putText(img, f"{value:.3g}", (px(value) - 8, top + plot_h + 12), font, 0.33, (60, 60, 60), 1,
                    cv2.LINE_AA)
    if curve.xlabel:
        cv2.putText(img, curve.xlabel[:40], (left + plot_w // 2 - 20, height - 6), font, 0.35, (60, 60, 60),
                    1,
                    cv2.LINE_AA)
    return img


def short_labels(labels: list[str], width: int = 6) -> list[str]:
    """Tick labels for bars: the common prefix dropped ("view 03" -> "03"), at most ``width`` chars."""
    prefix = labels[0] if len(labels) > 1 else ""
    for label in labels[1:]:  # the longest common prefix, character by character
        while not label.startswith(prefix):
            prefix = prefix[:-1]
    out = [label[len(prefix):] or label for label in labels]
    return [text if len(text) <= width else text[:width - 1] + "~" for text in out]


# --- geometry helpers ---------------------------------------------------------------------------
def wxyz_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a 3x3 rotation (what ``viser.transforms.SO3.from_matrix`` gives)."""
    import viser.transforms as vtf

    return np.asarray(vtf.SO3.from_matrix(rotation).wxyz, dtype=np.float64)


def points_of(value: Any) -> np.ndarray | None:
    """3D points that bound a drawn value (for framing the camera and sizing glyphs), ``(N, 3)``."""
    if isinstance(value, PointCloud):
        return value.xyz
    if isinstance(value, Cameras):
        return value.centers
    if isinstance(value, Segments3D):
        return np.concatenate([value.start, value.end])
    if isinstance(value, Mesh):
        return value.vertices
    if isinstance(value, GaussianSplats):
        return value.centers
    return None


def default_cloud_colors(state: Mapping[str, Any]) -> dict[str, tuple[int, int, int]]:
    """The colour each point cloud of ``state`` without colours of its own is drawn in: :data:`CLOUD_COLORS`
    in the order of their names (so a module's training points, noised points and samples differ, and the
    legend says which is which)."""
    names = sorted(n for n, v in state.items() if isinstance(v, PointCloud) and v.colors is None)
    return {name: CLOUD_COLORS[k % len(CLOUD_COLORS)] for k, name in enumerate(names)}


def scene_bounds(values: Iterable[Any]) -> np.ndarray | None:
    """``(2, 3)`` min and max corner of every 3D value (robust to a few far outliers), or None."""
    chunks = [p for p in (points_of(v) for v in values) if p is not None and len(p)]
    if not chunks:
        return None
    points = np.concatenate(chunks)
    points = points[np.all(np.isfinite(points), axis=1)]
    if not len(points):
        return None
    if len(points) > 100:
        lo, hi = np.percentile(points, [1, 99], axis=0)
    else:
        lo, hi = points.min(axis=0), points.max(axis=0)
    return np.stack([lo, hi])


#: How far below the cameras' mean optical axis the viewer's camera looks (y is down): a slight look down.
LOOK_DOWN = 0.35


def viewpoint(values: Iterable[Any]) -> tuple[np.ndarray, np.ndarray] | None:
    """Where to put the user's camera to see the 3D values: ``(position, look_at)``, or None.

    With cameras in the scene, the eye looks along their mean viewing direction tilted a little down
    (:data:`LOOK_DOWN`), from behind and above their content (seeing what they see, e.g. the board they
    surround, whatever else is drawn beside it); otherwise it looks at the content's centre from the front
    and above (world up is -y, OpenCV's convention). :func:`lab.viewer.camera.fit_camera` then moves the eye
    along that direction so the content fills the browser's canvas.
    """
    values = list(values)
    bounds = scene_bounds(values)
    if bounds is None:
        return None
    center = bounds.mean(axis=0)
    size = max(float(np.linalg.norm(bounds[1] - bounds[0])), 1e-3)
    direction = np.array([-0.35, 0.6, 1.1])
    cameras = [v for v in values if isinstance(v, Cameras) and len(v)]
    if cameras:
        forward = np.concatenate([c.R[:, 2, :] for c in cameras]).mean(axis=0)  # optical axes in the world
        if np.linalg.norm(forward) > 1e-6:
            direction = forward / np.linalg.norm(forward) + np.array([0.0, LOOK_DOWN, 0.0])
    direction = direction / np.linalg.norm(direction)
    return center - 1.3 * size * direction, center


def scene_extent(values: Iterable[Any]) -> float:
    """Diagonal of :func:`scene_bounds` (1.0 when there is nothing 3D), rounded to a power of 2^(1/2).

    Glyph sizes (frustums, points) are fractions of it; the rounding keeps them stable when the
    scene changes a little, so values are not redrawn for nothing.
    """
    bounds = scene_bounds(values)
    if bounds is None:
        return 1.0
    diagonal = float(np.linalg.norm(bounds[1] - bounds[0]))
    if not np.isfinite(diagonal) or diagonal <= 0:
        return 1.0
    return float(2.0 ** (round(2 * math.log2(diagonal)) / 2))


# --- the canvas and drawn values ----------------------------------------------------------------
@dataclass
class Canvas:
    """Where values are drawn: a viser ``scene`` (a client's or a server's) and optionally GUI.

    ``gui`` is a viser GUI API and ``images``/``plots`` the containers (folder, tab or panel
    handles, used as context managers) that image and plot elements go into; with ``gui`` None
    (a headless export) only the 3D scene is drawn. ``on_view_selected(image_name, view)`` is
    called when the user clicks a frustum (the viewer then shows that view in the image panel).
    """

    scene: Any
    gui: Any = None
    images: Any = None
    plots: Any = None
    on_view_selected: Callable[[str, int], None] | None = None
    #: ``on_pixel_clicked(image_name, view, pixel)``: a click on a frustum's picture, at that pixel of the
    #: view; True when something (an interaction) took it, else the click selects the view.
    on_pixel_clicked: Callable[[str, int, np.ndarray], bool] | None = None
    extent: float = 1.0
    #: Which view each image set shows in the panel (the view sliders write it).
    views: dict[str, int] = field(default_factory=dict)


@dataclass
class Drawn:
    """What a renderer put on a canvas for one value: handles to remove, and its fingerprint."""

    fingerprint: tuple
    handles: list[Any] = field(default_factory=list)
    #: Redraw just the picture of the current view (ImageSet); None for other types.
    refresh_view: Callable[[], None] | None = None
    #: Named widgets inside a drawn container (an image set's ``slider`` and ``image``).
    parts: dict[str, Any] = field(default_factory=dict)
    #: The renderer that drew it (set by :class:`StateDrawer`: only it can :meth:`Renderer.redraw` it).
    renderer: Renderer | None = None

    #: When it was drawn (``time.monotonic()``): a GUI picture removed within :data:`GUI_SETTLE_S` of its
    #: drawing is hidden at once and removed later (see :meth:`remove`).
    drawn_at: float = field(default_factory=time.monotonic)

    def remove(self) -> None:
        """Remove the handles; a GUI picture or folder drawn under :data:`GUI_SETTLE_S` ago is hidden now
        and removed once that time has passed: viser's client applies a frame's GUI updates after the
        frame's adds and removes, so a picture added (an add, then its picture as an update) and removed
        within one frame of a slow page gets its update after its removal ("Tried to update non-existent
        component", issue 16: splatting's render steps end within milliseconds of each other)."""
        young = time.monotonic() - self.drawn_at < GUI_SETTLE_S
        later = [h for h in self.handles if young and _is_gui_picture_or_folder(h)]
        for handle in reversed(self.handles):
            with contextlib.suppress(Exception):  # already gone with its parent (a removed folder / node)
                if handle in later:
                    handle.visible = False
                else:
                    handle.remove()
        self.handles.clear()
        if later:
            timer = threading.Timer(GUI_SETTLE_S, _remove_all, args=(later,))
            timer.daemon = True
            timer.start()


#: Seconds a GUI picture or folder lives at least before it is removed (hidden meanwhile): more than a
#: frame of a slow page (a software-rendered browser draws a few frames a second).
GUI_SETTLE_S = 1.0


def _is_gui_picture_or_folder(handle: Any) -> bool:
    kind = type(handle)
    return kind.__module__.startswith("viser") and kind.__name__ in ("GuiImageHandle", "GuiFolderHandle")


def _remove_all(handles: list[Any]) -> None:
    for handle in reversed(handles):
        with contextlib.suppress(Exception):  # gone already (the client left, its parent removed)
            handle.remove()


def _node(name: str) -> str:
    return f"{SCENE_ROOT}/{name}"


def _gui_context(container: Any):
    """A container handle used as a context manager, or a no-op context when there is none."""
    import contextlib

    return container if container is not None else contextlib.nullcontext()


class Renderer:
    """Draws one value type. Subclasses set ``value_type`` and implement :meth:`draw`; those whose drawing can
    change in place implement :meth:`redraw` too."""

    value_type: type = object
    #: True for values drawn in the 3D scene, False for GUI-only ones (skipped without a GUI).
    in_scene: bool = True

    def fingerprint(self, name: str, value: Any, state: Mapping[str, Any], canvas: Canvas) -> tuple:
        """Changes when the drawing must be redone (values are immutable: identity is enough)."""
        return (id(value), canvas.extent)

    def draw(self, canvas: Canvas, name: str, value: Any, state: Mapping[str, Any], order: float) -> Drawn:
        raise NotImplementedError

    def redraw(self, canvas: Canvas, name: str, value: Any, state: Mapping[str, Any], order: float,
               drawn: Drawn) -> bool:
        """Bring ``drawn`` (this renderer's drawing of an earlier value of ``name``) up to date with ``value``
        by changing its handles in place; False when it cannot, and :class:`StateDrawer` then removes it and
        draws the value anew. The default: it cannot (a scene node is replaced under its own name, which
        viser's client handles in order). The GUI renderers always can: a GUI picture or chart keeps its
        element for as long as its value is drawn (the module docstring says why)."""
        return False


class PointCloudRenderer(Renderer):
    """:class:`PointCloud` -> ``scene.add_point_cloud`` (its colours, else :func:`default_cloud_colors`)."""

    value_type = PointCloud

    def fingerprint(self, name, value: PointCloud, state, canvas) -> tuple:
        return (id(value), canvas.extent, default_cloud_colors(state).get(name))

    def draw(self, canvas, name, value: PointCloud, state, order) -> Drawn:
        colors = default_cloud_colors(state)[name] if value.colors is None else \
            (np.clip(value.colors, 0, 1) * 255).astype(np.uint8)
        handle = canvas.scene.add_point_cloud(_node(name), points=value.xyz.astype(np.float32), colors=colors,
                                              point_size=0.006 * canvas.extent, point_shape="circle",
                                              precision="float32")
        return Drawn(self.fingerprint(name, value, state, canvas), [handle])


class CamerasRenderer(Renderer):
    """:class:`Cameras` -> one ``scene.add_camera_frustum`` per camera, carrying its view.

    Camera ``i`` sits at ``C = -R^T t`` with orientation ``R^T`` (camera to world; viser frustums
    use OpenCV's axes), vertical field of view ``2 atan(h / 2 fy)``; it carries view
    ``views[i]`` (or ``i``) of the image set named by ``Cameras.image`` with that set's overlays
    drawn in, and is tinted by ``colors[i]``. Clicking a frustum shows its view in the image panel.
    """

    value_type = Cameras

    def fingerprint(self, name, value: Cameras, state, canvas) -> tuple:
        images = state.get(value.image) if value.image else None
        return (id(value), canvas.extent, id(images),
                tuple(id(o) for _, o in overlays_of(state, value.image)))

    def draw(self, canvas, name, value: Cameras, state, order) -> Drawn:
        images = state.get(value.image) if value.image else None
        if isinstance(images, Image):
            images = ImageSet((images,))
        if not isinstance(images, ImageSet):
            images = None
        overlays = [o for _, o in overlays_of(state, value.image)] if images is not None else []
        drawn = Drawn(self.fingerprint(name, value, state, canvas))
        drawn.handles.append(canvas.scene.add_frame(_node(name), show_axes=False))
        views = value.views if value.views is not None else np.arange(len(value))
        scale = FRUSTUM_SHARE * canvas.extent
        for i in range(len(value)):
            view = int(views[i])
            picture = None
            if images is not None and 0 <= view < len(images):
                picture = overlay_view(images[view], overlays, view=view, max_side=FRUSTUM_MAX_SIDE)
            rotation_cw = value.R[i].T
            center = -rotation_cw @ value.t[i]
            fy = value.K[i, 1, 1]
            fov = 2.0 * math.atan2(value.height / 2.0, fy) if fy > 0 else math.radians(60)
            handle = canvas.scene.add_camera_frustum(
                f"{_node(name)}/camera_{i:03d}", fov=fov, aspect=value.width / value.height, scale=scale,
                thickness=2.0, thickness_units="screen",
                color=_color8(value.colors, i, DEFAULT_CAMERA_COLOR), image=picture, format="jpeg",
                jpeg_quality=85, wxyz=wxyz_from_matrix(rotation_cw), position=center)
            if canvas.on_view_selected is not None and value.image:
                def clicked(event: Any, image_name: str = value.image, view: int = view, index: int = i,
                            cameras: Cameras = value,
                            callback: Callable[[str, int], None] = canvas.on_view_selected,
                            on_pixel: Callable[[str, int, np.ndarray], bool] | None = canvas.on_pixel_clicked,
                            fov: float = fov) -> None:
                    pixel = frustum_click_pixel(cameras, index, fov=fov, scale=scale,
                                                ray_origin=getattr(event, "ray_origin", None),
                                                ray_direction=getattr(event, "ray_direction", None))
                    if on_pixel is not None and pixel is not None and on_pixel(image_name, view, pixel):
                        return
                    callback(image_name, view)

                handle.on_click(clicked)
            drawn.handles.append(handle)
        return drawn


def frustum_plane_depth(fov: float, aspect: float, scale: float) -> float:
    """The depth of a viser camera frustum's picture in the camera's frame: viser scales a frustum to a fixed
    volume, so the picture of ``add_camera_frustum(fov, aspect, scale)`` lies at
    ``z = scale / cbrt(tan(fov / 2)^2 aspect / 3)`` (viser's CameraFrustumVariants.tsx)."""
    half = math.tan(fov / 2.0)
    return scale / ((half * half * aspect / 3.0) ** (1.0 / 3.0))


def frustum_corners(cameras: Cameras, extent: float) -> np.ndarray:
    """``(4 N, 3)`` world corners of the pictures of the ``N`` frustums :class:`CamerasRenderer` draws in a
    scene of extent ``extent`` (:func:`frustum_plane_depth`; what framing the camera must keep in view)."""
    corners = []
    for i in range(len(cameras)):
        fy = cameras.K[i, 1, 1]
        fov = 2.0 * math.atan2(cameras.height / 2.0, fy) if fy > 0 else math.radians(60)
        aspect = cameras.width / cameras.height
        depth = frustum_plane_depth(fov, aspect, FRUSTUM_SHARE * extent)
        half_y = depth * math.tan(fov / 2.0)
        local = np.array([[sx * half_y * aspect, sy * half_y, depth] for sx in (-1, 1) for sy in (-1, 1)])
        corners.append((local - cameras.t[i]) @ cameras.R[i])  # camera -> world: X = R^T (X_c - t)
    return np.concatenate(corners) if corners else np.zeros((0, 3))


def frustum_click_pixel(cameras: Cameras, index: int, *, fov: float, scale: float, ray_origin: Any,
                        ray_direction: Any) -> np.ndarray | None:
    """The pixel ``(u, v)`` of the picture on camera ``index``'s frustum that a click's ray (world frame)
    meets, or None when it misses the picture. The picture spans the view uniformly (as the texture is
    drawn): ``u = (X / Z / (2 tan(fov / 2) aspect) + 1/2) width``, ``v`` alike with the height."""
    if ray_origin is None or ray_direction is None:
        return None
    R, t = cameras.R[index], cameras.t[index]
    origin = R @ np.asarray(ray_origin, dtype=np.float64) + t  # world -> camera: X_c = R X + t
    direction = R @ np.asarray(ray_direction, dtype=np.float64)
    aspect = cameras.width / cameras.height
    depth = frustum_plane_depth(fov, aspect, scale)
    if abs(direction[2]) < 1e-12:
        return None
    along = (depth - origin[2]) / direction[2]
    if along < 0:
        return None
    x, y, z = origin + along * direction
    half = math.tan(fov / 2.0)
    u = (x / z / (2.0 * half * aspect) + 0.5) * cameras.width
    v = (y / z / (2.0 * half) + 0.5) * cameras.height
    if not (0.0 <= u <= cameras.width and 0.0 <= v <= cameras.height):
        return None
    return np.array([u, v])


class Segments3DRenderer(Renderer):
    """:class:`Segments3D` -> ``scene.add_line_segments`` (colours per segment, else black)."""

    value_type = Segments3D

    def draw(self, canvas, name, value: Segments3D, state, order) -> Drawn:
        points = np.stack([value.start, value.end], axis=1).astype(np.float32)
        colors: np.ndarray | tuple[int, int, int]
        if value.colors is not None:
            colors = np.repeat((np.clip(value.colors, 0, 1) * 255).astype(np.uint8)[:, None, :], 2, axis=1)
        else:
            colors = (20, 20, 20)
        handle = canvas.scene.add_line_segments(_node(name), points=points, colors=colors, thickness=2.0,
                                                thickness_units="screen")
        return Drawn(self.fingerprint(name, value, state, canvas), [handle])


class MeshRenderer(Renderer):
    """:class:`Mesh` -> ``scene.add_mesh_trimesh`` with vertex colours, else ``add_mesh_simple``, light grey
    and see-through (:data:`PLAIN_MESH_OPACITY`: a shape with points on it); both sides are drawn (a
    calibration board is seen from behind its printed face's normal)."""

    value_type = Mesh

    def draw(self, canvas, name, value: Mesh, state, order) -> Drawn:
        if value.vertex_colors is not None:
            import trimesh

            # GLB materials are one-sided: add a back copy (own vertices, reversed winding, so
            # its normals point the other way) so a board is seen from the cameras' side too.
            n = len(value.vertices)
            vertices = np.concatenate([value.vertices, value.vertices])
            faces = np.concatenate([value.faces, value.faces[:, ::-1] + n])
            colors = (np.clip(value.vertex_colors, 0, 1) * 255).astype(np.uint8)
            rgba = np.concatenate([colors, np.full((n, 1), 255, np.uint8)], axis=1)
            mesh = trimesh.Trimesh(vertices, faces, vertex_colors=np.concatenate([rgba, rgba]), process=False)
            handle = canvas.scene.add_mesh_trimesh(_node(name), mesh)
        else:
            handle = canvas.scene.add_mesh_simple(_node(name), value.vertices.astype(np.float32),
                                                  value.faces.astype(np.uint32), color=DEFAULT_MESH_COLOR,
                                                  side="double", flat_shading=True,
                                                  opacity=PLAIN_MESH_OPACITY)
        return Drawn(self.fingerprint(name, value, state, canvas), [handle])


class GaussianSplatsRenderer(Renderer):
    """:class:`GaussianSplats` -> ``scene.add_gaussian_splats``."""

    value_type = GaussianSplats

    def draw(self, canvas, name, value: GaussianSplats, state, order) -> Drawn:
        handle = canvas.scene.add_gaussian_splats(
            _node(name), centers=value.centers.astype(np.float32),
            covariances=value.covariances.astype(np.float32),
            rgbs=np.clip(value.rgbs, 0, 1).astype(np.float32),
            opacities=np.clip(value.opacities, 0, 1).astype(np.float32))
        return Drawn(self.fingerprint(name, value, state, canvas), [handle])


def _set_order(handle: Any, order: float) -> None:
    if handle.order != order:
        handle.order = order


class ImageRenderer(Renderer):
    """:class:`Image` -> a GUI image panel (with the overlays that name it), its picture changed in place."""

    value_type = Image
    in_scene = False

    def fingerprint(self, name, value, state, canvas) -> tuple:
        return (id(value), tuple(id(o) for _, o in overlays_of(state, name)))

    def draw(self, canvas, name, value: Image, state, order) -> Drawn:
        overlays = [o for _, o in overlays_of(state, name)]
        with _gui_context(canvas.images):
            handle = canvas.gui.add_image(overlay_view(value, overlays, min_side=PANEL_MIN_SIDE),
                                          label=self.label(name, value), format="jpeg", jpeg_quality=90,
                                          order=order)
        return Drawn(self.fingerprint(name, value, state, canvas), [handle], parts={"image": handle})

    def redraw(self, canvas, name, value: Image, state, order, drawn: Drawn) -> bool:
        handle = drawn.parts["image"]
        handle.image = overlay_view(value, [o for _, o in overlays_of(state, name)], min_side=PANEL_MIN_SIDE)
        handle.label = self.label(name, value)
        _set_order(handle, order)
        return True

    @staticmethod
    def label(name: str, value: Image) -> str:
        return f"{name} ({value.width}x{value.height})"


class ImageSetPanel:
    """The GUI of one image set: a folder holding a view slider and the picture of the view shown, made once
    (:meth:`ImageSetRenderer.draw`) and then changed in place for every new value (:meth:`set`) or view
    (:meth:`show`). The slider is hidden while the set has one view, the picture while it has none."""

    def __init__(self, canvas: Canvas, name: str, order: float) -> None:
        self.canvas, self.name = canvas, name
        self.value: ImageSet = ImageSet(())
        self.overlays: list[tuple[str, Points2D | Segments2D]] = []
        gui = canvas.gui
        with _gui_context(canvas.images):
            self.folder = gui.add_folder(name, order=order)
            with self.folder:
                self.slider = gui.add_slider("view", min=0, max=1, step=1, initial_value=0, visible=False,
                                             hint=f"which view of {name} to show")
                self.picture = gui.add_image(np.zeros((8, 8, 3), np.uint8), label=name, format="jpeg",
                                             jpeg_quality=90, visible=False)
        #: The view the picture shows (the slider's callback skips a move to it: the code moved it).
        self.shown: int | None = None
        self.slider.on_update(lambda event: None if int(event.target.value) == self.shown else
                              self.show(event.target.value))

    def set(self, value: ImageSet, overlays: list[tuple[str, Points2D | Segments2D]], order: float) -> None:
        """Show ``value`` with these overlays, at the view the canvas remembers for it (clamped)."""
        self.value, self.overlays = value, overlays
        n = len(value)
        self.folder.label = f"{self.name} ({n} views)" if n else f"{self.name} (empty image set)"
        _set_order(self.folder, order)
        view = min(max(self.canvas.views.get(self.name, 0), 0), max(n - 1, 0))
        self.shown = view
        if n > 1:
            if self.slider.value > n - 1:  # never a value beyond the slider's end, not even for a moment
                self.slider.value = view
            self.slider.max = n - 1
        self.slider.visible = n > 1
        self.picture.visible = n > 0
        self.show(view)

    def caption(self, index: int) -> str:
        parts = [f"{self.name}[{index}] {self.value.names[index]}"]
        for overlay_name, overlay in self.overlays:
            parts.append(f"{overlay_name}: {int(_on_view(overlay, index).sum())}")
        return " | ".join(parts)

    def show(self, index: int) -> None:
        """Show view ``index`` (clamped) in the picture, and on the slider."""
        n = len(self.value)
        if n == 0:
            return
        index = min(max(int(index), 0), n - 1)
        self.canvas.views[self.name] = index
        self.shown = index
        self.picture.image = overlay_view(self.value[index], [o for _, o in self.overlays], view=index,
                                          min_side=PANEL_MIN_SIDE)
        self.picture.label = self.caption(index)
        if n > 1 and self.slider.value != index:
            self.slider.value = index


class ImageSetRenderer(Renderer):
    """:class:`ImageSet` -> a GUI image panel with a view slider (an :class:`ImageSetPanel`); 2D overlays
    drawn into each view.

    Overlays are the :class:`Points2D` / :class:`Segments2D` in state whose ``image`` is this
    set's name (e.g. detected corners, and reprojection residuals magnified by the module);
    each keeps only its items on the view shown. The caption names the view and the overlays.
    """

    value_type = ImageSet
    in_scene = False

    def fingerprint(self, name, value, state, canvas) -> tuple:
        return (id(value), tuple(id(o) for _, o in overlays_of(state, name)))

    def draw(self, canvas, name, value: ImageSet, state, order) -> Drawn:
        panel = ImageSetPanel(canvas, name, order)
        drawn = Drawn(self.fingerprint(name, value, state, canvas), [panel.folder],
                      refresh_view=lambda: panel.show(canvas.views.get(name, 0)),
                      parts={"panel": panel, "slider": panel.slider, "image": panel.picture})
        panel.set(value, overlays_of(state, name), order)
        return drawn

    def redraw(self, canvas, name, value: ImageSet, state, order, drawn: Drawn) -> bool:
        drawn.parts["panel"].set(value, overlays_of(state, name), order)
        return True


class CurveRenderer(Renderer):
    """:class:`Curve` -> a uPlot chart (line, scatter) or a bar chart image where the worst bar is red; a new
    curve changes the element in place (:func:`lab.viewer.plots.set_uplot`). A curve that turns from a chart
    into a picture (or back) shows the other element and hides the one it had: both stay until the value
    goes, so no element is removed while an update of it may still be on its way to the page."""

    value_type = Curve
    in_scene = False

    @staticmethod
    def as_picture(value: Curve) -> bool:
        return value.kind == "bar" or len(value.x) < 2

    def draw(self, canvas, name, value: Curve, state, order) -> Drawn:
        drawn = Drawn(self.fingerprint(name, value, state, canvas), [],
                      parts={"line": None, "bars": None, "picture": self.as_picture(value)})
        self._show(canvas, name, value, order, drawn)
        return drawn

    def redraw(self, canvas, name, value: Curve, state, order, drawn: Drawn) -> bool:
        self._show(canvas, name, value, order, drawn)
        return True

    def _show(self, canvas: Canvas, name: str, value: Curve, order: float, drawn: Drawn) -> None:
        """Show ``value`` in the element of its kind (``parts["line"]``, a uPlot chart, or ``parts["bars"]``,
        a picture; added the first time it is needed), the other hidden; ``parts["chart"]`` is the one
        shown."""
        picture, title = self.as_picture(value), value.title or name
        key, other = ("bars", "line") if picture else ("line", "bars")
        handle = drawn.parts[key]
        if handle is None:
            with _gui_context(canvas.plots):
                if picture:  # the panel's label is the title
                    handle = canvas.gui.add_image(curve_image(replace(value, title="")), label=title,
                                                  format="png", order=order)
                else:
                    handle = add_uplot(canvas.gui, value, title=title, order=order, name=name)
            drawn.handles.append(handle)
            drawn.parts[key] = handle
        elif picture:
            handle.image = curve_image(replace(value, title=""))
            handle.label = title
        else:
            config = uplot_config(value, name)
            set_uplot(handle, data=config["data"], series=config["series"], scales=config["scales"],
                      axes=config["axes"], title=title)
        if not handle.visible:
            handle.visible = True
        _set_order(handle, order)
        hidden = drawn.parts[other]
        if hidden is not None and hidden.visible:
            hidden.visible = False
        drawn.parts["picture"], drawn.parts["chart"] = picture, handle


def uplot_config(curve: Curve, name: str = "") -> dict[str, Any]:
    """Keyword arguments of ``gui.add_uplot`` for a line or scatter :class:`Curve`.

    The y axis is logarithmic, labelled per decade, when every value is positive and they span decades (a
    loss curve, a noise schedule: :func:`lab.viewer.plots.chart_axes`); the x axis ends at the last x.
    """
    palette = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd")
    series: list[dict[str, Any]] = [{"label": curve.xlabel or "x"}]
    for s in range(len(curve.y)):
        label = curve.labels[s] if s < len(curve.labels) else (curve.ylabel or curve.title or name or f"y{s}")
        entry: dict[str, Any] = {"label": label, "stroke": palette[s % len(palette)], "width": 2}
        if curve.kind == "scatter":
            entry.update(width=0, points={"show": True, "size": 5, "fill": palette[s % len(palette)]})
        series.append(entry)
    scales, axes = chart_axes(curve.x, curve.y)  # log axes labelled per decade (uPlot: 1e-4 reads "0")
    scales["x"] = {**scales["x"], "time": False}
    return {"data": (curve.x.astype(np.float64), *[row.astype(np.float64) for row in curve.y]),
            "series": tuple(series), "scales": scales, "axes": axes}


def add_uplot(gui: Any, curve: Curve, *, title: str, order: float | None = None, name: str = "") -> Any:
    config = uplot_config(curve, name)
    return gui.add_uplot(config["data"], config["series"], scales=config["scales"], axes=config["axes"],
                         title=title, aspect=1.6, order=order)


#: The renderer of every drawable type. Points2D and Segments2D are overlays: they have none of
#: their own and are drawn by the Image / ImageSet / Cameras renderers of the image they name.
RENDERERS: dict[type, Renderer] = {r.value_type: r for r in (
    PointCloudRenderer(), CamerasRenderer(), Segments3DRenderer(), MeshRenderer(), GaussianSplatsRenderer(),
    ImageRenderer(), ImageSetRenderer(), CurveRenderer())}

#: Types drawn only as overlays on the image (set) they name.
OVERLAY_TYPES = (Points2D, Segments2D)


def renderer_for(value: Any) -> Renderer | None:
    return RENDERERS.get(type(value))


class StateDrawer:
    """Keeps a :class:`Canvas` in step with a state dict: draw new values, redraw changed ones,
    remove the ones that are gone (invalidated by a re-run upstream).

    Not thread-safe by itself: the viewer calls it under its per-client lock.
    """

    def __init__(self, canvas: Canvas) -> None:
        self.canvas = canvas
        self.drawn: dict[str, Drawn] = {}
        self.errors: dict[str, str] = {}
        self.kept: dict[str, Any] = {}

    def sync(self, state: Mapping[str, Any], *, order: Mapping[str, float] | None = None) -> list[str]:
        """Draw ``state``; returns the names (re)drawn. A value whose drawing fails is skipped
        and its error kept in :attr:`errors` (a bad value never breaks the rest of the scene)."""
        self.canvas.extent = scene_extent(state.values())
        self.kept = dict(state)  # fingerprints are ids: the values they name must live until the next sync
        drawable = {name: value for name, value in state.items() if self._draws(value)}
        for name in [n for n in self.drawn if n not in drawable]:
            self.drawn.pop(name).remove()
            self.errors.pop(name, None)
        changed = []
        for position, name in enumerate(sorted(drawable, key=lambda n: ((order or {}).get(n, 1e9), n))):
            value = drawable[name]
            renderer = renderer_for(value)
            if renderer is None:  # not drawable (_draws left it out already)
                continue
            fingerprint = renderer.fingerprint(name, value, state, self.canvas)
            old = self.drawn.get(name)
            if old is not None and old.fingerprint == fingerprint:
                continue
            try:
                if old is not None and old.renderer is renderer and \
                        renderer.redraw(self.canvas, name, value, state, float(position), old):
                    old.fingerprint = fingerprint
                else:  # new, or of another type now (another module's value of that name)
                    if old is not None:
                        old.remove()
                        del self.drawn[name]
                    self.drawn[name] = renderer.draw(self.canvas, name, value, state, float(position))
                    self.drawn[name].renderer = renderer
                self.errors.pop(name, None)
                changed.append(name)
            except Exception as exc:  # report it in the GUI, keep drawing the rest
                self.errors[name] = f"{type(exc).__name__}: {exc}"
        return changed

    def _draws(self, value: Any) -> bool:
        renderer = renderer_for(value)
        if renderer is None:
            return False
        return renderer.in_scene or self.canvas.gui is not None

    def show_view(self, image_name: str, view: int) -> None:
        """Show view ``view`` of the image set ``image_name`` in its panel (a frustum was clicked)."""
        self.canvas.views[image_name] = int(view)
        drawn = self.drawn.get(image_name)
        if drawn is not None and drawn.refresh_view is not None:
            drawn.refresh_view()

    def clear(self) -> None:
        for drawn in self.drawn.values():
            drawn.remove()
        self.drawn.clear()
        self.errors.clear()
        self.kept = {}


__all__ = ["CLOUD_COLORS", "FRUSTUM_SHARE", "OVERLAY_TYPES", "PLAIN_MESH_OPACITY", "RENDERERS", "SCENE_ROOT",
           "Canvas", "Drawn", "Renderer", "StateDrawer", "curve_image", "default_cloud_colors",
           "frustum_corners", "overlay_view", "overlays_of", "renderer_for", "scene_bounds", "scene_extent",
           "to_rgb8", "uplot_config", "viewpoint", "wxyz_from_matrix"]
