"""What calibration exports: the camera as OpenCV's calibration sample writes it (``vision-lab export``).

The CLI and REST call it through the pipeline, never by state name::

    written = PIPELINE.export("opencv-yaml").write(session.state, session.metrics, out)
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lab.core import Cameras, Export, ImageSet, InvalidValue, MissingInput


def write_opencv_yaml(state: Mapping[str, Any], metrics: Mapping[str, Mapping[str, Any]], out: Path) -> Path:
    """Write ``K`` and ``dist`` with the image size, the board, the poses and the reprojection errors.

    ``metrics`` maps step names to their last metrics: the RMS errors are those of
    ``refine_calibration`` (``rms_px``, ``per_view_rms_px``), left out when it has not run. The image
    size is the cameras' (or the first photo's); the board and the poses (``rotations``,
    ``translations``) are written when the state has them. The file reads back with
    ``cv2.FileStorage`` and :func:`lab.data.exports.read_opencv_calibration`.
    """
    from lab.data.exports import write_opencv_calibration

    for name in ("K", "dist"):
        if name not in state:
            raise MissingInput(name, f"opencv-yaml writes the camera's {name}: run refine_calibration first")
    cameras, images = state.get("cameras"), state.get("images")
    if isinstance(cameras, Cameras):
        width, height = cameras.width, cameras.height
    elif isinstance(images, ImageSet) and len(images):
        height, width = images[0].pixels.shape[:2]
    else:
        raise InvalidValue("images", "opencv-yaml needs the image size: the session has no images or cameras")
    fit = metrics.get("refine_calibration", {})
    per_view = fit.get("per_view_rms_px")
    board = state.get("board")
    return write_opencv_calibration(
        out, state["K"], state["dist"], image_width=width, image_height=height,
        avg_reprojection_error=fit.get("rms_px"),
        per_view_reprojection_errors=per_view if isinstance(per_view, list) else None,
        board_width=getattr(board, "columns", None), board_height=getattr(board, "rows", None),
        square_size=getattr(board, "square_size", None),
        rotations=state.get("rotations"), translations=state.get("translations"))


OPENCV_YAML = Export(
    "opencv-yaml", "the camera (K, dist, image size, board, poses, RMS errors) as OpenCV's calibration YAML",
    reads=("K", "dist", "cameras", "images", "board", "rotations", "translations"), write=write_opencv_yaml)

__all__ = ["OPENCV_YAML", "write_opencv_yaml"]
