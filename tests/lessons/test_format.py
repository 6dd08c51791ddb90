"""The lesson format: loading, validation against the module, the catalog, what students see."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from lab.core.errors import UnknownName
from lab.lessons.format import (LessonCatalog, LessonFormatError, Limits, annotation_text, find_lesson,
                                load_lesson, parse_signature)

from lesson_helpers import FIXTURES

TOY = FIXTURES / "lessons" / "00-toy"


def copy_toy(tmp_path: Path, *, tasks: str | None = None, starter: str | None = None,
             name: str = "00-toy") -> Path:
    folder = tmp_path / name
    shutil.copytree(TOY, folder)
    if tasks is not None:
        (folder / "tasks.toml").write_text(tasks)
    if starter is not None:
        (folder / "starter.py").write_text(starter)
    return folder


def edited(old: str, new: str) -> str:
    text = (TOY / "tasks.toml").read_text()
    assert old in text
    return text.replace(old, new, 1)


# --- smoke and known answers -----------------------------------------------------------------------
def test_toy_lesson_loads_with_its_tasks_checks_and_points(toy_lesson):
    assert toy_lesson.id == "00-toy"
    assert toy_lesson.title == "Toy lesson: noise and means"  # the first heading of lesson.md
    assert [t.step for t in toy_lesson.tasks] == ["make_noisy", "mean_intensity"]
    assert toy_lesson.points == 6.0
    assert toy_lesson.datasets["secret"].seed == 1234 and toy_lesson.datasets["small"].seed is None
    check = toy_lesson.task("means").checks[1]
    assert check.params == {"scale": 3} and check.options == {"rtol": 1e-6}
    assert toy_lesson.limits.call_timeout_s == 10


def test_calibration_lesson_is_valid_and_matches_the_module(calibration_lesson):
    assert [t.step for t in calibration_lesson.tasks] == ["estimate_homographies", "estimate_intrinsics"]
    assert calibration_lesson.points == 20.0
    assert calibration_lesson.pipeline.name == "calibration"
    assert set(calibration_lesson.datasets) == {"clean", "noisy"}


def test_describe_shows_text_tasks_starter_but_no_seeds_or_check_data(toy_lesson):
    described = toy_lesson.describe()
    assert described["starter"].startswith('"""Toy lesson')
    assert "Write `make_noisy`" in described["text"]
    assert described["tasks"][1]["signature"].startswith("mean_intensity(")
    text = repr(described)
    assert "1234" not in text and "seed" not in text and "gradients" not in text


def test_catalog_lists_and_resolves_ids_and_names(tmp_path):
    copy_toy(tmp_path)
    catalog = LessonCatalog(tmp_path)
    assert catalog.ids() == ["00-toy"]
    assert catalog.get("toy").id == "00-toy" and catalog.get("00-toy") is catalog.get("toy")
    with pytest.raises(UnknownName, match="lessons are"):
        catalog.get("stereo")


def test_find_lesson_by_folder_path(tmp_path):
    folder = copy_toy(tmp_path)
    assert find_lesson(folder).id == "00-toy"
    assert find_lesson(folder / "tasks.toml").id == "00-toy"


def test_parse_signature():
    name, params = parse_signature("f(a: T, b, *, k: int = 1, rng) -> R", "x")
    assert name == "f" and params.positional == ("a", "b") and params.keyword == ("k", "rng")
    assert params.defaults == {"k": 1}
    with pytest.raises(LessonFormatError, match="not a Python signature"):
        parse_signature("f(a,, b)", "x")


# --- errors: each names the file and the key ------------------------------------------------------------
SCALE_HINT = '[hints.scale_ignored]\nwhen = "same_as_reference_with"\nparams = { scale = 1 }\n'


