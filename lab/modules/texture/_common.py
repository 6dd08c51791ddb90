"""What every part of the texture module shares: the input checks, the image layouts, luminance.

Images are float32 ``(H, W)`` or ``(H, W, 3)`` in [0, 1]; the synthesis works on ``(H, W, C)``
float64 (:func:`as_hwc`) and hands back the caller's layout (:func:`from_hwc`).
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from typing import Annotated, Any, TypeVar

import numpy as np

from lab.core import Image, InvalidControl, InvalidValue, Progress, Range

#: An output size control: (height, width) in pixels.
Size = Annotated[tuple[int, int], Range(1, 1024)]

_Item = TypeVar("_Item")
_Result = TypeVar("_Result")


def as_image(value: Any, name: str) -> Image:
    """``value`` if it is an :class:`Image`, else :class:`InvalidValue` naming the input ``name``."""
    if not isinstance(value, Image):
        raise InvalidValue(name, f"expected an Image, got {type(value).__name__}")
    return value


def channel_count(pixels: np.ndarray) -> int:
    """1 for ``(H, W)``, ``C`` for ``(H, W, C)``."""
    return 1 if pixels.ndim == 2 else pixels.shape[2]


def as_hwc(pixels: np.ndarray) -> np.ndarray:
    """``(H, W)`` or ``(H, W, C)`` -> ``(H, W, C)`` float64."""
    array = np.asarray(pixels, dtype=np.float64)
    return array[:, :, None] if array.ndim == 2 else array


def from_hwc(array: np.ndarray, like_channels: int) -> np.ndarray:
    """``(H, W, C)`` back to ``(H, W)`` when the image it stands for has one channel."""
    return array[:, :, 0] if like_channels == 1 else array


def luminance(pixels: np.ndarray) -> np.ndarray:
    """``(H, W)`` float64 luminance (BT.601 weights, as ``cv2.cvtColor`` RGB2GRAY)."""
    array = np.asarray(pixels, dtype=np.float64)
    if array.ndim == 2:
        return array
    return array @ np.array([0.299, 0.587, 0.114])


def largest_odd(value: int) -> int:
    return value if value % 2 else value - 1


def check_window(window: int, sample: Image, *, name: str = "window") -> int:
    """An odd window side that fits in the sample, else :class:`InvalidControl` saying what would."""
    window = int(window)
    if window < 1 or window % 2 == 0:
        raise InvalidControl(name, "must be odd so that the window has a centre pixel (3, 5, 7 ...), "
                                   f"got {window}")
    if window > min(sample.height, sample.width):
        raise InvalidControl(name, f"the window ({window} x {window}) is larger than the sample "
                                   f"({sample.width} x {sample.height}); use at most "
                                   f"{largest_odd(min(sample.height, sample.width))}")
    return window


def check_size(size: tuple[int, int], *, smallest: int = 1, what: str = "") -> tuple[int, int]:
    """``(height, width)`` as ints, each at least ``smallest`` (``what`` names that bound in the message)."""
    height, width = (int(v) for v in size)
    if height < smallest or width < smallest:
        raise InvalidControl("size", f"the output ({height} x {width}) is smaller than {what or smallest} "
                                     f"({smallest} px); make it at least {smallest} x {smallest}")
    return height, width


def check_block(block: int, overlap: int, sample: Image) -> tuple[int, int]:
    """A quilting block that fits in the sample and an overlap narrower than it."""
    block, overlap = int(block), int(overlap)
    if block > min(sample.height, sample.width):
        raise InvalidControl("block", f"the block ({block} x {block}) is larger than the sample "
                                      f"({sample.width} x {sample.height}); use at most "
                                      f"{min(sample.height, sample.width)}")
    if block < 2:
        raise InvalidControl("block", f"must be at least 2 pixels, got {block}")
    if not 0 < overlap < block:
        raise InvalidControl("overlap", f"must be at least 1 and smaller than the block ({block}), "
                                        f"got {overlap}")
    return block, overlap


def exhaust(generator: Generator[Any, None, _Result]) -> _Result:
    """Run a generator to its end and return what it returns (its snapshots are dropped)."""
    while True:
        try:
            next(generator)
        except StopIteration as stop:
            return stop.value


def relay(generator: Generator[_Item, None, _Result],
          progress: Callable[[_Item], Progress]) -> Generator[Progress, None, _Result]:
    """Yield ``progress(item)`` for every item ``generator`` yields; return what it returns.

    A step writes ``result = yield from relay(grower, lambda item: Progress(...))``.
    """
    while True:
        try:
            item = next(generator)
        except StopIteration as stop:
            return stop.value
        yield progress(item)
