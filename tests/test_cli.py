"""The ``vision-lab`` CLI: run (JSON and table), --set/--option/--until/--dataset, export, modules, serve,
one-line errors with exit code 2, and the real console script in a subprocess.

Most tests run the CLI in-process with typer's CliRunner on small pipelines injected through
``lab.cli.lookup_pipeline``; one test runs the real calibration module end to end.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import types
from pathlib import Path
from typing import Annotated

import cv2
import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

import lab
import lab.cli as cli
from lab.core import Cameras, Export, ImageSet, Loaded, Pipeline, Range, UnknownName, Warnings, metric, step_result
from lab.core.codecs import image_from_cv2
from toy_pipeline import TOY, add_noise, gradients, lift, mean_intensity

runner = CliRunner()


# --- small pipelines for the CLI's cases -----------------------------------------------------------
def folder(*, path: str, pattern: str = "*.png") -> Loaded:
    """The images of a folder (or one image file)."""
    where = Path(path)
    files = sorted(where.glob(pattern)) if where.is_dir() else [where]
    if not files:
        raise FileNotFoundError(f"no {pattern} in {path}")
    return Loaded({"images": ImageSet(tuple(image_from_cv2(cv2.imread(str(f), cv2.IMREAD_UNCHANGED), name=f.name)
                                            for f in files))})


@step_result
class Checked:
    warnings: Warnings
    image_count: int = metric("images read")


def check_images(images: ImageSet, *, min_size: Annotated[int, Range(1, 100)] = 8) -> Checked:
    """Count the images; warn about the ones smaller than ``min_size`` pixels."""
    small = tuple(f"{im.name} is smaller than {min_size} px" for im in images.images
                  if min(im.pixels.shape[:2]) < min_size)
    return Checked(small, len(images))


def explode(noisy: ImageSet, *, fail: bool = True) -> Annotated[np.ndarray, "debris"]:
    """Fails on purpose (a step that raises on its input)."""
    if fail:
        raise ValueError("this input breaks the step")
    return np.zeros(3)


@step_result
class CameraFit:
    K: np.ndarray
    dist: np.ndarray
    cameras: Cameras
    rms_px: float = metric("reprojection RMS", unit="px")
    per_view_rms_px: list[float] = metric("RMS of each view", unit="px")


def fit_camera(images: ImageSet, *, focal: Annotated[float, Range(1.0, 1e4)] = 100.0) -> CameraFit:
    """A fake calibration: K from ``focal`` and the image size, a fixed distortion."""
    height, width = images[0].pixels.shape[:2]
    K = np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal * 1.01, (height - 1) / 2], [0.0, 0.0, 1.0]])
    dist = np.array([-0.1, 0.02, 0.001, -0.002, 0.0])
    cameras = Cameras(np.stack([K] * len(images)), np.stack([np.eye(3)] * len(images)),
                      np.zeros((len(images), 3)), width, height, dist=dist)
    return CameraFit(K, dist, cameras, 0.25, [0.2, 0.3][: len(images)])


FILES = Pipeline.build(name="files", title="Files", summary="Reads a folder.",
                       steps=[check_images, add_noise, explode], datasets=[gradients, folder])
def write_camera_yaml(state, metrics, out):
    """The fake calibration as OpenCV's YAML (a module declares its own formats: Pipeline.exports)."""
    from lab.data.exports import write_opencv_calibration

    cameras, fit = state["cameras"], metrics["fit_camera"]
    return write_opencv_calibration(out, state["K"], state["dist"], image_width=cameras.width,
                                    image_height=cameras.height, avg_reprojection_error=fit["rms_px"],
                                    per_view_reprojection_errors=fit["per_view_rms_px"])


CAMERA = Pipeline.build(name="camera", title="Camera", summary="A fake calibration.",
                        steps=[fit_camera], datasets=[gradients],
                        exports=[Export("opencv-yaml", "K and dist in OpenCV's YAML", ("K", "dist"), write_camera_yaml)])
PIPELINES = {"toy": TOY, "files": FILES, "camera": CAMERA}