@pytest.mark.parametrize("old,new,field,reason", [
    ('module = "toy_lesson_pipeline:PIPELINE"', 'module = "no_such_module:X"', "lesson.module",
     "cannot import"),
    ('step = "make_noisy"', 'step = "no_step"', "tasks[0].step", "has no step"),
    ('compare = "allclose"', 'compare = "roughly"', "tasks[0].checks[0].compare", "unknown comparison"),
    ('rtol = 1e-5\natol = 1e-6', 'rtol = 1e-5\nwiggle = 1e-6', "tasks[0].checks[0].wiggle", "no option"),
    ('dataset = "small"\ncompare', 'dataset = "huge"\ncompare', "tasks[0].checks[0].dataset",
     "no [datasets.huge]"),
    ('title = "Noisy images"\n', 'title = "Noisy images"\npoints = 2\n', "tasks[0].points",
     "sum of its checks' points"),
    ("params = { scale = 3 }", "params = { scale = 30 }", "tasks[1].checks[1].params.scale", "at most"),
    ("params = { scale = 3 }", "params = { zoom = 3 }", "tasks[1].checks[1].params.zoom", "no control"),
    ('seed = 1234', 'seed = "sometimes"', "datasets.secret.seed", "an integer"),
    ('seed = 1234', 'seed = "fresh"', "datasets.secret.seed", "practice run"),
    ('seed = 1234', 'seed = 1234\nvariants = 0', "datasets.secret.variants", "from 1 to"),
    ('seed = 1234', 'seed = 1234\nvariants = [{ pixels = 3 }]', "datasets.secret.variants[0].pixels",
     "no such option"),
    ('seed = 1234', 'seed = 1234\nvariants = [{ seed = 3 }]', "datasets.secret.variants[0].seed",
     "derived from the assignment seed"),
    ('options = { count = 4, size = 8 }', 'options = { count = 4, pixels = 8 }',
     "datasets.secret.options.pixels", "no such option"),
    ('until = "mean_intensity"', 'until = "make_noisy"', "tasks[0].checks[1].until", "after"),
    ('value = "means"', 'value = "images"', "tasks[0].checks[1].value", "writes"),
    ('visibility = "after_published"', 'visibility = "secret"', "tasks[1].checks[2].visibility",
     "must be one of"),
    ("[limits]\ncpu_seconds = 20", "[limits]\ncpu_seconds = -1", "limits.cpu_seconds", "positive"),
    ("[limits]\n", "[limits]\ngpu = 1\n", "limits.gpu", "unknown key"),
    ('title = "Mean intensity"\n',
     'title = "Mean intensity"\nsignature = "mean_intensity(noisy, *, scale=1)"\n',
     "tasks[1].signature", "comes from its step"),
    # hints: defined once in [hints], named by the checks
    ('[hints.scale_ignored]\nwhen = "same_as_reference_with"', '[hints.scale_ignored]\nwhen = "psychic"',
     "hints.scale_ignored.when", "unknown detector"),
    ('hints = ["scaled", "scale_ignored"]', 'hints = ["scaled", "scale_ignore"]',
     "tasks[1].checks[0].hints[1]",
     "unknown hint 'scale_ignore'; the [hints] table defines ['means_summed', 'noisy_without_clipping', "
     "'scale_ignored']"),
    ('hints = ["scaled", "scale_ignored"]', 'hints = ["entry_not"]', "tasks[1].checks[0].hints[0]",
     "unknown hint"),
    ('hints = ["scaled", "scale_ignored"]', 'hints = ["scaled", "scaled"]', "tasks[1].checks[0].hints",
     "twice"),
    ('hints = ["scaled", "scale_ignored"]', 'hints = [{ when = "scaled" }]', "tasks[1].checks[0].hints[0]",
     "defined once, in the lesson's [hints] table"),
    ('hints = ["scaled", "scale_ignored"]', 'hints = "scaled"', "tasks[1].checks[0].hints",
     "a list of hint names"),
    ("[hints.scale_ignored]", "[hints.transposed]", "hints.transposed", "a detector's name"),
    ('params = { scale = 1 }\nsay', 'params = { zoom = 1 }\nsay', "hints.scale_ignored.params.zoom",
     "no control"),
    ("[hints.means_summed]", '[hints.h22]\nwhen = "entry_not"\n\n[hints.means_summed]', "hints.h22.index",
     "needs option 'index'"),
])
def test_format_errors_name_the_file_and_key(tmp_path, old, new, field, reason):
    folder = copy_toy(tmp_path, tasks=edited(old, new))
    with pytest.raises(LessonFormatError) as caught:
        load_lesson(folder)
    assert caught.value.field.startswith("00-toy/tasks.toml")
    assert caught.value.field.endswith(field), caught.value.field
    assert reason in caught.value.reason


