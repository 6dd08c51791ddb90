"""The values the viewer draws from a calibration: the camera rig, the board, residuals and error plots."""

from __future__ import annotations

import numpy as np

from lab.core import Cameras, Curve, ImageSet, Mesh, Segments2D
from lab.modules.calibration.board import Checkerboard
from lab.modules.calibration.observations import Observations


def rms_colors(values: np.ndarray) -> np.ndarray:
    """Green (smallest) to red (largest) for each value, ``(N, 3)``."""
    values = np.asarray(values, dtype=np.float64)
    span = values.max() - values.min() if len(values) else 0.0
    level = (values - values.min()) / span if span > 0 else np.zeros(len(values))
    return np.stack([0.15 + 0.8 * level, 0.75 - 0.65 * level, 0.2 - 0.1 * level], axis=1)


def board_mesh(board: Checkerboard | None, board_points: np.ndarray) -> Mesh:
    """The printed board (its squares), or a grey rectangle around the corners when the board is unknown."""
    if isinstance(board, Checkerboard):
        return board.mesh()
    lo, hi = board_points[:, :2].min(axis=0), board_points[:, :2].max(axis=0)
    vertices = np.array([[lo[0], lo[1], 0.0], [hi[0], lo[1], 0.0], [hi[0], hi[1], 0.0], [lo[0], hi[1], 0.0]])
    return Mesh(vertices, np.array([[0, 1, 2], [0, 2, 3]]), np.full((4, 3), 0.8))


def view_names(images: ImageSet | None, views: np.ndarray) -> tuple[str, ...]:
    """The photo name of each used view (``view i`` where there are no photos)."""
    if isinstance(images, ImageSet):
        names = images.names
    else:
        names = tuple(f"view {i}" for i in range(int(views.max()) + 1))
    return tuple(names[i] if i < len(names) else f"view {i}" for i in views)


def camera_rig(K: np.ndarray, dist: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
               views: np.ndarray, per_view_rms: np.ndarray, images: ImageSet | None) -> Cameras:
    """The cameras around the board (board frame = world), each carrying its photo, coloured by its RMS."""
    if isinstance(images, ImageSet) and len(images):
        width, height = images[0].width, images[0].height
    else:
        width, height = max(1, round(2 * K[0, 2] + 1)), max(1, round(2 * K[1, 2] + 1))
    return Cameras(K=np.broadcast_to(K, (len(views), 3, 3)).copy(), R=rotations, t=translations, width=width,
                   height=height, dist=dist, image="images", views=views, colors=rms_colors(per_view_rms))


def residual_segments(seen: Observations, residuals: np.ndarray, scale: float) -> Segments2D:
    """Detected corner -> detected + ``scale`` (reprojected - detected), coloured by the residual's length."""
    magnitude = np.sqrt(np.sum(residuals * residuals, axis=1))
    return Segments2D(seen.pixels, seen.pixels + scale * residuals, view=seen.image,
                      colors=rms_colors(magnitude), image="images")


def per_view_curve(per_view_rms: np.ndarray, names: tuple[str, ...]) -> Curve:
    """Bars of the RMS reprojection error per view, named by photo; the title names the worst."""
    worst = int(np.argmax(per_view_rms))
    return Curve(np.arange(len(per_view_rms), dtype=np.float64), per_view_rms, kind="bar",
                 title=f"RMS reprojection error per view (worst: {names[worst]}, "
                       f"{per_view_rms[worst]:.3f} px)",
                 xlabel="view", ylabel="RMS (px)", labels=("RMS",), categories=names)


def cost_curve(history: list[float]) -> Curve:
    """The RMS reprojection error after every Levenberg-Marquardt iteration."""
    return Curve(np.arange(len(history), dtype=np.float64), np.array(history), kind="line",
                 title="Levenberg-Marquardt", xlabel="iteration", ylabel="RMS reprojection error (px)",
                 labels=("RMS",))


__all__ = ["board_mesh", "camera_rig", "cost_curve", "per_view_curve", "residual_segments", "rms_colors",
           "view_names"]