@pytest.fixture(autouse=True)
def toy_registry(monkeypatch):
    """The CLI sees the test pipelines instead of the real modules."""
    def lookup(name: str) -> Pipeline:
        if name not in PIPELINES:
            raise UnknownName("module", f"no module {name!r}; modules are {list(PIPELINES)}")
        return PIPELINES[name]

    monkeypatch.setattr(cli, "lookup_pipeline", lookup)
    monkeypatch.setattr(cli, "module_names", lambda: tuple(PIPELINES))


def invoke(*args: str):
    return runner.invoke(cli.app, [str(a) for a in args], prog_name="vision-lab")


def run_json(*args: str) -> dict:
    result = invoke("run", *args, "--json")
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def assert_one_line_error(result, field: str) -> str:
    """Exit code 2, nothing on stdout, one line ``error: <field>: <reason>`` on stderr, no traceback."""
    assert result.exit_code == 2, result.output
    assert result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"error: {field}: "), lines[0]
    assert "Traceback" not in result.stderr
    return lines[0]


# --- run --json -----------------------------------------------------------------------------------
def test_run_json_is_one_object_with_every_step():
    result = invoke("run", "toy", "--json")
    assert result.exit_code == 0, result.output
    assert result.stderr == ""
    summary = json.loads(result.stdout)  # the whole of stdout is one JSON object
    assert set(summary) == {"module", "dataset", "steps", "metrics"}
    assert summary["module"] == "toy" and summary["dataset"] == "gradients"
    assert [s["name"] for s in summary["steps"]] == ["add_noise", "mean_intensity", "lift"]
    for step in summary["steps"]:
        assert set(step) == {"name", "seconds", "metrics", "warnings"}
        assert isinstance(step["seconds"], float) and step["seconds"] >= 0
        assert step["warnings"] == []
    merged = {k: v for s in summary["steps"] for k, v in s["metrics"].items()}
    assert summary["metrics"] == merged
    assert set(merged) == {"mean_abs_change", "means_abs_error", "final_loss"}
    assert merged["final_loss"] == pytest.approx(0.5 ** 5)  # lift halves the loss 5 times by default


def test_run_json_equals_python_api_with_the_same_seed():
    summary = run_json("toy", "--seed", "7", "-o", "count=2")
    session = lab.open_session(TOY, seed=7, count=2)
    for spec in TOY.steps:
        record = session.run(spec.name)
        assert summary["steps"][TOY.steps.index(spec)]["metrics"] == pytest.approx(record.metrics)


def test_run_is_reproducible_and_the_seed_matters():
    first, again = run_json("toy", "--seed", "1"), run_json("toy", "--seed", "1")
    other = run_json("toy", "--seed", "2")
    assert first["metrics"] == again["metrics"]
    assert first["metrics"]["mean_abs_change"] != other["metrics"]["mean_abs_change"]


def test_set_changes_controls():
    summary = run_json("toy", "--set", "add_noise.sigma=0", "--set", "lift.iterations=3")
    assert summary["metrics"]["mean_abs_change"] == 0.0
    assert summary["metrics"]["means_abs_error"] == pytest.approx(0.0, abs=1e-6)  # no noise: exact means
    assert summary["metrics"]["final_loss"] == pytest.approx(0.125)


def test_set_accepts_choices_and_the_last_value_wins():
    summary = run_json("toy", "-s", "add_noise.mode=uniform", "-s", "add_noise.sigma=0.5", "-s", "add_noise.sigma=0")
    assert summary["metrics"]["mean_abs_change"] == 0.0


def test_until_stops_after_the_step():
    summary = run_json("toy", "--until", "mean_intensity")
    assert [s["name"] for s in summary["steps"]] == ["add_noise", "mean_intensity"]
    assert "final_loss" not in summary["metrics"]
    assert [s["name"] for s in run_json("toy", "-u", "add_noise")["steps"]] == ["add_noise"]