def test_invalid_toml_is_reported(tmp_path):
    folder = copy_toy(tmp_path, tasks="[lesson\nmodule = 1")
    with pytest.raises(LessonFormatError, match="not valid TOML"):
        load_lesson(folder)


def test_a_step_returning_one_value_can_be_a_task(tmp_path):
    tasks = (TOY / "tasks.toml").read_text() + """
[[tasks]]
name = "bad"
step = "normalize_means"
[[tasks.checks]]
name = "x"
points = 1
dataset = "small"
compare = "allclose"
"""
    starter = ((TOY / "starter.py").read_text()
               + "\n\ndef normalize_means(means):\n    raise NotImplementedError\n")
    folder = copy_toy(tmp_path, tasks=tasks, starter=starter)
    task = load_lesson(folder).task("bad")
    assert task.step == "normalize_means"  # one value: allowed
    assert task.signature == "normalize_means(means: np.ndarray) -> np.ndarray" and task.points == 1.0


@pytest.mark.parametrize("starter,reason", [
    ('def make_noisy(images, *, sigma=0.05, rng):\n    raise NotImplementedError\n',
     "defines no function 'mean_intensity'"),
    ('def make_noisy(images, *, sigma=0.05, rng):\n    raise NotImplementedError\n'
     'def mean_intensity(noisy, *, factor=1):\n    raise NotImplementedError\n', "differs"),
    ('def make_noisy(images, *, sigma=0.05, rng):\n    raise NotImplementedError\n'
     'def mean_intensity(noisy, *, scale=1):\n    return noisy\n', "must raise NotImplementedError"),
    ('def make_noisy(images, *, sigma=0.05, rng)\n', "line 1"),
])
def test_starter_must_define_every_task_with_its_parameters_raising(tmp_path, starter, reason):
    folder = copy_toy(tmp_path, starter=starter)
    with pytest.raises(LessonFormatError, match=r"starter\.py") as caught:
        load_lesson(folder)
    assert reason in caught.value.reason


MISTAKE_HINT = '[hints.scale_ignored]\nwhen = "same_as_mistake"\nmistake = "%s"\n'


@pytest.mark.parametrize("extra,name,reason", [
    (None, "means_unscaled", "defines no function 'noisy_without_clipping' (is the file missing?)"),
    ("", "means_typo",
     "defines no function 'means_typo'; it defines ['means_summed', 'noisy_without_clipping']"),
    ("def means_unscaled(noisy, *, factor=1):\n    return noisy\n", "means_unscaled",
     "differs from the step's"),
    ("def means_unscaled(noisy, *, scale=1)\n", "means_unscaled", "line"),
    ("", "", "names a function of mistakes.py"),
])
def test_a_mistake_hint_names_a_function_of_mistakes_py_with_the_steps_parameters(tmp_path, extra, name,
                                                                                   reason):
    folder = copy_toy(tmp_path, tasks=edited(SCALE_HINT, MISTAKE_HINT % name))
    if extra is None:
        (folder / "mistakes.py").unlink()
    else:
        (folder / "mistakes.py").write_text((TOY / "mistakes.py").read_text() + "\n\n" + extra)
    with pytest.raises(LessonFormatError) as caught:
        load_lesson(folder)
    assert caught.value.field.startswith("00-toy/tasks.toml") or "mistakes.py" in caught.value.field
    assert reason in caught.value.reason, caught.value.reason


