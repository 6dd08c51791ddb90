"""lab.modules.nerf's datasets: the synthetic object (white background, exact depth inside the bounds) and
the NeRF-synthetic layout read back through the one transforms.json reader, with its errors."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from lab.core import Cameras, InvalidValue
from lab.data.scenes import render
from lab.data.transforms_json import camera_to_world_opengl
from lab.modules import nerf as N


@pytest.fixture(scope="module")
def small():
    return N.PIPELINE.dataset("synthetic_object").load({"train_views": 3, "test_views": 2})


def test_synthetic_object_state_and_truth(small):
    state, truth = small.state, small.truth
    assert len(state["images"]) == 3 and len(state["cameras"]) == 3 and len(state["test_cameras"]) == 2
    assert state["cameras"].image == "images"
    assert (state["cameras"].width, state["cameras"].height) == (100, 100)
    assert truth["test_images"].shape == (2, 100, 100, 3) and truth["test_depths"].shape == (2, 100, 100)
    for image in state["images"].images:
        assert image.pixels.shape == (100, 100, 3)
        np.testing.assert_array_equal(image.pixels[0, 0], [1.0, 1.0, 1.0])  # white background
    seen = np.isfinite(truth["test_depths"])
    assert 0.05 < seen.mean() < 0.8  # an object in the middle, background around it
    near_object = np.stack([cv2.dilate(m.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0 for m in seen])
    np.testing.assert_array_equal(truth["test_images"][~near_object], 1.0)  # edges mix supersamples


def test_held_out_views_differ_from_training_views(small):
    train, test = small.state["cameras"], small.state["test_cameras"]
    gaps = np.linalg.norm(train.centers[:, None] - test.centers[None], axis=-1)
    assert gaps.min() > 0.1


def test_every_surface_seen_lies_inside_the_bounds(small):
    """Rays of the training pixels reach the object at the renderer's exact depth, inside [near, far] and
    inside the ball that normalizes positions."""
    bounds, cameras = small.state["bounds"], small.state["cameras"]
    origins, directions = N.cameras_rays(cameras)
    for v, depth in enumerate(small.truth["train_depths"]):
        hit = np.isfinite(depth.reshape(-1))
        z = depth.reshape(-1)[hit]
        assert z.min() > bounds.near and z.max() < bounds.far
        points = origins[v].double().numpy()[hit] + z[:, None] * directions[v].double().numpy()[hit]
        assert np.linalg.norm(points - bounds.center, axis=1).max() < bounds.radius


def test_synthetic_object_is_deterministic():
    a = N.synthetic_object(train_views=2, test_views=1)
    b = N.synthetic_object(train_views=2, test_views=1)
    np.testing.assert_array_equal(a.state["images"][1].pixels, b.state["images"][1].pixels)


# --- the NeRF-synthetic layout ----------------------------------------------------------------------------
def _write_split(folder, split: str, cameras: Cameras, scene, *, names=None) -> list[np.ndarray]:
    """Render ``cameras`` and write them as RGBA PNGs with a transforms file that, like the Blender scenes,
    gives only ``camera_angle_x`` (no image size) and file paths without an ending. Returns the images as
    read back composited on white."""
    (folder / split).mkdir(exist_ok=True)
    c2w = camera_to_world_opengl(cameras.R, cameras.t)
    frames, expected = [], []
    for i in range(len(cameras)):
        view = render(scene, cameras, i)
        name = f"./{split}/r_{i}" if names is None else names[i]
        rgba = np.dstack([view.image.pixels[:, :, ::-1], view.mask.astype(np.float32)])
        cv2.imwrite(str(folder / f"{split}/r_{i}.png"), np.round(rgba * 255).astype(np.uint8))
        quantized = np.round(view.image.pixels * 255) / 255
        expected.append(np.where(view.mask[:, :, None], quantized, 1.0).astype(np.float32))
        frames.append({"file_path": name, "rotation": 0.012566, "transform_matrix": c2w[i].tolist()})
    angle = 2.0 * math.atan(0.5 * cameras.width / cameras.K[0, 0, 0])
    (folder / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    return expected


@pytest.fixture(scope="module")
def blender_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lego")
    scene = N.object_scene()
    train = N.hemisphere_cameras(3, size=40, distance=3.0, offset=0.0, center=np.zeros(3))
    test = N.hemisphere_cameras(2, size=40, distance=3.0, offset=0.5, center=np.zeros(3))
    train_images = _write_split(folder, "train", train, scene)
    return folder, train, test, train_images, _write_split(folder, "test", test, scene)


def test_nerf_synthetic_reads_cameras_and_composites_on_white(blender_folder):
    folder, train, test, train_images, test_images = blender_folder
    loaded = N.nerf_synthetic(path=str(folder), downscale=1, near=2.0, far=4.0)
    cameras = loaded.state["cameras"]
    np.testing.assert_allclose(cameras.K, train.K, atol=1e-9)  # the centre-origin principal point survives
    np.testing.assert_allclose(cameras.R, train.R, atol=1e-9)
    np.testing.assert_allclose(cameras.t, train.t, atol=1e-9)
    np.testing.assert_allclose(loaded.state["test_cameras"].t, test.t, atol=1e-9)
    for got, want in zip(loaded.state["images"].images, train_images, strict=True):
        np.testing.assert_allclose(got.pixels, want, atol=1e-6)
    np.testing.assert_allclose(loaded.truth["test_images"], np.stack(test_images), atol=1e-6)
    assert loaded.state["bounds"].near == 2.0 and loaded.state["bounds"].far == 4.0


def test_nerf_synthetic_downscale_keeps_the_rays_of_pixel_centres(blender_folder):
    folder, train, _, train_images, _ = blender_folder
    loaded = N.nerf_synthetic(path=str(folder), downscale=2, train_views=2, test_views=1)
    cameras = loaded.state["cameras"]
    assert (cameras.width, cameras.height) == (20, 20) and len(cameras) == 2
    np.testing.assert_allclose(cameras.K, N.scaled_cameras(train, 0.5).K[:2], atol=1e-9)
    np.testing.assert_allclose(loaded.state["images"][0].pixels,
                               cv2.resize(train_images[0], (20, 20), interpolation=cv2.INTER_AREA), atol=1e-6)


def test_nerf_synthetic_errors_name_the_problem(tmp_path, blender_folder):
    folder, train, test, _, _ = blender_folder
    with pytest.raises(InvalidValue, match=r"transforms_train\.json") as info:
        N.nerf_synthetic(path=str(tmp_path))
    assert info.value.field == "path"
    scene = N.object_scene()
    broken = tmp_path / "broken"
    broken.mkdir()
    _write_split(broken, "train", train, scene, names=["./train/r_0", "./train/missing", "./train/r_2"])
    _write_split(broken, "test", test, scene)
    with pytest.raises(InvalidValue, match="missing") as info:
        N.nerf_synthetic(path=str(broken), downscale=1)
    assert info.value.field == "transforms_train.json frames[1]"
    # an image of another size than the rest
    _write_split(broken, "train", train, scene)
    cv2.imwrite(str(broken / "train/r_2.png"), np.zeros((30, 40, 4), np.uint8))
    with pytest.raises(InvalidValue, match="30") as info:
        N.nerf_synthetic(path=str(broken), downscale=1)
    assert info.value.field == "transforms_train.json frames[2]"
    # no frames at all, a NaN pose
    data = json.loads((broken / "transforms_test.json").read_text())
    (broken / "transforms_test.json").write_text(json.dumps({**data, "frames": []}))
    with pytest.raises(InvalidValue, match="no 'frames'") as info:
        N.nerf_synthetic(path=str(broken), downscale=1, train_views=2)
    assert info.value.field == "frames"
    data["frames"][1]["transform_matrix"][0][3] = float("nan")
    (broken / "transforms_test.json").write_text(json.dumps(data))
    with pytest.raises(InvalidValue, match="finite") as info:
        N.nerf_synthetic(path=str(broken), downscale=1, train_views=2)
    assert info.value.field == "frames[1]"
    _write_split(broken, "train", train, scene)
    with pytest.raises(InvalidValue, match="divide") as info:
        N.nerf_synthetic(path=str(folder), downscale=3)
    assert info.value.field == "downscale"


def test_written_untuned_scene_reads_back_as_the_renderer_supersampled_it(tmp_path):
    """write_nerf_synthetic's folder through nerf_synthetic: the poses it rendered, and at downscale 2 each
    pixel is the renderer's 2 x 2 supersampled pixel (8-bit PNGs: within 2 levels where the object covers
    the whole block, the mean of the blocks about edges within the quantization too)."""
    from lab.modules.nerf.datasets import BLENDER_DISTANCE, untuned_scene, write_nerf_synthetic

    scene = untuned_scene(0)
    folder = write_nerf_synthetic(str(tmp_path / "untuned"), scene, size=48, views=(3, 1, 2))
    loaded = N.nerf_synthetic(path=folder, downscale=2)
    train = N.hemisphere_cameras(3, size=24, distance=BLENDER_DISTANCE, offset=0.0, center=np.zeros(3))
    cameras = loaded.state["cameras"]
    assert len(cameras) == 3 and len(loaded.truth["test_images"]) == 2
    assert np.allclose(cameras.R, train.R, atol=1e-6) and np.allclose(cameras.t, train.t, atol=1e-6)
    assert np.allclose(cameras.K, train.K, atol=1e-6)
    lower, upper = scene.bounds()
    assert np.linalg.norm(np.maximum(np.abs(lower), np.abs(upper))) < 1.5   # the Blender scenes' radius
    for i in range(3):
        expected = render(scene, train, i, supersample=2).image.pixels
        read = loaded.state["images"].images[i].pixels
        assert np.abs(read - expected).max() < 2.5 / 255
    assert not np.allclose(loaded.state["images"].images[0].pixels, 1.0)    # the object is in view


def test_held_out_rays_sample_each_pixel_as_the_dataset_made_it(small):
    """The synthetic object's pixels are 2 x 2 supersampled (``pixel_supersample``), and render_held_out's
    default takes that factor: the exact scene rendered one ray per pixel at twice the resolution
    (scaled_cameras, the rays render_held_out casts) and box-filtered is the truth itself, where one ray
    through each pixel centre is not (about 30 dB)."""
    from lab.modules.nerf.model import ImageRendering
    from lab.modules.nerf.steps import held_out_supersample

    state, truth = small.state, small.truth
    factor = held_out_supersample(0, state["pixel_supersample"])
    assert state["pixel_supersample"] == factor == 2
    scene = N.object_scene(0)
    fine = N.scaled_cameras(state["test_cameras"], factor)
    for i in range(2):
        rendered = render(scene, fine, i, supersample=1)
        pixels = ImageRendering(rendered.image.pixels, rendered.depth, rendered.mask.astype(np.float32))
        area = pixels.box_filtered(factor).color
        np.testing.assert_allclose(area, truth["test_images"][i], atol=2e-6)
        centres = render(scene, state["test_cameras"], i, supersample=1).image.pixels
        assert N.image_psnr(centres, truth["test_images"][i]) < 33.0


def test_held_out_supersampling_follows_the_dataset_unless_told(blender_folder):
    from lab.modules.nerf.steps import MAX_HELD_OUT_SUPERSAMPLE, held_out_supersample

    folder = str(blender_folder[0])
    assert N.nerf_synthetic(path=folder, downscale=2).state["pixel_supersample"] == 2
    assert N.nerf_synthetic(path=folder, downscale=1).state["pixel_supersample"] == 1
    assert held_out_supersample(0, None) == 1                     # a dataset that does not say: centres
    assert held_out_supersample(0, 3) == 3 and held_out_supersample(1, 3) == 1
    assert held_out_supersample(2, None) == 2
    assert held_out_supersample(0, 8) == MAX_HELD_OUT_SUPERSAMPLE == 4
    for bad in (0, -2, 1.5, True):
        with pytest.raises(InvalidValue) as info:
            held_out_supersample(0, bad)
        assert info.value.field == "pixel_supersample"
