"""Budgets on what one request may make the lab hold: pixels per image and per dataset, JSON size and depth.

Each budget is a module constant, read when it is checked, so whoever runs the server (or a
test) changes it by assignment before serving, e.g. ``lab.core.budgets.MAX_IMAGE_PIXELS =
120_000_000`` for a 100 MP camera. The defaults fit real photos (a 24 MP camera photo passes;
the lab's own datasets are far below) and keep one request under about a gigabyte:

``MAX_IMAGE_PIXELS``
    Width x height of one image read from bytes: an upload or a file of a folder dataset. It is
    checked from the file's header (:func:`lab.core.codecs.image_size`) before anything is
    decoded, so a 1 MB PNG claiming 30000 x 30000 pixels is refused without allocating them.
``MAX_DATASET_PIXELS``
    Views x width x height that a generated dataset's options may ask for (the synthetic
    checkerboard, rendered scenes and pairs), checked before anything is rendered, and the total
    pixels of the images of one upload request.
``MAX_STEREO_BYTES``
    Memory that stereo's semi-global matching may hold for one pair (1 GiB). A cost volume too
    large to keep whole is aggregated by rows (:mod:`lab.modules.stereo.lean`: 16-bit path sums of
    every pixel and disparity, about ``width x height x disparities x 2`` bytes); a pair needing more
    is refused before anything is computed, naming the memory it needs and the dataset's
    ``downsample`` option. A 1.5-megapixel pair with 256 disparities needs about 0.85 GiB.
``MAX_JSON_NUMBERS``
    Numbers in one ``format=json`` answer (a JSON number costs about 20 bytes of text and far more
    as a Python object while it is built); larger values are refused and pointed to ``npy``/``png``.
``MAX_JSON_DEPTH``
    Nesting of arrays and objects in an uploaded JSON document (the lab's deepest value, an image
    set, nests 5 levels).

A budget exceeded is :class:`~lab.core.errors.CapacityExceeded` (413, kind ``capacity``) naming the
field at fault and the budget; a JSON answer that is too large or an upload nested too deeply is
:class:`~lab.core.errors.InvalidValue` (422) saying what to ask for instead.
"""

from __future__ import annotations

from lab.core.errors import CapacityExceeded

MAX_IMAGE_PIXELS: int = 50_000_000
MAX_DATASET_PIXELS: int = 64 * 2**20
MAX_STEREO_BYTES: int = 2**30
MAX_JSON_NUMBERS: int = 2**20
MAX_JSON_DEPTH: int = 64


def megapixels(pixels: int) -> str:
    """``pixels`` in words: ``"900.0 MP"``."""
    return f"{pixels / 1e6:.1f} MP"


def check_image_pixels(width: int, height: int, *, field: str, what: str) -> None:
    """Refuse (CapacityExceeded on ``field``) an image of ``width`` x ``height`` over
    :data:`MAX_IMAGE_PIXELS`.

    ``what`` names the image in the reason (``"'big.png'"``, ``"the upload"``).
    """
    pixels = int(width) * int(height)
    if pixels > MAX_IMAGE_PIXELS:
        raise CapacityExceeded(field, f"{what} is {width} x {height} pixels ({megapixels(pixels)}); "
                                      f"images may have at most {megapixels(MAX_IMAGE_PIXELS)} "
                                      "(lab.core.budgets.MAX_IMAGE_PIXELS): shrink it before loading it")


def check_dataset_pixels(*, views: int, width: int, height: int, field: str = "num_views") -> None:
    """Refuse (CapacityExceeded on ``field``) options asking for ``views`` x ``width`` x ``height`` over
    :data:`MAX_DATASET_PIXELS` (called by generated datasets before they render anything)."""
    pixels = int(views) * int(width) * int(height)
    if pixels > MAX_DATASET_PIXELS:
        raise CapacityExceeded(field, f"{views} views of {width} x {height} pixels make "
                                      f"{megapixels(pixels)}; a dataset may make at most "
                                      f"{megapixels(MAX_DATASET_PIXELS)} "
                                      "(lab.core.budgets.MAX_DATASET_PIXELS): ask for fewer or smaller views")


def check_upload_pixels(pixels: int, *, field: str) -> None:
    """Refuse (CapacityExceeded on ``field``) one upload whose images total over
    :data:`MAX_DATASET_PIXELS`."""
    if pixels > MAX_DATASET_PIXELS:
        raise CapacityExceeded(field, f"the uploaded images total {megapixels(pixels)}; one upload may hold "
                                      f"at most {megapixels(MAX_DATASET_PIXELS)} "
                                      "(lab.core.budgets.MAX_DATASET_PIXELS): send fewer or smaller images "
                                      "per request (?append=true adds views)")


__all__ = ["MAX_DATASET_PIXELS", "MAX_IMAGE_PIXELS", "MAX_JSON_DEPTH", "MAX_JSON_NUMBERS", "MAX_STEREO_BYTES",
           "check_dataset_pixels", "check_image_pixels", "check_upload_pixels", "megapixels"]
