"""Image pairs: which are matched, where a pair's matches are, how much parallax a verified pair has."""

from __future__ import annotations

import numpy as np


def image_pairs(count: int, *, pairs: str = "exhaustive", window: int = 3) -> list[tuple[int, int]]:
    """The pairs ``(a, b)``, ``a < b``, to match: all of them, or each image with the next ``window`` ones."""
    if pairs == "exhaustive":
        return [(a, b) for a in range(count) for b in range(a + 1, count)]
    return [(a, b) for a in range(count) for b in range(a + 1, min(count, a + 1 + int(window)))]


def pair_rows(matches: np.ndarray, a: int, b: int) -> np.ndarray:
    """Rows of ``matches`` ``(M, 4)`` between views ``a`` and ``b`` (``a < b``)."""
    return np.flatnonzero((matches[:, 0] == a) & (matches[:, 1] == b))


def pair_parallax(x1: np.ndarray, x2: np.ndarray, K1: np.ndarray, K2: np.ndarray, R: np.ndarray,
                  t: np.ndarray) -> float:
    """Median angle (deg) between the two rays of each correspondence under the relative pose ``(R, t)``."""
    r1 = np.column_stack([x1, np.ones(len(x1))]) @ np.linalg.inv(K1).T
    r2 = (np.column_stack([x2, np.ones(len(x2))]) @ np.linalg.inv(K2).T) @ R  # in camera 1's frame
    cos = np.sum(r1 * r2, axis=1) / (np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1))
    return float(np.degrees(np.median(np.arccos(np.clip(cos, -1.0, 1.0)))))
