"""A user's image files: list them in a folder by a shell pattern, and read them as :class:`lab.core.Image`.

Shared by the loaders of a user's photos (:func:`lab.modules.epipolar.datasets.photos`,
:func:`lab.modules.calibration.datasets.folder`, :mod:`lab.modules.stereo.datasets`).
Files are decoded by OpenCV's
``imread`` (any depth, alpha dropped, BGR turned into RGB by
:func:`lab.core.codecs.image_from_cv2`) after their header passed the pixel budget
(:data:`lab.core.budgets.MAX_IMAGE_PIXELS`): a huge file is refused by name, never decoded.
"""

from __future__ import annotations

import glob
import os

import numpy as np

from lab.core import Image, InvalidValue

#: File-name endings OpenCV's ``imread`` decodes.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".jpe", ".bmp", ".dib", ".tif", ".tiff", ".webp", ".pbm", ".pgm",
                  ".ppm", ".pxm", ".pnm", ".sr", ".ras", ".exr", ".hdr", ".pic", ".jp2")


def check_folder(path: str) -> str:
    """``path`` if it names a folder, else :class:`InvalidValue` on ``path``."""
    if not path or not os.path.isdir(path):
        raise InvalidValue("path", f"no folder {path!r}")
    return path


def list_images(path: str, pattern: str = "*") -> list[str]:
    """The image files of folder ``path`` whose names match the shell ``pattern``, sorted by name.

    ``pattern`` is a file-name pattern (``*.jpg``, ``left0?.png``), never a path; files whose
    endings OpenCV does not read are skipped. The list may be empty.
    """
    check_folder(path)
    if not pattern or os.sep in pattern or (os.altsep and os.altsep in pattern):
        raise InvalidValue("pattern", f"must be a file-name pattern such as '*.jpg', got {pattern!r}")
    return sorted(f for f in glob.glob(os.path.join(glob.escape(path), pattern))
                  if os.path.isfile(f) and f.lower().endswith(IMAGE_SUFFIXES))


def read_image_file(file: str) -> np.ndarray:
    """``cv2.imread(file, IMREAD_UNCHANGED)`` once the header is within the pixel budget.

    Raises CapacityExceeded (413) on ``path`` naming the file when it has more than
    :data:`lab.core.budgets.MAX_IMAGE_PIXELS` pixels, InvalidValue when it is not an image the lab
    reads; neither decodes a pixel.
    """
    import cv2

    from lab.core.codecs import check_image_header

    what = f"{os.path.basename(file)!r} in {os.path.dirname(file) or '.'!r}"
    try:
        with open(file, "rb") as stream:
            check_image_header(stream, field="path", what=what)
    except OSError as exc:
        raise InvalidValue("path", f"cannot open {what}: {exc.strerror or exc}") from None
    decoded = cv2.imread(file, cv2.IMREAD_UNCHANGED)
    if decoded is None:
        raise InvalidValue("path", f"OpenCV cannot read {what}")
    return decoded


def read_images(files: list[str]) -> list[Image]:
    """Decode each file (:func:`read_image_file`, unchanged depth) into an Image named by its file name."""
    from lab.core.codecs import image_from_cv2

    return [image_from_cv2(read_image_file(file), name=os.path.basename(file)) for file in files]


__all__ = ["IMAGE_SUFFIXES", "check_folder", "list_images", "read_image_file", "read_images"]