def test_option_reaches_the_dataset(tmp_path):
    out = tmp_path / "means.npy"
    result = invoke("export", "toy", "--what", "means", "--format", "npy", "--out", out,
                    "--option", "count=2", "--set", "add_noise.sigma=0")
    assert result.exit_code == 0, result.output
    means = np.load(out)
    assert means.shape == (2,)
    np.testing.assert_allclose(means, [im.pixels.mean() for im in gradients(count=2).state["images"].images],
                               rtol=1e-6)


def test_dataset_path_picks_the_folder_dataset(tmp_path):
    for i, size in enumerate((16, 4, 12)):
        cv2.imwrite(str(tmp_path / f"im{i}.png"), np.full((size, size), 40 * i, np.uint8))
    summary = run_json("files", "--dataset", tmp_path, "--until", "check_images")
    assert summary["dataset"] == "folder"
    assert summary["metrics"]["image_count"] == 3
    assert summary["steps"][0]["warnings"] == ["im1.png is smaller than 8 px"]
    # --until plans by data flow: add_noise reads only the images, so check_images does not run before it
    assert [s["name"] for s in run_json("files", "--dataset", tmp_path, "--until", "add_noise")["steps"]] == \
        ["add_noise"]
    one_file = run_json("files", "--dataset", tmp_path / "im2.png", "--until", "check_images")
    assert one_file["metrics"]["image_count"] == 1
    named = run_json("files", "--dataset", "folder", "--option", f"path={tmp_path}", "--option", "pattern=im0*",
                     "--until", "check_images")
    assert named["metrics"]["image_count"] == 1


