"""Paths and helpers shared by the lesson tests (imported by name: conftest modules are not importable safely)."""

from __future__ import annotations

import sys
from pathlib import Path

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
SUBMISSIONS = FIXTURES / "submissions"
REPO = Path(__file__).resolve().parents[2]

if str(FIXTURES) not in sys.path:  # the toy lesson's module "toy_lesson_pipeline:PIPELINE"
    sys.path.insert(0, str(FIXTURES))


def submission(*parts: str) -> str:
    """The text of a fixture submission, e.g. ``submission("toy", "solution.py")``."""
    return SUBMISSIONS.joinpath(*parts).read_text(encoding="utf-8")
