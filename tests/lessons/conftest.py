"""Shared fixtures of the lesson tests: the toy lesson (fast) and the calibration lesson."""

from __future__ import annotations

import pytest

from lesson_helpers import FIXTURES, REPO


@pytest.fixture(scope="session")
def toy_lesson():
    from lab.lessons.format import load_lesson

    return load_lesson(FIXTURES / "lessons" / "00-toy")


@pytest.fixture(scope="session")
def calibration_lesson():
    from lab.lessons.format import load_lesson

    return load_lesson(REPO / "lessons" / "01-calibration")