def test_warnings_go_to_stderr_and_into_the_summary(tmp_path):
    cv2.imwrite(str(tmp_path / "tiny.png"), np.zeros((3, 3), np.uint8))
    result = invoke("run", "files", "-d", tmp_path, "-u", "check_images", "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["steps"][0]["warnings"] == ["tiny.png is smaller than 8 px"]
    assert result.stderr.strip() == "warning: check_images: tiny.png is smaller than 8 px"
    table = invoke("run", "files", "-d", tmp_path, "-u", "check_images", "--set", "check_images.min_size=2")
    assert table.exit_code == 0 and table.stderr == ""


def test_run_prints_a_table_without_json():
    result = invoke("run", "toy", "--set", "lift.iterations=2")
    assert result.exit_code == 0, result.output
    for text in ("toy on gradients", "add_noise", "mean_intensity", "lift", "final_loss = 0.25", "seconds"):
        assert text in result.stdout
    with pytest.raises(json.JSONDecodeError):
        json.loads(result.stdout)
    assert result.stderr == ""  # no progress bar when stderr is not a terminal


def test_progress_bar_on_a_terminal_only_without_json(monkeypatch):
    monkeypatch.setattr(cli, "_stderr_is_terminal", lambda: True)
    result = invoke("run", "toy", "--set", "lift.iterations=4")
    assert result.exit_code == 0, result.output
    assert "lift" in result.stderr and "4/4" in result.stderr
    quiet = invoke("run", "toy", "--json")
    assert quiet.exit_code == 0 and quiet.stderr == ""


def test_json_keeps_stdout_clean_when_a_step_prints(monkeypatch):
    def noisy_lift(means: np.ndarray, *, iterations: int = 5):
        print("chatter from a step")
        return (yield from lift(means, iterations=iterations))

    chatty = Pipeline.build(name="chatty", title="", summary="", steps=[add_noise, mean_intensity, noisy_lift],
                            datasets=[gradients])
    monkeypatch.setitem(PIPELINES, "chatty", chatty)
    result = invoke("run", "chatty", "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["module"] == "chatty"
    assert "chatter from a step" in result.stderr


# --- one-line errors --------------------------------------------------------------------------------
@pytest.mark.parametrize(("args", "field"), [
    (["--set", "add_noise=3"], "--set"),
    (["--set", "add_noise.sigma"], "--set"),
    (["--set", ".sigma=1"], "--set"),
    (["--set", "no_such_step.sigma=1"], "step"),
    (["--set", "add_noise.no_such_control=1"], "add_noise.no_such_control"),
    (["--set", "add_noise.sigma=2"], "add_noise.sigma"),
    (["--set", "add_noise.sigma=abc"], "add_noise.sigma"),
    (["--set", "add_noise.mode=laplace"], "add_noise.mode"),
    (["--set", "lift.iterations=2.5"], "lift.iterations"),
    (["--until", "no_such_step"], "step"),
    (["--option", "count"], "--option"),
    (["--option", "count=99"], "--option count"),
    (["--option", "colour=red"], "--option colour"),
    (["--dataset", "no_such_dataset"], "dataset"),
    (["--dataset", "/no/such/folder"], "dataset"),
    (["--seed", "x"], "--seed"),
    (["--no-such-flag"], "--no-such-flag"),
])
def test_bad_arguments_are_one_line_and_exit_2(args, field):
    assert_one_line_error(invoke("run", "toy", *args, "--json"), field)


def test_unknown_module_names_the_modules():
    line = assert_one_line_error(invoke("run", "nope"), "module")
    assert "toy" in line


def test_a_dataset_that_reads_no_files_refuses_a_path(tmp_path):
    assert_one_line_error(invoke("run", "toy", "--dataset", tmp_path), "dataset")


def test_a_folder_the_loader_cannot_read(tmp_path):
    line = assert_one_line_error(invoke("run", "files", "--dataset", "folder", "-o", f"path={tmp_path}"), "dataset")
    assert "FileNotFoundError" in line


def test_a_failing_step_is_one_line_and_runs_nothing_after_it():
    line = assert_one_line_error(invoke("run", "files", "--json"), "explode")
    assert "ValueError: this input breaks the step" in line


def test_set_is_checked_before_the_dataset_loads(tmp_path):
    # the step name is wrong *and* the folder is missing: the --set problem is reported first
    assert_one_line_error(invoke("run", "files", "-d", tmp_path / "missing", "-s", "nope.x=1"), "step")


# --- export -----------------------------------------------------------------------------------------
def test_export_json_npy_png_ply(tmp_path):
    common = ["--option", "count=2", "--option", "size=8"]
    assert invoke("export", "toy", "--what", "means", "--format", "json", "--out", tmp_path / "m.json",
                  *common).exit_code == 0
    assert len(json.loads((tmp_path / "m.json").read_text())) == 2

    assert invoke("export", "toy", "--what", "noisy", "--format", "npy", "--out", tmp_path / "n.npy",
                  *common).exit_code == 0
    assert np.load(tmp_path / "n.npy").shape == (2, 8, 8)

    result = invoke("export", "toy", "-w", "images", "-f", "png", "--out", tmp_path / "sub" / "im1.png",
                    "--index", "1", *common)
    assert result.exit_code == 0, result.output
    assert "wrote images (png)" in result.stdout
    pixels = cv2.imread(str(tmp_path / "sub" / "im1.png"), cv2.IMREAD_UNCHANGED)
    expected = np.clip(gradients(count=2, size=8).state["images"][1].pixels * 255 + 0.5, 0, 255).astype(np.uint8)
    np.testing.assert_array_equal(pixels, expected)

    assert invoke("export", "toy", "--what", "cloud", "--format", "ply", "--out", tmp_path / "c.ply",
                  "--set", "add_noise.sigma=0", *common).exit_code == 0
    cloud = trimesh.load(tmp_path / "c.ply")
    means = np.array([im.pixels.mean() for im in gradients(count=2, size=8).state["images"].images])
    np.testing.assert_allclose(np.asarray(cloud.vertices), np.stack([means, means, [0.0, 1.0]], axis=1), atol=1e-6)


def test_export_runs_only_up_to_the_producer(tmp_path):
    # 'noisy' comes from the first step; the failing third step of 'files' must not run
    result = invoke("export", "files", "--what", "noisy", "--format", "npy", "--out", tmp_path / "n.npy")
    assert result.exit_code == 0, result.output


def test_export_opencv_yaml_reads_back_with_filestorage(tmp_path):
    out = tmp_path / "calib" / "camera.yaml"
    result = invoke("export", "camera", "--format", "opencv-yaml", "--out", out, "-o", "size=20",
                    "--set", "fit_camera.focal=321.5")
    assert result.exit_code == 0, result.output
    storage = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    K = storage.getNode("camera_matrix").mat()
    dist = storage.getNode("distortion_coefficients").mat()
    np.testing.assert_allclose(K, [[321.5, 0, 9.5], [0, 321.5 * 1.01, 9.5], [0, 0, 1]])
    assert dist.shape == (5, 1)
    np.testing.assert_allclose(dist.ravel(), [-0.1, 0.02, 0.001, -0.002, 0.0])
    assert storage.getNode("image_width").real() == 20 and storage.getNode("image_height").real() == 20
    assert storage.getNode("avg_reprojection_error").real() == pytest.approx(0.25)
    storage.release()
    text = out.read_text()
    assert text.startswith("%YAML") and "camera_matrix: !!opencv-matrix" in text


@pytest.mark.parametrize(("args", "field"), [
    (["--what", "means", "--format", "tiff"], "--format"),
    (["--format", "json"], "--what"),
    (["--what", "cloud", "--format", "png"], "format"),
    (["--what", "cloud", "--format", "ply", "--until", "add_noise"], "--until"),
    (["--what", "no_such_value", "--format", "json"], "value"),
    (["--format", "opencv-yaml"], "--format"),
    (["--format", "colmap"], "--format"),  # the toy module makes no reconstruction
    (["--format", "transforms-json", "--what", "cloud"], "--format"),  # nor a transforms.json
    (["--what", "means", "--format", "json", "--set", "add_noise.sigma=-1"], "add_noise.sigma"),
])
def test_export_errors(tmp_path, args, field):
    out = tmp_path / "out.bin"
    assert_one_line_error(invoke("export", "toy", *args, "--out", out), field)
    assert not out.exists()


def test_export_opencv_yaml_accepts_only_k_or_dist(tmp_path):
    assert_one_line_error(invoke("export", "camera", "--format", "opencv-yaml", "--what", "cameras",
                                 "--out", tmp_path / "c.yaml"), "--what")


# --- modules and serve ------------------------------------------------------------------------------
def test_modules_lists_steps_controls_and_datasets():
    result = invoke("modules")
    assert result.exit_code == 0, result.output
    text = result.stdout
    for expected in ("toy: Toy.", "gradients (default)", "--option count=3  (int in [1, 8])",
                     "1. add_noise", "--set add_noise.sigma=0.1  (float in [0, 1])  standard deviation of the noise.",
                     "--set add_noise.mode=gaussian  (one of gaussian|uniform)", "3. lift (long)",
                     "folder (reads a folder or file: --dataset PATH)", "--option path=...  (str, required)"):
        assert expected in text, expected


def test_modules_lists_a_modules_own_export_formats():
    text = invoke("modules").stdout
    assert "exports (vision-lab export MODULE --format FORMAT):" in text
    assert "opencv-yaml: K and dist in OpenCV's YAML (reads K, dist)" in text
    listed = json.loads(invoke("modules", "--json").stdout)["modules"]
    assert listed[2]["exports"] == [{"format": "opencv-yaml", "summary": "K and dist in OpenCV's YAML",
                                     "reads": ["K", "dist"]}]


def test_modules_json():
    result = invoke("modules", "--json")
    assert result.exit_code == 0, result.output
    listed = json.loads(result.stdout)["modules"]
    assert [m["name"] for m in listed] == list(PIPELINES)
    toy = listed[0]
    assert [s["name"] for s in toy["steps"]] == ["add_noise", "mean_intensity", "lift"]
    assert toy["steps"][0]["controls"]["properties"]["sigma"] == {
        "type": "number", "minimum": 0.0, "maximum": 1.0, "default": 0.1, "title": "sigma",
        "description": "standard deviation of the noise."}
    assert toy["steps"][2]["long"] is True
    assert listed[1]["datasets"][1]["takes_path"] is True


def test_serve_calls_the_server_with_the_options(monkeypatch, tmp_path):
    calls = []
    fake = types.ModuleType("lab.server")
    fake.serve = lambda **kwargs: calls.append(kwargs)
    monkeypatch.setitem(sys.modules, "lab.server", fake)
    assert invoke("serve").exit_code == 0
    assert invoke("serve", "--host", "0.0.0.0", "--port", "9001", "--viewer-port", "9002",
                  "--data-root", str(tmp_path), "--no-warmup").exit_code == 0
    assert invoke("serve", "--worker-id", "w1", "--peers", "w0=http://h:1,w1=http://h:2", "--no-grading",
                  "--no-warmup", "--trust-forwarded-for").exit_code == 0
    assert calls[:2] == [{"host": "127.0.0.1", "port": 8000, "viewer_port": 8080, "data_root": None, "warmup": True,
                          "worker": None, "grading": True, "trust_forwarded_for": False},
                         {"host": "0.0.0.0", "port": 9001, "viewer_port": 9002, "data_root": str(tmp_path),
                          "warmup": False, "worker": None, "grading": True, "trust_forwarded_for": False}]
    worker = calls[2].pop("worker")
    assert (worker.id, dict(worker.peers)) == ("w1", {"w0": "http://h:1", "w1": "http://h:2"})
    assert calls[2] == {"host": "127.0.0.1", "port": 8000, "viewer_port": 8080, "data_root": None, "warmup": False,
                        "grading": False, "trust_forwarded_for": True}
    assert_one_line_error(invoke("serve", "--port", "70000"), "--port")
    assert_one_line_error(invoke("serve", "--data-root", str(tmp_path / "missing")), "--data-root")
    assert_one_line_error(invoke("serve", "--worker-id", "W 1"), "--worker-id")
    assert_one_line_error(invoke("serve", "--worker-id", "w1", "--peers", "w0"), "--peers")
    assert_one_line_error(invoke("serve", "--peers", "w0=http://h:1"), "--peers")


def test_serve_workers_plans_one_process_per_port_and_only_w0_grades(monkeypatch):
    started = []
    fake = types.ModuleType("lab.server")
    from lab.server import plan_workers

    fake.plan_workers = plan_workers
    fake.serve_workers = lambda plans: started.append(plans) or 0
    monkeypatch.setitem(sys.modules, "lab.server", fake)
    assert invoke("serve", "--workers", "3", "--port", "9000", "--viewer-port", "9100", "--no-warmup",
                  "--trust-forwarded-for").exit_code == 0
    (plans,) = started
    assert [(p.id, p.port, p.viewer_port) for p in plans] == [("w0", 9000, 9100), ("w1", 9001, 9101),
                                                              ("w2", 9002, 9102)]
    for plan in plans:
        command = list(plan.command)
        assert command[command.index("--worker-id") + 1] == plan.id
        assert command[command.index("--peers") + 1] == ",".join(f"w{i}=http://127.0.0.1:{9000 + i}" for i in range(3))
        assert ("--no-grading" in command) == (plan.id != "w0")
        assert "--no-warmup" in command and "--trust-forwarded-for" in command
    assert_one_line_error(invoke("serve", "--workers", "2", "--port", "9000", "--viewer-port", "9001"), "--workers")
    assert_one_line_error(invoke("serve", "--workers", "2", "--no-grading"), "--workers")


def test_serve_reports_a_port_in_use_in_one_line(monkeypatch):
    def busy(**kwargs):
        raise OSError(98, "Address already in use")

    monkeypatch.setitem(sys.modules, "lab.server", types.SimpleNamespace(serve=busy))
    assert "Address already in use" in assert_one_line_error(invoke("serve"), "os")


# --- the Python API ---------------------------------------------------------------------------------
def test_open_session_by_pipeline_dataset_path_and_options(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((9, 9), np.uint8))
    session = lab.open_session(FILES, tmp_path, seed=3)
    assert session.dataset == "folder" and session.options == {"path": str(tmp_path)} and session.seed == 3
    assert session.run("check_images").metrics == {"image_count": 1}
    assert len(lab.open_session(TOY, count=2).get("images")) == 2
    assert lab.open_session(TOY, options={"count": 1}, size=4).get("images")[0].pixels.shape == (4, 4)


def test_resolve_dataset_errors(tmp_path):
    from lab.core import InvalidValue

    assert lab.resolve_dataset(TOY, None, {"count": 2}) == (None, {"count": 2})
    assert lab.resolve_dataset(TOY, "gradients") == ("gradients", {})
    with pytest.raises(UnknownName, match="no dataset 'nope'"):
        lab.resolve_dataset(TOY, "nope")
    with pytest.raises(InvalidValue, match="reads no files"):
        lab.resolve_dataset(TOY, tmp_path)
    with pytest.raises(InvalidValue, match="given twice"):
        lab.resolve_dataset(FILES, tmp_path, {"path": "elsewhere"})


# --- the real command -------------------------------------------------------------------------------
def _console_script() -> str:
    beside = Path(sys.executable).with_name("vision-lab")
    found = str(beside) if beside.exists() else shutil.which("vision-lab")
    assert found, "the vision-lab console script is not installed (pip install -e .)"
    return found


def test_console_script_and_python_m_lab():
    helped = subprocess.run([_console_script(), "--help"], capture_output=True, text=True, timeout=120)
    assert helped.returncode == 0, helped.stderr
    for command in ("serve", "modules", "run", "export"):
        assert command in helped.stdout
    bad = subprocess.run([sys.executable, "-m", "lab", "run", "no_such_module", "--json"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2
    assert bad.stdout == ""
    assert bad.stderr.strip().splitlines() == [
        bad.stderr.strip()] and bad.stderr.startswith("error: module: no module 'no_such_module'")


# --- the real calibration module, end to end (real console script, real registry) -----------------
CALIBRATION_STEPS = ["detect_corners", "estimate_homographies", "estimate_intrinsics", "estimate_extrinsics",
                     "estimate_distortion", "refine_calibration", "undistort_image"]
OPENCV_SAMPLES = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "opencv-samples"


def test_run_calibration_json_end_to_end():
    done = subprocess.run([_console_script(), "run", "calibration", "--json", "--option", "num_views=10"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert (summary["module"], summary["dataset"]) == ("calibration", "synthetic")
    assert [s["name"] for s in summary["steps"]] == CALIBRATION_STEPS
    metrics = summary["metrics"]
    assert metrics["views_found"] == metrics["views_total"] == 10
    assert metrics["rms_px"] < 0.5  # corners carry 0.2 px of noise per axis
    assert metrics["fx_rel_error"] < 0.01 and metrics["fy_rel_error"] < 0.01
    assert len(metrics["per_view_rms_px"]) == 10


def test_export_calibration_of_opencv_samples_matches_opencv(tmp_path):
    """Real photos (OpenCV's left*.jpg) -> opencv-yaml, compared with OpenCV's own calibration of them."""
    from lab.data.exports import read_opencv_calibration

    out = tmp_path / "left.yaml"
    done = subprocess.run([sys.executable, "-m", "lab", "export", "calibration", "--dataset", str(OPENCV_SAMPLES),
                           "--option", "pattern=left*.jpg", "--format", "opencv-yaml", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().startswith("wrote the camera (K, dist")
    assert done.stdout.strip().endswith(f"(opencv-yaml) to {out}")
    ours, opencv = read_opencv_calibration(out), read_opencv_calibration(OPENCV_SAMPLES / "left_intrinsics.yml")
    assert (ours.image_width, ours.image_height) == (640, 480)
    np.testing.assert_allclose(ours.K[[0, 1], [0, 1]], opencv.K[[0, 1], [0, 1]], rtol=0.015)  # focal lengths
    np.testing.assert_allclose(ours.K[:2, 2], opencv.K[:2, 2], atol=5.0)  # principal point, px
    assert ours.dist[0] == pytest.approx(opencv.dist[0], abs=0.05)  # k1
    assert ours.avg_reprojection_error < 0.5
