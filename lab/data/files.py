"""A user's image files: list them in a folder by a shell pattern, and read them as :class:`lab.core.Image`.

Shared by the loaders of a user's photos (:func:`lab.modules.epipolar.datasets.photos`,
:func:`lab.modules.calibration.datasets.folder`, :mod:`lab.modules.stereo.datasets`).
Files are decoded by OpenCV's
``imread`` (any depth, alpha dropped, BGR turned into RGB by
:func:`lab.core.codecs.image_from_cv2`) after their header passed the pixel budget
(:data:`lab.core.budgets.MAX_IMAGE_PIXELS`): a huge file is refused by name, never decoded.

Photos are read at a working size (:func:`read_working_images`): a 12-megapixel phone photo is 144 MB of
float32 pixels, and a folder of them would hold gigabytes (issue 19: three 4096 x 4096 views cost 4.2 GB).
A file larger than the working size is decoded reduced where its codec can (JPEG's DCT scaling, OpenCV's
``IMREAD_REDUCED_COLOR_2/4/8``) and then shrunk by area averaging (``cv2.INTER_AREA``) in its own depth,
before the one float32 copy; the loaders scale K with the image and say so in their description.
"""

from __future__ import annotations

import glob
import os
from dataclasses import dataclass

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


#: The longer side, in pixels, of the working size the folder datasets read photos at by default (a
#: 4000 x 3000 photo is read at 1600 x 1200: 23 MB of float32 pixels instead of 144 MB).
WORKING_SIDE = 1600


def _file_header(file: str) -> tuple[str, tuple[int, int], bool]:
    """``(what, (width, height), is_jpeg)`` of ``file`` once its header passed the pixel budget."""
    from lab.core.codecs import check_image_header

    what = f"{os.path.basename(file)!r} in {os.path.dirname(file) or '.'!r}"
    try:
        with open(file, "rb") as stream:
            size = check_image_header(stream, field="path", what=what)
            stream.seek(0)
            is_jpeg = stream.read(2) == b"\xff\xd8"
    except OSError as exc:
        raise InvalidValue("path", f"cannot open {what}: {exc.strerror or exc}") from None
    return what, size, is_jpeg


def read_image_file(file: str, *, max_side: int = 0) -> np.ndarray:
    """``cv2.imread(file, IMREAD_UNCHANGED)`` once the header is within the pixel budget, shrunk so that its
    longer side is at most ``max_side`` pixels (0: full size).

    A shrunk JPEG is decoded reduced by the largest of 2, 4, 8 that keeps it at least ``max_side``
    (``IMREAD_REDUCED_COLOR_n``: 8-bit colour; a grey photo comes back with one channel), other files at
    full size; then ``cv2.resize(..., INTER_AREA)`` to the exact size, in the file's own depth.

    Raises CapacityExceeded (413) on ``path`` naming the file when it has more than
    :data:`lab.core.budgets.MAX_IMAGE_PIXELS` pixels, InvalidValue when it is not an image the lab
    reads; neither decodes a pixel.
    """
    import cv2

    what, (width, height), is_jpeg = _file_header(file)
    longer = max(width, height)
    target = working_size((width, height), max_side)
    reduction = 1
    if is_jpeg:
        while reduction < 8 and longer / (2 * reduction) >= max(target):
            reduction *= 2
    flags = {1: cv2.IMREAD_UNCHANGED, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
             8: cv2.IMREAD_REDUCED_COLOR_8}[reduction]
    decoded = cv2.imread(file, flags)
    if decoded is None:
        raise InvalidValue("path", f"OpenCV cannot read {what}")
    if reduction > 1 and np.array_equal(decoded[..., 0], decoded[..., 1]) \
            and np.array_equal(decoded[..., 0], decoded[..., 2]):
        decoded = np.ascontiguousarray(decoded[..., 0])
    if (decoded.shape[1], decoded.shape[0]) != target:
        decoded = cv2.resize(decoded, target, interpolation=cv2.INTER_AREA)
    return decoded


def working_size(size: tuple[int, int], max_side: int) -> tuple[int, int]:
    """``(width, height)`` of an image of ``size`` shrunk (never enlarged) so its longer side is at most
    ``max_side`` (0: ``size``), the aspect kept to the nearest pixel."""
    width, height = size
    if not max_side or max(width, height) <= max_side:
        return width, height
    scale = max_side / max(width, height)
    return max(1, round(width * scale)), max(1, round(height * scale))


def read_images(files: list[str]) -> list[Image]:
    """Decode each file (:func:`read_image_file`, unchanged depth) into an Image named by its file name."""
    from lab.core.codecs import image_from_cv2

    return [image_from_cv2(read_image_file(file), name=os.path.basename(file)) for file in files]


@dataclass(frozen=True)
class WorkingImages:
    """Photos read at a working size (:func:`read_working_images`).

    ``images`` at most ``max_side`` on their longer side; ``scales`` each image's working width over its
    file's width (1.0: read at full size; K of the file becomes
    :func:`lab.geometry.camera.scale_intrinsics` ``(K, scale)``); ``original_sizes`` the files'
    ``(width, height)``.
    """

    images: tuple[Image, ...]
    scales: tuple[float, ...]
    original_sizes: tuple[tuple[int, int], ...]
    max_side: int

    @property
    def note(self) -> str:
        """What was shrunk, for a dataset's description ("" when nothing was)."""
        shrunk = [i for i, s in enumerate(self.scales) if s < 1.0]
        if not shrunk:
            return ""
        first = shrunk[0]
        (w, h), image = self.original_sizes[first], self.images[first]
        count = len(self.images)
        which = "the photo" if count == 1 else (
            "every photo" if len(shrunk) == count else f"{len(shrunk)} of {count} photos")
        return (f"{which} read at the working size (e.g. {image.width} x {image.height} instead of "
                f"{w} x {h}: max_side={self.max_side}; max_side=0 reads full resolution)")


def read_working_images(files: list[str], *, max_side: int = WORKING_SIDE) -> WorkingImages:
    """Each file as an Image named by its file name, at most ``max_side`` pixels on its longer side (0: full
    resolution): at most one full-size decode in the file's own depth is alive at a time, and only the
    working-size pixels are turned into float32 (:func:`read_image_file`)."""
    from lab.core.codecs import image_from_cv2

    if max_side < 0:
        raise InvalidValue("max_side", f"must be 0 (full resolution) or a positive side, got {max_side}")
    images, scales, sizes = [], [], []
    for file in files:
        _, size, _ = _file_header(file)
        image = image_from_cv2(read_image_file(file, max_side=max_side), name=os.path.basename(file))
        images.append(image)
        scales.append(image.width / size[0])
        sizes.append(size)
    return WorkingImages(tuple(images), tuple(scales), tuple(sizes), int(max_side))


__all__ = ["IMAGE_SUFFIXES", "WORKING_SIDE", "WorkingImages", "check_folder", "list_images",
           "read_image_file", "read_images", "read_working_images", "working_size"]
