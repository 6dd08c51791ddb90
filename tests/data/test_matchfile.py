"""lab.data.matchfile: the course's matching<i>.txt files -> keypoints, colours, matches, tracks."""

import numpy as np
import pytest

from lab.core import InvalidValue
from lab.data.matchfile import MatchFiles, read_match_files

# Three images. Feature A: seen in 1, 2, 3. Feature B: in 1 and 3. Feature C: in 2 and 3 (listed in
# matching2.txt). Feature A again from image 2's side (2 -> 3), the same pixels: no new keypoint.
MATCHING1 = """nFeatures: 2
3 10 20 30 100.5 200.25 2 110.0 205.0 3 120.0 210.0
2 40 50 60 300.0 50.0 3 310.0 55.0
"""
MATCHING2 = """nFeatures: 2
2 10 20 30 110.0 205.0 3 120.0 210.0
2 70 80 90 400.0 60.0 3 405.0 66.5
"""


def _write(tmp_path, files):
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    return tmp_path


def test_smoke_and_types(tmp_path):
    data = read_match_files(_write(tmp_path, {"matching1.txt": MATCHING1, "matching2.txt": MATCHING2}))
    assert isinstance(data, MatchFiles)
    assert data.num_images == 3
    assert all(k.dtype == np.float64 and k.shape[1] == 2 for k in data.keypoints)
    assert all(c.dtype == np.uint8 and c.shape[1] == 3 for c in data.colors)
    assert all(t.dtype == np.int64 and t.shape[1] == 2 for t in data.tracks)
    assert [p.rsplit("/", 1)[-1] for p in data.sources] == ["matching1.txt", "matching2.txt"]


def test_known_answer(tmp_path):
    data = read_match_files(_write(tmp_path, {"matching1.txt": MATCHING1, "matching2.txt": MATCHING2}))
    np.testing.assert_array_equal(data.keypoints[0], [[100.5, 200.25], [300.0, 50.0]])
    np.testing.assert_array_equal(data.keypoints[1], [[110.0, 205.0], [400.0, 60.0]])
    np.testing.assert_array_equal(data.keypoints[2], [[120.0, 210.0], [310.0, 55.0], [405.0, 66.5]])
    np.testing.assert_array_equal(data.colors[2], [[10, 20, 30], [40, 50, 60], [70, 80, 90]])
    assert sorted(data.matches) == [(0, 1), (0, 2), (1, 2)]
    np.testing.assert_array_equal(data.matches[(0, 1)], [[0, 0]])
    np.testing.assert_array_equal(data.matches[(0, 2)], [[0, 0], [1, 1]])
    np.testing.assert_array_equal(data.matches[(1, 2)], [[0, 0], [1, 2]])  # A listed twice, kept once
    tracks = sorted(map(lambda t: t.tolist(), data.tracks))
    assert tracks == [[[0, 0], [1, 0], [2, 0]], [[0, 1], [2, 1]], [[1, 1], [2, 2]]]
    assert data.inconsistent_tracks == 0


def test_file_order_and_list_input_do_not_matter(tmp_path):
    folder = _write(tmp_path, {"matching1.txt": MATCHING1, "matching2.txt": MATCHING2})
    a = read_match_files(folder)
    b = read_match_files([folder / "matching2.txt", folder / "matching1.txt"])
    assert all(np.array_equal(x, y) for x, y in zip(a.keypoints, b.keypoints, strict=True))
    assert [t.tolist() for t in a.tracks] == [t.tolist() for t in b.tracks]


def test_num_images_adds_unseen_images(tmp_path):
    data = read_match_files(_write(tmp_path, {"matching1.txt": MATCHING1}), num_images=5)
    assert data.num_images == 5
    assert data.keypoints[4].shape == (0, 2)


def test_inconsistent_tracks_are_dropped_and_counted(tmp_path):
    text = """nFeatures: 2
2 1 2 3 10.0 10.0 2 50.0 50.0
2 1 2 3 20.0 20.0 2 50.0 50.0
"""  # two different features of image 1 both match the same pixel of image 2
    data = read_match_files(_write(tmp_path, {"matching1.txt": text}))
    assert data.tracks == () and data.inconsistent_tracks == 1
    np.testing.assert_array_equal(data.matches[(0, 1)], [[0, 0], [1, 0]])


@pytest.mark.parametrize("text, line, message", [
    ("nFeature 2\n", 1, "nFeatures: N"),
    ("", 1, "empty"),
    ("nFeatures: 1\n2 1 2 3 10 10 2 5\n", 2, "has 9 numbers"),
    ("nFeatures: 1\n1 1 2 300 10 10\n", 2, r"\[0, 255\]"),
    ("nFeatures: 1\nx 1 2 3 10 10\n", 2, "expected 'm R G B u v'"),
    ("nFeatures: 1\n2 1 2 3 10 10 0 5 5\n", 2, "1-based"),
    ("nFeatures: 1\n2 1 2 3 10 10 1 5 5\n", 2, "itself"),
    ("nFeatures: 1\n2 1 2 3 10 10 2 nan 5\n", 2, "finite"),
    ("nFeatures: 2\n1 1 2 3 10 10\n", 2, "announces 2 features but the file has 1"),
    ("nFeatures: 1\n1 1 2 3 10 10\n\n1 1 2 3 11 10\n", 4, "more feature rows"),
])
def test_malformed_file_names_file_and_line(tmp_path, text, line, message):
    _write(tmp_path, {"matching1.txt": text})
    with pytest.raises(InvalidValue, match=message) as info:
        read_match_files(tmp_path / "matching1.txt")
    assert info.value.field == f"matching1.txt:{line}"
    assert f"line {line}" in info.value.reason


def test_match_beyond_num_images_names_the_line(tmp_path):
    _write(tmp_path, {"matching1.txt": "nFeatures: 2\n1 1 2 3 5 5\n2 1 2 3 10 10 4 5 5\n"})
    with pytest.raises(InvalidValue, match="beyond the 3 images") as info:
        read_match_files(tmp_path, num_images=3)
    assert info.value.field == "matching1.txt:3"


def test_bad_names_and_missing_files(tmp_path):
    (tmp_path / "matches.txt").write_text(MATCHING1)
    with pytest.raises(InvalidValue, match=r"matching<i>\.txt"):
        read_match_files(tmp_path / "matches.txt")
    with pytest.raises(InvalidValue, match="no matching"):
        read_match_files(tmp_path)
    with pytest.raises(InvalidValue, match="no such file"):
        read_match_files([tmp_path / "matching3.txt"])
