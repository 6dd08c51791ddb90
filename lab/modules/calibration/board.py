"""The calibration target: a printed chessboard, its inner corners and what is printed where.

The board (:class:`Checkerboard`) has ``columns x rows`` inner corners; corner ``k = r * columns + c``
lies at ``(c * square_size, r * square_size, 0)`` in the board frame, which is the order in which
``cv2.findChessboardCorners`` returns them (row by row). The square between corners 0, 1,
``columns`` and ``columns + 1`` is black, as in OpenCV's sample photos; for boards whose corner
counts differ in parity (9 x 6) that colour fixes which end of the board is corner 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lab.core import InvalidValue, Mesh

#: Label values of the printed pattern (see :meth:`Checkerboard.labels`).
BLACK, WHITE, BACKGROUND = 0, 1, 2


@dataclass(frozen=True)
class Checkerboard:
    """A chessboard calibration target.

    ``columns`` inner corners per row, ``rows`` inner corners per column (OpenCV's ``patternSize``
    is ``(columns, rows)``), squares of ``square_size`` metres. The printed pattern has
    ``(columns + 1) x (rows + 1)`` squares, spanning ``[-s, columns * s] x [-s, rows * s]``.
    """

    columns: int = 9
    rows: int = 6
    square_size: float = 0.025

    def __post_init__(self) -> None:
        for name in ("columns", "rows"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 2:
                raise InvalidValue(name, "a board needs an integer of at least 2 inner corners, "
                                         f"got {value!r}")
            object.__setattr__(self, name, int(value))
        size = self.square_size
        if isinstance(size, bool) or not isinstance(size, (int, float, np.integer, np.floating)) \
                or not np.isfinite(size) or size <= 0:
            raise InvalidValue("square_size", f"must be a positive number of metres, got {size!r}")
        object.__setattr__(self, "square_size", float(size))

    @property
    def pattern_size(self) -> tuple[int, int]:
        """``(columns, rows)``, OpenCV's ``patternSize``."""
        return self.columns, self.rows

    @property
    def num_corners(self) -> int:
        return self.columns * self.rows

    def object_points(self) -> np.ndarray:
        """Inner corners in the board frame, ``(N, 3)`` float64, row by row (OpenCV's order), Z = 0."""
        r, c = np.divmod(np.arange(self.num_corners), self.columns)
        return np.stack([c * self.square_size, r * self.square_size, np.zeros(self.num_corners)], axis=1)

    def labels(self, X: np.ndarray, Y: np.ndarray, *, margin: float | None = None) -> np.ndarray:
        """What is printed at board coordinates ``(X, Y)`` (metres, any shape): BLACK, WHITE or BACKGROUND.

        The squares are surrounded by a white paper margin of ``margin`` metres (default one square);
        outside the paper is BACKGROUND. Square ``(a, b)``, spanning ``[a s, (a + 1) s] x [b s, (b + 1) s]``,
        is black when ``a + b`` is even.
        """
        s = self.square_size
        margin = s if margin is None else margin
        x = np.asarray(X)
        y = np.asarray(Y)
        a = np.floor(x / s)
        b = np.floor(y / s)
        in_squares = (a >= -1) & (a <= self.columns - 1) & (b >= -1) & (b <= self.rows - 1)
        black = in_squares & ((a + b) % 2 == 0)
        in_paper = (x >= -s - margin) & (x <= self.columns * s + margin) & (y >= -s - margin) \
            & (y <= self.rows * s + margin)
        out = np.where(in_paper, WHITE, BACKGROUND).astype(np.int8)
        out[black] = BLACK
        return out

    def mesh(self) -> Mesh:
        """The printed squares as a triangle mesh in the board frame (Z = 0), black and white vertex colours.

        Four vertices per square (so each square has one flat colour), two triangles each.
        """
        s = self.square_size
        grid_a, grid_b = np.meshgrid(np.arange(-1, self.columns), np.arange(-1, self.rows), indexing="xy")
        a, b = grid_a.ravel(), grid_b.ravel()
        x0, y0 = a * s, b * s
        corners = np.stack([np.stack([x0, y0], 1), np.stack([x0 + s, y0], 1), np.stack([x0 + s, y0 + s], 1),
                            np.stack([x0, y0 + s], 1)], axis=1)  # (S, 4, 2)
        vertices = np.concatenate([corners.reshape(-1, 2), np.zeros((corners.size // 2, 1))], axis=1)
        base = 4 * np.arange(len(a))[:, None]
        faces = np.concatenate([base + np.array([0, 1, 2]), base + np.array([0, 2, 3])], axis=0)
        shade = np.where((a + b) % 2 == 0, 0.05, 0.95)
        colors = np.repeat(np.repeat(shade[:, None], 3, axis=1), 4, axis=0)
        return Mesh(vertices, faces, colors)

    def paper_outline(self, per_edge: int = 25) -> np.ndarray:
        """``(4 per_edge, 3)`` points along the edge of the paper (the squares and a one-square margin)."""
        s = self.square_size
        x0, x1, y0, y1 = -2 * s, (self.columns + 1) * s, -2 * s, (self.rows + 1) * s
        edge = np.linspace(0.0, 1.0, per_edge)
        xs, ys = x0 + (x1 - x0) * edge, y0 + (y1 - y0) * edge
        outline = np.concatenate([np.stack([xs, np.full_like(xs, y0)], 1),
                                  np.stack([xs, np.full_like(xs, y1)], 1),
                                  np.stack([np.full_like(ys, x0), ys], 1),
                                  np.stack([np.full_like(ys, x1), ys], 1)])
        return np.concatenate([outline, np.zeros((len(outline), 1))], axis=1)


__all__ = ["BACKGROUND", "BLACK", "WHITE", "Checkerboard"]
