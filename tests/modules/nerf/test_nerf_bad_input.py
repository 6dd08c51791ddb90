"""Bad input to the NeRF module gets a clear error naming the problem (a LabError with its field), through
the steps and through a session: near >= far, a time budget too small for one training step, NaN poses,
views that do not fit their cameras, a transforms file without frames or with a missing image, an image of
another size. Cancelling training keeps the model trained so far. (The loaders' own checks are in
test_nerf_datasets.py; this file is what a user meets through the pipeline.)"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from lab.core import Cameras, Cancelled, InvalidControl, InvalidValue, LabError, open_session
from lab.data.transforms_json import camera_to_world_opengl
from lab.modules import nerf as N
from lab.modules.nerf import PIPELINE

torch.set_num_threads(1)

TINY = {"samples": 8, "hidden": 16, "layers": 2, "batch_rays": 128, "iterations": 30, "preview_every": 10}


@pytest.fixture(scope="module")
def session():
    session = open_session(PIPELINE, "synthetic_object", {"train_views": 2, "test_views": 1}, seed=1)
    session.run("generate_rays")
    session.run("encode_positions")
    return session


def _blender_folder(folder, cameras: Cameras, *, size: int = 16) -> None:
    """A NeRF-synthetic folder whose train and test splits both hold ``cameras``' views (grey RGBA)."""
    c2w = camera_to_world_opengl(cameras.R, cameras.t)
    (folder / "train").mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(len(cameras)):
        cv2.imwrite(str(folder / f"train/r_{i}.png"), np.full((size, size, 4), 128, np.uint8))
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": c2w[i].tolist()})
    angle = 2.0 * np.arctan(0.5 * cameras.width / cameras.K[0, 0, 0])
    for split in ("train", "test"):
        data = {"camera_angle_x": angle, "frames": frames}
        (folder / f"transforms_{split}.json").write_text(json.dumps(data))


def _rewrite(folder, split: str, change) -> None:
    file = folder / f"transforms_{split}.json"
    data = json.loads(file.read_text())
    change(data)
    file.write_text(json.dumps(data))


def test_near_not_before_far_is_refused_naming_it():
    with pytest.raises(InvalidValue, match=r"near \(3\) must be less than far \(3\)") as info:
        N.SceneBounds(3.0, 3.0, np.zeros(3), 1.0)
    assert info.value.field == "bounds"
    with pytest.raises(InvalidValue, match="near"):
        N.stratified_samples(4.0, 2.0, 1, 8)


def test_near_not_before_far_in_a_dataset_is_refused_before_anything_runs(tmp_path):
    cameras = N.hemisphere_cameras(2, size=16, distance=3.0, offset=0.0, center=np.zeros(3))
    _blender_folder(tmp_path, cameras)
    with pytest.raises(LabError, match="less than far") as info:
        open_session(PIPELINE, "nerf_synthetic", {"path": str(tmp_path), "downscale": 1, "near": 6.0,
                                                  "far": 2.0})
    assert info.value.field in {"bounds", "near"}


def test_a_transforms_file_without_frames_or_with_a_missing_image_or_size(tmp_path):
    cameras = N.hemisphere_cameras(3, size=16, distance=3.0, offset=0.0, center=np.zeros(3))
    _blender_folder(tmp_path, cameras)
    open_session(PIPELINE, "nerf_synthetic", {"path": str(tmp_path), "downscale": 1})  # the good folder loads
    (tmp_path / "train/r_1.png").unlink()
    with pytest.raises(LabError, match="missing") as info:
        open_session(PIPELINE, "nerf_synthetic", {"path": str(tmp_path), "downscale": 1})
    assert "frames[1]" in info.value.field
    cv2.imwrite(str(tmp_path / "train/r_1.png"), np.full((12, 16, 4), 128, np.uint8))
    with pytest.raises(LabError, match="12") as info:
        open_session(PIPELINE, "nerf_synthetic", {"path": str(tmp_path), "downscale": 1})
    assert "frames[1]" in info.value.field
    _rewrite(tmp_path, "train", lambda data: data.update(frames=[]))
    with pytest.raises(LabError, match="frames"):
        open_session(PIPELINE, "nerf_synthetic", {"path": str(tmp_path), "downscale": 1})


def test_a_nan_pose_is_refused_naming_the_frame(tmp_path):
    cameras = N.hemisphere_cameras(2, size=16, distance=3.0, offset=0.0, center=np.zeros(3))
    _blender_folder(tmp_path, cameras)

    def poison(data):
        data["frames"][1]["transform_matrix"][1][3] = float("nan")

    _rewrite(tmp_path, "train", poison)
    with pytest.raises(LabError, match="finite") as info:
        open_session(PIPELINE, "nerf_synthetic", {"path": str(tmp_path), "downscale": 1})
    assert "frames[1]" in info.value.field


def test_nan_poses_never_reach_the_steps(session):
    cameras = session.state["cameras"]
    t = cameras.t.copy()
    t[1, 2] = np.nan
    with pytest.raises(InvalidValue, match="NaN") as info:  # the lab's Cameras refuse them
        Cameras(cameras.K, cameras.R, t, cameras.width, cameras.height, image="images")
    assert info.value.field == "t"


def test_a_budget_too_small_for_one_step_is_refused_naming_the_control(session):
    with pytest.raises(InvalidControl, match="ran out during the first training step") as info:
        session.run("train_nerf", {**TINY, "budget_seconds": 1e-9})
    assert info.value.field == "budget_seconds"
    assert "model" not in session.state and session.history[-1].status == "failed"


@pytest.mark.parametrize("method", ["mlp", "grid"])
def test_cancelling_training_keeps_the_model_trained_so_far(session, method):
    state = session.state
    controls = {**TINY, "method": method, "grid_resolution": 16, "iterations": 1000, "budget_seconds": 0.0}
    generator = N.train_nerf(state["rays"], state["encoding"], state["cameras"], **controls,
                             rng=np.random.default_rng(0))
    assert [next(generator).iteration for _ in range(2)] == [10, 20]
    with pytest.raises(StopIteration) as stop:  # what the runner does on Cancel: Cancelled thrown in
        generator.throw(Cancelled("train_nerf", "cancelled by the user"))
    result = stop.value.value
    assert result.iterations == 20 and "stopped after 20 of 1000 iterations" in result.warnings[0]
    assert isinstance(result.model, N.GridCheckpoint if method == "grid" else N.NerfCheckpoint)
    held_out = N.render_held_out(result.model, state["test_cameras"])  # the kept model renders
    assert held_out.test_renders[0].pixels.shape == (100, 100, 3)


def test_cancel_in_a_session_keeps_the_model_and_says_so(session):
    fork = session.fork()
    seen = []

    def cancel_at_the_second_report(step, progress):
        seen.append(progress.iteration)
        if len(seen) == 2:
            fork.cancel()

    record = fork.run("train_nerf", {**TINY, "method": "grid", "grid_resolution": 16, "iterations": 1000,
                                     "budget_seconds": 0.0}, on_progress=cancel_at_the_second_report)
    assert seen == [10, 20] and record.status == "ok"  # asked while report 20 shows, it stops at the next
    assert record.metrics["iterations"] == 30 and "the model trained so far is kept" in record.warnings[0]
    assert isinstance(fork.state["model"], N.GridCheckpoint)
    fork.run("render_held_out")  # and the rest of the pipeline runs on it
