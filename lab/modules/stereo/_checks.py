"""Input checks of the stereo steps and their helpers: each refuses a bad value with an error naming it.

Private to the package; :data:`MAX_VOLUME_ENTRIES` is re-exported by ``lab.modules.stereo``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lab.core import Image, InvalidControl, InvalidValue

#: Largest cost volume (H * W * D entries) a step builds and keeps whole: 2**26 float32 entries are 256 MiB.
#: A larger census volume is aggregated by rows in bounded memory (:mod:`lab.modules.stereo.lean`).
MAX_VOLUME_ENTRIES = 2**26


def check_pair(left: Any, right: Any, *, names: tuple[str, str] = ("left", "right")) -> tuple[Image, Image]:
    for value, name in zip((left, right), names, strict=True):
        if not isinstance(value, Image):
            raise InvalidValue(name, f"expected an Image, got {type(value).__name__}")
    if left.pixels.shape[:2] != right.pixels.shape[:2]:
        raise InvalidValue(names[1], f"the two images differ in size: {names[0]} is {left.width} x "
                                     f"{left.height}, {names[1]} is {right.width} x {right.height}; a stereo "
                                     "pair needs one size")
    return left, right


def check_window(window: int, cost: str = "sad") -> int:
    window = int(window)
    if window < 1 or window % 2 == 0:
        raise InvalidControl("window", f"must be an odd number of pixels (1, 3, 5 ...), got {window}")
    if cost in ("rank", "census") and window < 3:
        raise InvalidControl("window", f"{cost} compares each pixel with its neighbours: the window must "
                                       "be at least 3")
    return window


def check_max_disparity(max_disparity: int, width: int) -> int:
    max_disparity = int(max_disparity)
    if max_disparity < 1:
        raise InvalidControl("max_disparity", f"must be at least 1 pixel, got {max_disparity}")
    if max_disparity >= width:
        raise InvalidControl("max_disparity", f"the disparity range (0 to {max_disparity} px) is larger than "
                                              f"the image, which is {width} px wide; use at most {width - 1}")
    return max_disparity


def check_volume(volume: Any, name: str, *, finite: bool = True) -> np.ndarray:
    array = np.asarray(volume)
    if array.ndim != 3 or array.shape[2] < 1:
        raise InvalidValue(name, f"a cost volume is (H, W, D), got shape {array.shape}")
    if array.dtype.kind not in "fiu":
        raise InvalidValue(name, f"a cost volume holds numbers, got dtype {array.dtype}")
    array = np.ascontiguousarray(array, dtype=np.float32)
    # NaN propagates through min and max
    if finite and array.size and not (np.isfinite(array.min()) and np.isfinite(array.max())):
        raise InvalidValue(name, "contains NaN or infinite costs")
    return array


def check_map(value: Any, name: str, shape: tuple[int, int], *, kind: str = "f") -> np.ndarray:
    array = np.asarray(value)
    if array.shape != shape:
        raise InvalidValue(name, f"expected shape {shape} (the cost volume's H, W), got {array.shape}")
    if kind == "b":
        if array.dtype != bool:
            raise InvalidValue(name, f"expected a boolean mask, got dtype {array.dtype}")
        return array
    if array.dtype.kind not in "fiu":
        raise InvalidValue(name, f"expected numbers, got dtype {array.dtype}")
    array = array.astype(np.float64)
    if not np.all(np.isfinite(array)):
        raise InvalidValue(name, "contains NaN or infinite entries; mark holes with -1")
    return array


def integer_disparity(disparity: Any, name: str, shape: tuple[int, int], disparities: int) -> np.ndarray:
    values = check_map(disparity, name, shape)
    rounded = np.rint(values)
    if np.any(rounded < 0) or np.any(rounded >= disparities):
        raise InvalidValue(name, f"winner-take-all disparities must lie in [0, {disparities - 1}] (the "
                                 "volume's range)")
    return rounded.astype(np.int64)


def volume_fits(height: int, width: int, disparities: int) -> bool:
    """Whether a cost volume of ``height x width x disparities`` is kept whole (:data:`MAX_VOLUME_ENTRIES`,
    read at each call so that a test or a server may change it)."""
    return height * width * disparities <= MAX_VOLUME_ENTRIES


def check_baseline(baseline: Any) -> float:
    try:
        value = float(baseline)
    except (TypeError, ValueError):
        raise InvalidValue("baseline", f"expected a number of metres, got {baseline!r}") from None
    if not np.isfinite(value) or value == 0.0:
        raise InvalidValue("baseline", f"the baseline is {value!r}: with both cameras at one place depth "
                                       "cannot be triangulated (Z = f B / d); give the distance between the "
                                       "cameras in metres")
    if value < 0:
        raise InvalidValue("baseline", f"must be a positive distance in metres, got {value}")
    return value
