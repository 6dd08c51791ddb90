"""Headless lesson runs and their HTML report (metrics, images, the saved 3D scene)."""

from __future__ import annotations

import json

import cv2
import numpy as np

from lab.lessons.report import run_lesson, write_report


def test_run_lesson_runs_every_step_on_the_first_check_dataset(toy_lesson):
    run = run_lesson(toy_lesson, seed=2)
    assert [r.step for r in run.records] == ["make_noisy", "mean_intensity", "normalize_means"]
    assert run.dataset == "gradients" and run.options == {"count": 3, "size": 16, "seed": 2} and not run.error
    assert run.records[0].params == {"sigma": 0.05}  # the dataset's step controls from tasks.toml
    again = run_lesson(toy_lesson, seed=2)
    assert again.session.state["means"].tolist() == run.session.state["means"].tolist()


def test_calibration_report_has_metrics_images_and_the_3d_scene(calibration_lesson, tmp_path):
    # the clean dataset: whole boards, every corner detected
    index = write_report(calibration_lesson, tmp_path / "report", dataset="clean", seed=1)
    page = index.read_text()
    assert "<h1>Camera calibration: homographies and intrinsics</h1>" in page
    for step in ("detect_corners", "estimate_homographies", "estimate_intrinsics", "refine_calibration"):
        assert f"<td>{step}</td>" in page
    assert "rms_px = " in page and "fx_rel_error = " in page
    assert "<details><summary>lesson.md</summary>" in page
    # the 3D scene: its poster at once (the interactive page is loaded under it when asked), and a link
    assert '<div id="scene" class="scene"><img src="scene.png"' in page and 'frame.src = "scene.html"' in page
    assert 'id="scene-load"' in page and '<a href="scene.html">' in page
    scene = (tmp_path / "report" / "scene.html").read_text()
    assert scene.lstrip().lower().startswith("<!doctype html") and len(scene) > 10_000
    poster = cv2.imread(str(tmp_path / "report" / "scene.png"))
    assert poster is not None and poster.shape[1] > poster.shape[0] and np.any(poster < 128)
    images = sorted(p.name for p in (tmp_path / "report" / "images").iterdir())
    assert "images_view_00.png" in images and "per_view_rms.png" in images
    assert (tmp_path / "report" / "images" / "images_view_00.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads((tmp_path / "report" / "report.json").read_text())
    assert summary["dataset"] == "synthetic" and summary["options"]["noise_px"] == 0.0
    assert summary["seed"] == 1
    assert summary["steps"][-2]["step"] == "refine_calibration"
    assert summary["steps"][-2]["metrics"]["rms_px"] > 0


def test_run_lesson_stops_at_the_first_failing_step_and_names_it(toy_lesson):
    import dataclasses

    def failing(noisy, *, scale=1):
        raise ValueError("broken")

    pipeline = toy_lesson.pipeline
    steps = tuple(dataclasses.replace(s, func=failing) if s.name == "mean_intensity" else s
                  for s in pipeline.steps)
    lesson = dataclasses.replace(toy_lesson)
    lesson.__dict__["pipeline"] = dataclasses.replace(pipeline, steps=steps)  # the cached property, replaced
    run = run_lesson(lesson, seed=2)
    assert [r.step for r in run.records] == ["make_noisy"]
    assert run.error == "step mean_intensity failed: ValueError: broken"
    assert "means" not in run.session.state and "unit_means" not in run.session.state