@pytest.mark.parametrize("hint,field,reason", [
    ('when = "same_as_mistake"\nmistake = "means_summed"\ncompare = "roughly"\n',
     "hints.scale_ignored.compare", "unknown comparison 'roughly'"),
    ('when = "same_as_mistake"\nmistake = "means_summed"\ncompare = "allclose"\n'
     'compare_options = { wiggle = 1 }\n', "hints.scale_ignored.compare_options.wiggle",
     "has no option 'wiggle'"),
    ('when = "same_as_mistake"\nmistake = "means_summed"\ncompare_options = { rtol = 1 }\n',
     "hints.scale_ignored.compare_options", "give the comparison"),
    ('when = "same_as_mistake"\nmistake = "means_summed"\nparams = { scale = 2 }\n',
     "hints.scale_ignored.params", "takes no option 'params'"),
    ('when = "entry_not"\nindex = [0]\nvalu = 1.0\n', "hints.scale_ignored.valu", "takes no option 'valu'"),
    ('when = "same_as_mistake"\n', "hints.scale_ignored.mistake", "needs option 'mistake'"),
    ('when = "scaled"\nsay = 3\n', "hints.scale_ignored.say", "must be a string"),
])
def test_hint_keys_are_the_detectors_options(tmp_path, hint, field, reason):
    folder = copy_toy(tmp_path, tasks=edited(SCALE_HINT, "[hints.scale_ignored]\n" + hint).replace(
        'say = "you ignore the control scale: multiply by it"\n', "", 1))
    with pytest.raises(LessonFormatError) as caught:
        load_lesson(folder)
    assert caught.value.field.endswith(field), caught.value.field
    assert reason in caught.value.reason


def test_a_hint_is_written_once_and_named_by_each_check_that_tries_it(toy_lesson):
    assert set(toy_lesson.hints) == {"noisy_without_clipping", "scale_ignored", "means_summed"}
    first, second = toy_lesson.task("means").checks[1].hints[1], toy_lesson.task("means").checks[2].hints[0]
    assert first is second is toy_lesson.hints["means_summed"]
    assert first.when == "same_as_mistake" and first.options == {"mistake": "means_summed"}
    assert first.say == "you sum each image's pixels: divide by their number"
    scaled = toy_lesson.task("means").checks[0].hints[0]  # a detector named directly
    assert (scaled.name, scaled.when, scaled.say, scaled.options) == ("scaled", "scaled", "", {})
    assert toy_lesson.warnings == ()


def test_a_hint_no_check_names_is_reported(tmp_path, caplog):
    forgotten = '[hints.forgotten]\nwhen = "negated"\nsay = "flip it"\n\n[hints.means_summed]'
    folder = copy_toy(tmp_path, tasks=edited("[hints.means_summed]", forgotten))
    with caplog.at_level("WARNING", logger="lab.lessons"):
        lesson = load_lesson(folder)
    assert lesson.warnings == ("00-toy/tasks.toml: hints.forgotten is named by no check",)
    assert "hints.forgotten is named by no check" in caplog.text


def test_a_task_signature_comes_from_its_step_and_its_points_from_its_checks(toy_lesson):
    noise, means = toy_lesson.tasks
    assert noise.signature == ("make_noisy(images: ImageSet, *, sigma: float = 0.05, "
                               "rng: np.random.Generator) -> ImageSet")
    assert means.signature == "mean_intensity(noisy: ImageSet, *, scale: int = 1) -> np.ndarray"
    assert (noise.points, means.points) == (2.0, 4.0)
    assert toy_lesson.describe()["tasks"][0]["points"] == 2.0


