"""The classic course format of feature matches (``matching1.txt``, ``matching2.txt``, ...).

File ``matching<i>.txt`` lists the features of image ``i`` (1-based) that were matched in other
images::

    nFeatures: 3930
    3 137 128 105 454.74 392.37 2 308.57 500.32 4 447.58 479.36
    ...

Each row after the header is one feature: ``m`` (the number of images the feature is seen in,
this one included), its colour ``R G B``, its pixel ``u v`` in image ``i``, then ``m - 1`` triples
``(image id, u, v)``: where it is seen in the other images (ids 1-based; usually only images with
a larger id). Pixels are taken as they are, in the lab's convention (pixel (0, 0) is the centre
of the top-left pixel).

:func:`read_match_files` turns a set of such files into per-image keypoints (every distinct pixel
seen in an image becomes one keypoint), their colours, pairwise matches and tracks: the connected
components of the match graph over all (image, keypoint) observations (union-find; here
``scipy.sparse.csgraph.connected_components``), dropping components that see one image twice
(inconsistent matches).
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import connected_components

from lab.core.errors import InvalidValue

_NAME = re.compile(r"matching(\d+)\.txt$")
_HEADER = re.compile(r"^\s*nFeatures\s*:\s*(\d+)\s*$")


@dataclass(frozen=True, eq=False)
class MatchFiles:
    """What a set of match files holds, indexed from 0.

    ``keypoints``: per image ``(K_i, 2)`` float64 pixels; ``colors``: per image ``(K_i, 3)`` uint8
    RGB; ``matches``: ``{(i, j): (L, 2) int64}`` for ``i < j``, rows ``(keypoint in i, keypoint in
    j)``; ``tracks``: ``(L_t, 2)`` int64 rows ``(image, keypoint)``, one image at most once per
    track, sorted by image; ``inconsistent_tracks``: components dropped because they see an image
    twice; ``sources``: the files read, in order.
    """

    keypoints: tuple[np.ndarray, ...]
    colors: tuple[np.ndarray, ...]
    matches: dict[tuple[int, int], np.ndarray]
    tracks: tuple[np.ndarray, ...]
    inconsistent_tracks: int
    sources: tuple[str, ...]

    @property
    def num_images(self) -> int:
        return len(self.keypoints)


def _error(path: Path, line: int, reason: str) -> InvalidValue:
    return InvalidValue(f"{path.name}:{line}", f"{path} line {line}: {reason}")


def _files(source: str | Path | Iterable[str | Path]) -> list[tuple[int, Path]]:
    if isinstance(source, (str, Path)) and Path(source).is_dir():
        paths = [p for p in Path(source).iterdir() if _NAME.search(p.name)]
        if not paths:
            raise InvalidValue("folder", f"no matching<i>.txt files in {str(source)!r}")
    elif isinstance(source, (str, Path)):
        paths = [Path(source)]
    else:
        paths = [Path(p) for p in source]
    out = []
    for path in paths:
        found = _NAME.search(path.name)
        if not found or int(found.group(1)) < 1:
            raise InvalidValue("path",
                               f"{str(path)!r} is not named matching<i>.txt (i >= 1, the image it is about)")
        if not path.is_file():
            raise InvalidValue("path", f"no such file: {str(path)!r}")
        out.append((int(found.group(1)) - 1, path))
    indices = [i for i, _ in out]
    if len(set(indices)) != len(indices):
        raise InvalidValue("path", "two match files are about the same image")
    return sorted(out)


def _parse(path: Path, image: int) -> list[tuple[tuple[int, int, int], list[tuple[int, float, float]]]]:
    """Rows of one file: (colour, [(image, u, v), ...] starting with this image's own pixel)."""
    lines = path.read_text().splitlines()
    header = _HEADER.match(lines[0]) if lines else None
    if header is None:
        raise _error(path, 1, f"the first line must be 'nFeatures: N', got {lines[0][:40]!r}" if lines
                     else "the file is empty; the first line must be 'nFeatures: N'")
    expected = int(header.group(1))
    rows: list[tuple[tuple[int, int, int], list[tuple[int, float, float]]]] = []
    for number, line in enumerate(lines[1:], start=2):
        fields = line.split()
        if not fields:
            continue
        if len(rows) == expected:
            raise _error(path, number, f"more feature rows than the {expected} that nFeatures announces")
        try:
            count = int(fields[0])
            colour = (int(fields[1]), int(fields[2]), int(fields[3]))
            u, v = float(fields[4]), float(fields[5])
        except (ValueError, IndexError):
            raise _error(path, number, "expected 'm R G B u v' then (image id, u, v) per match") from None
        if count < 1:
            raise _error(path, number, f"the number of matches must be at least 1 (this image), got {count}")
        if len(fields) != 6 + 3 * (count - 1):
            raise _error(path, number, f"a feature seen in {count} images has {6 + 3 * (count - 1)} numbers "
                                       f"(m R G B u v and {count - 1} triples), got {len(fields)}")
        if len(colour) != 3 or any(c < 0 or c > 255 for c in colour):
            raise _error(path, number, f"colour {colour} must be three integers in [0, 255]")
        observations = [(image, u, v)]
        try:
            for k in range(6, len(fields), 3):
                observations.append((int(fields[k]) - 1, float(fields[k + 1]), float(fields[k + 2])))
        except ValueError:
            raise _error(path, number, "a match must be an integer image id and two numbers u v") from None
        for other, mu, mv in observations:
            if not (np.isfinite(mu) and np.isfinite(mv)):
                raise _error(path, number, "pixels must be finite numbers")
            if other < 0:
                raise _error(path, number, f"image ids are 1-based, got {other + 1}")
        if any(other == image for other, _, _ in observations[1:]):
            raise _error(path, number,
                         f"a feature of image {image + 1} cannot match image {image + 1} itself")
        rows.append((colour, observations))
    if len(rows) != expected:
        raise _error(path, len(lines),
                     f"nFeatures announces {expected} features but the file has {len(rows)}")
    return rows


def read_match_files(source: str | Path | Iterable[str | Path], *,
                     num_images: int | None = None) -> MatchFiles:
    """Read ``matching<i>.txt`` files (a folder of them, one file, or a list) into keypoints, matches and
    tracks.

    Args:
        source: a folder (every ``matching<i>.txt`` in it), one file or a list of files; the
            number in each name is the (1-based) image the file is about.
        num_images: how many images there are (default: the largest image id seen, in a file
            name or a match); a match to an image beyond it is an error.

    Returns a :class:`MatchFiles`. Raises :class:`InvalidValue` naming the file and line of a
    malformed row (wrong header, wrong number of fields, colour outside [0, 255], image id 0 or
    beyond ``num_images``, a feature matched to its own image, a row count that disagrees with
    ``nFeatures``).
    """
    files = _files(source)
    parsed = [(image, path, _parse(path, image)) for image, path in files]
    largest = max([image for image, _, _ in parsed]
                  + [other for _, _, rows in parsed for _, obs in rows for other, _, _ in obs])
    total = largest + 1 if num_images is None else int(num_images)
    if total < 1:
        raise InvalidValue("num_images", f"must be positive, got {num_images}")
    for image, path, _ in parsed:
        if image >= total:
            raise InvalidValue("num_images",
                               f"{path.name} is about image {image + 1} but there are {total} images")
    index: list[dict[tuple[float, float], int]] = [{} for _ in range(total)]
    colours: list[list[tuple[int, int, int]]] = [[] for _ in range(total)]
    edges: list[tuple[int, int, int, int]] = []  # (image a, keypoint a, image b, keypoint b)
    for _, path, rows in parsed:
        for row_number, (colour, observations) in enumerate(rows):
            ids = []
            for other, u, v in observations:
                if other >= total:
                    raise _error(path, _row_line(path, row_number), f"image id {other + 1} is beyond the "
                                                                    f"{total} images")
                key = (u, v)
                if key not in index[other]:
                    index[other][key] = len(index[other])
                    colours[other].append(colour)
                ids.append((other, index[other][key]))
            edges.extend((ids[0][0], ids[0][1], b, kb) for b, kb in ids[1:])
    keypoints = tuple(np.array(list(d), dtype=np.float64).reshape(-1, 2) for d in index)
    colors = tuple(np.array(c, dtype=np.uint8).reshape(-1, 3) for c in colours)

    pairs: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for a, ka, b, kb in edges:
        if a < b:
            pairs.setdefault((a, b), []).append((ka, kb))
        else:
            pairs.setdefault((b, a), []).append((kb, ka))
    matches = {pair: np.unique(np.array(rows, dtype=np.int64), axis=0)
               for pair, rows in sorted(pairs.items())}

    offsets = np.concatenate([[0], np.cumsum([len(k) for k in keypoints])])
    nodes = int(offsets[-1])
    tracks: list[np.ndarray] = []
    inconsistent = 0
    if edges:
        e = np.array(edges, dtype=np.int64)
        first, second = offsets[e[:, 0]] + e[:, 1], offsets[e[:, 2]] + e[:, 3]
        graph = scipy.sparse.coo_matrix((np.ones(len(e)), (first, second)), shape=(nodes, nodes))
        _, labels = connected_components(graph, directed=False)
        node_image = np.repeat(np.arange(total), np.diff(offsets))
        node_keypoint = np.arange(nodes) - offsets[node_image]
        order = np.argsort(labels, kind="stable")
        boundaries = np.flatnonzero(np.diff(labels[order])) + 1
        for members in np.split(order, boundaries):
            if len(members) < 2:
                continue
            images = node_image[members]
            if len(np.unique(images)) != len(images):
                inconsistent += 1
                continue
            sort = np.argsort(images, kind="stable")
            tracks.append(np.stack([images[sort], node_keypoint[members][sort]], axis=1).astype(np.int64))
    return MatchFiles(keypoints=keypoints, colors=colors, matches=matches, tracks=tuple(tracks),
                      inconsistent_tracks=inconsistent, sources=tuple(str(path) for _, path in files))


def _row_line(path: Path, row: int) -> int:
    """The line number of the ``row``-th feature row (0-based) of a file, for error messages."""
    seen = -1
    for number, line in enumerate(path.read_text().splitlines()[1:], start=2):
        if line.split():
            seen += 1
            if seen == row:
                return number
    return 1


__all__ = ["MatchFiles", "read_match_files"]