def test_signatures_show_annotations_as_written():
    from typing import Annotated, Literal

    import numpy as np

    from lab.core import Points2D, Range

    assert annotation_text(Annotated[float, Range(0.0, 1.0)]) == "float"
    assert annotation_text(Annotated[np.ndarray, "F"]) == "np.ndarray"
    assert annotation_text(np.ndarray | None) == "np.ndarray | None"
    assert annotation_text(Literal["ssd", "ncc"]) == "Literal['ssd', 'ncc']"
    assert annotation_text(np.random.Generator) == "np.random.Generator"
    assert annotation_text(Points2D) == "Points2D"
    assert annotation_text(tuple[int, ...]) == "tuple[int, ...]"


def test_the_starter_gives_the_steps_defaults_or_none(tmp_path):
    starter = (TOY / "starter.py").read_text()
    assert "scale=1" in starter
    load_lesson(copy_toy(tmp_path / "a", starter=starter.replace("scale=1", "scale")))  # no default: fine
    with pytest.raises(LessonFormatError, match=r"starter\.py") as caught:
        load_lesson(copy_toy(tmp_path / "b", starter=starter.replace("scale=1", "scale=2")))
    assert "scale=2 differs from the step's default scale=1" in caught.value.reason
    with pytest.raises(LessonFormatError, match=r"starter\.py") as caught:
        load_lesson(copy_toy(tmp_path / "c", starter=starter.replace("def make_noisy(images,",
                                                                     "def make_noisy(images=None,")))
    assert "has a default the step's images does not have" in caught.value.reason


def test_a_mistakes_py_that_fails_to_run_is_a_format_error(tmp_path):
    folder = copy_toy(tmp_path)
    (folder / "mistakes.py").write_text((TOY / "mistakes.py").read_text() + "\nimport no_such_module_here\n")
    with pytest.raises(LessonFormatError, match="fails to run: ModuleNotFoundError") as caught:
        load_lesson(folder)
    assert caught.value.field == "00-toy/mistakes.py"


def test_mistakes_py_is_loaded_once_and_never_shown_to_students(tmp_path):
    folder = copy_toy(tmp_path, tasks=edited(SCALE_HINT, MISTAKE_HINT % "means_unscaled"))
    (folder / "mistakes.py").write_text((TOY / "mistakes.py").read_text()
                                        + "\n\nSECRET = 1\n\ndef means_unscaled(noisy, *, scale=1):\n"
                                          "    return 42\n")
    lesson = load_lesson(folder)
    assert set(lesson.mistakes) == {"means_unscaled", "means_summed", "noisy_without_clipping"}
    assert lesson.mistakes["means_unscaled"](None) == 42
    assert lesson.mistakes is lesson.mistakes
    assert "means_unscaled" not in str(lesson.describe())


def test_missing_files_and_bad_folder_names(tmp_path):
    folder = copy_toy(tmp_path)
    (folder / "lesson.md").unlink()
    with pytest.raises(LessonFormatError, match=r"lesson\.md"):
        load_lesson(folder)
    with pytest.raises(LessonFormatError, match="NN-name"):
        load_lesson(copy_toy(tmp_path, name="toy"))


def test_limits_refuse_nonsense():
    assert Limits().cpu_seconds > 0
    with pytest.raises(LessonFormatError, match="positive"):
        Limits(memory_mb=0)


def test_a_step_returning_a_result_dataclass_cannot_be_a_task(tmp_path):
    folder = tmp_path / "02-corners"
    folder.mkdir()
    (folder / "lesson.md").write_text("# Corners\n")
    (folder / "starter.py").write_text("def detect_corners(images, board, *, subpixel=True, window=5):\n"
                                       "    raise NotImplementedError\n")
    (folder / "tasks.toml").write_text("""
[lesson]
module = "calibration"
[datasets.d]
dataset = "synthetic"
[[tasks]]
step = "detect_corners"
[[tasks.checks]]
name = "x"
points = 1
dataset = "d"
compare = "allclose"
""")
    with pytest.raises(LessonFormatError, match="cannot be a task"):
        load_lesson(folder)
