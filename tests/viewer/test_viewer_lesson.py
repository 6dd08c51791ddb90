"""The viewer's lesson mode, driven through the viewer's own widgets on a real viser server: the
lesson picker and ``?lesson=``, the lesson text beside the pipeline, the student's file loaded into
a sandbox (uploaded or the starter), "use my code" on Run, and "Compare with reference" showing
both outputs with the verdict, the message and what the student printed. Errors from student code
are shown in the GUI, never raised; the sandbox ends with the tab."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest
import viser

from lab.core import Image, ImageSet, Points2D
from lab.core.errors import LabError
from lab.lessons.format import LessonCatalog
from lab.lessons.live import SideBySide
from lab.lessons.service import DEFAULT_MAX_SUBMISSION_BYTES
from lab.viewer.app import ClientView, ModuleCatalog, ViewerApp
from lab.viewer.lesson import (NO_LESSON, array_comparison, comparison_markdown, side_by_side_state,
                               upload_text)
from toy_pipeline import TOY

REPO = Path(__file__).resolve().parents[2]
FIXTURES = REPO / "tests" / "fixtures"
SUBMISSIONS = FIXTURES / "submissions"
if str(FIXTURES) not in sys.path:  # the toy lesson's module "toy_lesson_pipeline:PIPELINE"
    sys.path.insert(0, str(FIXTURES))

HOMOGRAPHIES, INTRINSICS = "estimate_homographies", "estimate_intrinsics"


@pytest.fixture(scope="module")
def lessons():
    return LessonCatalog(REPO / "lessons")


@pytest.fixture(scope="module")
def toy_lessons():
    return LessonCatalog(FIXTURES / "lessons")


@pytest.fixture
def views():
    """Views made by a test; each is closed at the end (which ends the student's sandbox)."""
    made: list[ClientView] = []
    yield made
    for view in made:
        view.close()


def make_view(server, store, views, lessons, *, background=False) -> ClientView:
    """A view on the server's shared GUI with lesson mode, offering the toy module."""
    view = ClientView(server, store, ModuleCatalog({"toy": TOY}), is_client=False, background=background,
                      lessons=lessons)
    views.append(view)
    return view


def upload(handle, name: str, content: bytes) -> None:
    """What viser does when a browser finished uploading a file to an upload button."""
    handle._impl.value = viser.UploadedFile(name, content)
    for callback in handle._impl.update_cb:
        callback(viser.GuiEvent(client=None, client_id=None, target=handle))


def click(button) -> None:
    button.value = True  # a button's value setter runs its click callbacks


def submission(*parts: str) -> bytes:
    return SUBMISSIONS.joinpath(*parts).read_bytes()


def calibration_view(server, store, views, lessons, **kwargs) -> ClientView:
    """A tab opened at ?lesson=01-calibration, with the corners detected (the first task's inputs)."""
    view = make_view(server, store, views, lessons, **kwargs)
    view.start({"lesson": "01-calibration"})
    view.press("detect_corners", "Run")
    view.wait()
    assert view.session.step_status()[HOMOGRAPHIES] == "ready"
    return view


# --- choosing a lesson ---------------------------------------------------------------------------
def test_the_picker_opens_a_lesson_beside_its_pipeline(server, store, views, lessons):
    view = make_view(server, store, views, lessons)
    view.start({})
    mode = view.lesson_mode
    assert view.session.pipeline.name == "toy" and mode.lesson is None
    assert mode.picker.options == (NO_LESSON, *lessons.ids())
    assert mode.upload_button.disabled and mode.rows == {}

    mode.picker.value = "01-calibration"  # what a student's choice does
    lesson = lessons.get("01-calibration")
    assert mode.lesson is lesson and view.session.pipeline.name == "calibration" and len(store) == 2
    assert view.session.dataset == "synthetic"
    assert mode.text.content == lesson.text and "## Task 1" in mode.text.content
    assert "estimate_homographies" in mode.summary.content and "20 points" in mode.summary.content
    assert isinstance(mode.panel, viser.PanelHandle) and not mode.upload_button.disabled
    assert not mode.starter_button.disabled
    # the task steps (and only they) get the lesson's widgets, inside their own folders
    assert list(mode.rows) == [HOMOGRAPHIES, INTRINSICS]
    row = mode.rows[HOMOGRAPHIES]
    assert isinstance(row.use_mine, viser.GuiCheckboxHandle) and row.use_mine.value is False
    assert isinstance(row.compare, viser.GuiButtonHandle) and row.compare.label == "Compare with reference"
    assert "def estimate_homographies(corners: Points2D" in row.handles[0].content
    assert mode.code_md.content == "No code of yours is loaded yet."

    mode.picker.value = NO_LESSON  # leave the lesson: its widgets go, the session stays
    assert mode.lesson is None and mode.rows == {} and mode.upload_button.disabled
    assert mode.panel is None and mode.text is None and view.session.pipeline.name == "calibration"


def test_a_lesson_that_does_not_load_is_reported(server, store, views, tmp_path):
    import shutil

    shutil.copytree(FIXTURES / "lessons" / "00-toy", tmp_path / "02-broken")
    toml = tmp_path / "02-broken" / "tasks.toml"
    toml.write_text(toml.read_text().replace('step = "make_noisy"', 'step = "no_such_step"'))
    view = make_view(server, store, views, LessonCatalog(tmp_path))
    view.start({})
    mode = view.lesson_mode
    mode.picker.value = "02-broken"
    assert "no_such_step" in view.tab.error_box.content
    assert "02-broken/tasks.toml" in view.tab.error_box.content
    assert mode.lesson is None and mode.picker.value == NO_LESSON and view.session.pipeline.name == "toy"


def test_the_page_query_opens_a_lesson(server, store, views, lessons):
    view = make_view(server, store, views, lessons)
    view.start({"lesson": "calibration"})  # the short name works too
    assert view.lesson_mode.lesson.id == "01-calibration"
    assert view.lesson_mode.picker.value == "01-calibration"
    assert view.session.pipeline.name == "calibration" and view.errors == []

    reloaded = make_view(server, store, views, lessons)  # ?session=ID&lesson=ID: the same session, no new one
    reloaded.start({"lesson": "01-calibration", "session": view.session.id})
    assert reloaded.session is view.session and len(store) == 1
    assert list(reloaded.lesson_mode.rows) == [HOMOGRAPHIES, INTRINSICS]

    unknown = make_view(server, store, views, lessons)  # an unknown lesson: said so, the default module opens
    unknown.start({"lesson": "99-nope"})
    assert "not_found" in unknown.tab.error_box.content and "99-nope" in unknown.tab.error_box.content
    assert unknown.session.pipeline.name == "toy" and unknown.lesson_mode.lesson is None


def test_a_session_of_another_module_gets_no_task_widgets(server, store, views, lessons):
    view = make_view(server, store, views, lessons)
    view.start({"lesson": "01-calibration"})
    view.open_session(store.create(TOY))
    mode = view.lesson_mode
    assert mode.rows == {} and "runs module `toy`" in mode.code_md.content
    assert mode.override("add_noise") is None
    assert mode.text.content == mode.lesson.text  # the lesson stays on screen


# --- the student's code ----------------------------------------------------------------------------
def test_a_correct_file_runs_in_place_of_the_reference_and_compares_equal(server, store, views, lessons):
    # sandbox work off viser's threads
    view = calibration_view(server, store, views, lessons, background=True)
    mode = view.lesson_mode
    upload(mode.upload_button, "solution.py", submission("calibration", "solution.py"))
    view.wait()
    assert "Loaded **`solution.py`**" in mode.code_md.content
    assert "✓ defines `estimate_homographies`" in mode.code_md.content
    assert "✓ defines `estimate_intrinsics`" in mode.code_md.content
    assert mode.code.sandbox.alive and all(row.use_mine.value for row in mode.rows.values())

    # Run with "use my code" on: the student's function wrote the state
    view.press(HOMOGRAPHIES, "Run")
    view.wait()
    session = view.session
    record = session.history[-1]
    assert (record.step, record.status, record.replaced) == (HOMOGRAPHIES, "ok", True)
    assert session.get("homographies").shape[1:] == (3, 3)
    assert "Ran **your** `estimate_homographies`" in mode.rows[HOMOGRAPHIES].result.content

    # compare: both outputs side by side, the session untouched
    before = dict(session.state)
    history = len(session.history)
    click(mode.rows[HOMOGRAPHIES].compare)
    view.wait()
    side = mode.compared[HOMOGRAPHIES]
    assert side.passed is True
    result = mode.rows[HOMOGRAPHIES].result.content
    assert "matches the reference" in result and "best scale factor" in result
    assert "| entry | yours | reference | yours − reference |" in result
    assert "*Your code printed nothing.*" in result
    assert session.state.keys() == before.keys() and all(session.state[k] is before[k] for k in before)
    assert len(session.history) == history and not view.tab.error_box.visible

    # "use my code" off: the reference runs again
    mode.rows[HOMOGRAPHIES].use_mine.value = False
    view.press(HOMOGRAPHIES, "Run")
    view.wait()
    assert session.history[-1].replaced is False and session.history[-1].status == "ok"
    # and on for the next task, through Run to here
    view.press(INTRINSICS, "Run to here")
    view.wait()
    assert session.history[-1].step == INTRINSICS and session.history[-1].replaced is True
    assert mode.use_mine == {HOMOGRAPHIES: False, INTRINSICS: True}


def test_a_wrong_file_is_reported_with_what_it_printed(server, store, views, lessons):
    view = calibration_view(server, store, views, lessons)
    mode = view.lesson_mode
    source = submission("calibration", "wrong_transposed_homography.py").decode() + (
        "\n\n_transposed = estimate_homographies\n\n\ndef estimate_homographies(corners, board_points, *, "
        "normalize=True):\n    print('hello from my homographies')\n    return _transposed(corners, "
        "board_points, normalize=normalize)\n")
    upload(mode.upload_button, "mine.py", source.encode())
    mode.compare(HOMOGRAPHIES)
    side = mode.compared[HOMOGRAPHIES]
    assert side.passed is False and "homographies" in side.student and "homographies" in side.reference
    assert side.student["homographies"].shape == side.reference["homographies"].shape
    assert not np.allclose(side.student["homographies"], side.reference["homographies"], rtol=1e-3)
    result = mode.rows[HOMOGRAPHIES].result.content
    assert "differs from the reference" in result
    assert "relative difference after the best scale factor" in result
    assert "**Your code printed:**" in result and "hello from my homographies" in result
    assert "homographies" not in view.session.state  # a comparison never writes the session


def test_the_starter_fails_with_the_students_message(server, store, views, lessons):
    view = calibration_view(server, store, views, lessons)
    mode = view.lesson_mode
    click(mode.starter_button)
    assert "Loaded **`starter.py`**" in mode.code_md.content and mode.rows[HOMOGRAPHIES].use_mine.value

    view.press(HOMOGRAPHIES, "Run")  # shown, never raised; the failure is in history, the state untouched
    assert "step_failed" in view.tab.error_box.content and "not implemented yet" in view.tab.error_box.content
    record = view.session.history[-1]
    assert (record.status, record.replaced) == ("failed", True) and "homographies" not in view.session.state
    assert "Your code failed" in mode.rows[HOMOGRAPHIES].result.content

    view.guard(lambda: mode.compare(HOMOGRAPHIES))
    assert mode.compared[HOMOGRAPHIES].passed is None
    assert "Your step failed" in mode.rows[HOMOGRAPHIES].result.content
    assert "not implemented yet" in mode.rows[HOMOGRAPHIES].result.content
    assert "not implemented yet" in view.tab.error_box.content


def test_a_step_the_students_code_failed_reads_failed_while_folded(server, store, views, lessons):
    view = calibration_view(server, store, views, lessons, background=True)
    mode = view.lesson_mode
    click(mode.starter_button)
    view.wait()
    view.press(HOMOGRAPHIES, "Run")
    view.wait()
    row = mode.rows[HOMOGRAPHIES]
    deadline = time.monotonic() + 20  # the label is set once the worker's last refresh is over
    while "failed" not in row.folder.label and time.monotonic() < deadline:
        time.sleep(0.02)
    assert "✗ failed" in row.folder.label and "ready" not in row.folder.label
    assert mode.banner.visible and "Your code failed" in mode.banner.content
    assert "not implemented yet" in mode.banner.content and HOMOGRAPHIES in mode.banner.content
    assert mode.status_of(HOMOGRAPHIES, "ready") == "failed"
    assert mode.status_of(INTRINSICS, "blocked") == "blocked"

    row.use_mine.value = False  # the reference's step works: the failure is gone
    view.press(HOMOGRAPHIES, "Run")
    view.wait()
    assert view.session.step_status()[HOMOGRAPHIES] == "done" and "✓ done" in row.folder.label
    assert mode.status_of(HOMOGRAPHIES, "done") == "done"


def test_lesson_summary_names_the_module_for_humans(lessons):
    from lab.viewer.lesson import lesson_summary

    sfm = LessonCatalog(REPO / "lessons").get("04-sfm")
    assert sfm.module == "lab.modules.sfm_basics:PIPELINE"
    assert sfm.module_title == sfm.pipeline.title and "Structure from motion" in sfm.module_title
    assert "module: Structure from motion" in lesson_summary(sfm) and "sfm_basics" not in lesson_summary(sfm)
    assert sfm.summary()["module_title"] == sfm.module_title and sfm.summary()["module"] == sfm.module


def test_broken_files_show_an_error_and_the_viewer_goes_on(server, store, views, lessons):
    view = calibration_view(server, store, views, lessons)
    mode = view.lesson_mode
    upload(mode.upload_button, "broken.py", b"def estimate_homographies(:\n")
    assert "SyntaxError" in view.tab.error_box.content
    assert "Could not load `broken.py`" in mode.code_md.content
    assert mode.code is None

    upload(mode.upload_button, "notes.txt", b"print('hi')\n")
    assert "unsupported_media_type" in view.tab.error_box.content and mode.code is None

    upload(mode.upload_button, "explodes.py", b"raise RuntimeError('boom at import')\n")
    assert "could not be loaded" in view.tab.error_box.content
    assert "boom at import" in view.tab.error_box.content
    assert mode.code is None

    mode.rows[HOMOGRAPHIES].use_mine.value = True  # on, with no code loaded: a clear message
    view.press(HOMOGRAPHIES, "Run")
    assert "no code of yours is loaded" in view.tab.error_box.content
    view.guard(lambda: mode.compare(HOMOGRAPHIES))
    assert "no code of yours is loaded" in view.tab.error_box.content

    upload(mode.upload_button, "solution.py", submission("calibration", "solution.py"))
    upload(mode.upload_button, "broken.py", b"def f(:\n")  # a bad file after a good one keeps the good one
    assert "Still using `solution.py`" in mode.code_md.content and mode.code is not None
    view.press(HOMOGRAPHIES, "Run")
    assert view.session.history[-1].status == "ok" and view.session.history[-1].replaced
    assert not view.tab.error_box.visible


def test_closing_the_tab_ends_the_students_sandbox(server, store, views, lessons):
    view = make_view(server, store, views, lessons)
    view.start({"lesson": "01-calibration"})
    click(view.lesson_mode.starter_button)
    click(view.lesson_mode.rows[HOMOGRAPHIES].compare)  # before its inputs exist: said so
    assert "missing_input" in view.tab.error_box.content and "corners" in view.tab.error_box.content
    assert "Could not compare" in view.lesson_mode.rows[HOMOGRAPHIES].result.content
    sandbox = view.lesson_mode.code.sandbox
    assert sandbox.alive
    view.close()
    assert not sandbox.alive and view.lesson_mode.code is None


def test_drawable_outputs_are_drawn_side_by_side(server, store, views, toy_lessons):
    view = make_view(server, store, views, toy_lessons)
    view.start({"lesson": "00-toy"})
    mode = view.lesson_mode
    upload(mode.upload_button, "solution.py", submission("toy", "solution.py"))
    mode.compare("make_noisy")
    assert mode.compared["make_noisy"].passed is True
    drawn = mode._compare_drawer.drawn
    assert {"yours/noisy", "reference/noisy"} <= set(drawn)
    assert drawn["yours/noisy"].parts["image"].label.startswith("yours/noisy[0]")
    assert "drawn in the **Compare** tab" in mode.rows["make_noisy"].result.content

    view.press("make_noisy", "Run")  # the student's noisy images, then their means, printed along the way
    mode.compare("mean_intensity")
    result = mode.rows["mean_intensity"].result.content
    assert mode.compared["mean_intensity"].passed is True and "computing 3 means" in result
    assert {"yours/noisy", "reference/noisy"} <= set(mode._compare_drawer.drawn)  # earlier comparisons stay

    view.open_session(store.create(mode.lesson.pipeline))  # a new session: its comparisons start over
    assert mode._compare_drawer.drawn == {} and mode.compared == {}


# --- helpers ------------------------------------------------------------------------------------------
def test_array_comparison_tables():
    reference = np.array([[800.0, 0.0, 320.0], [0.0, 810.0, 240.0], [0.0, 0.0, 1.0]])
    yours = reference.copy()
    yours[0, 1] = 2.0
    text = array_comparison("K_init", yours, reference)
    assert "largest \\|yours − reference\\| = 2 at [0, 1]" in text
    assert "| [0, 1] | 2 | 0 | 2 |" in text and text.count("\n| [") == 9

    stack = np.zeros((5, 3, 3))
    off = stack.copy()
    off[3, 2, 0] = -0.5
    text = array_comparison("homographies", off, stack)
    assert "Item 3 of 5, the one that differs most" in text and "| [3, 2, 0] | -0.5 | 0 | -0.5 |" in text
    assert text.count("\n| [3,") == 9

    long = np.arange(100.0)
    moved = long.copy()
    moved[[7, 50]] += [1.0, 3.0]
    text = array_comparison("means", moved, long, rows=2)
    assert "The 2 entries that differ most" in text and "| [7] |" in text and "| [50] |" in text

    assert "The shapes differ" in array_comparison("H", np.zeros((2, 3, 3)), np.zeros((3, 3, 3)))
    nan = np.array([1.0, np.nan, 3.0])
    assert "at [1]" in array_comparison("x", nan, np.array([1.0, 2.0, 3.0]))


def test_comparison_markdown_and_side_by_side_state():
    images = ImageSet((Image(np.zeros((4, 4), np.float32)),))
    corners = Points2D(np.zeros((2, 2)), image="images")
    side = SideBySide(step="detect", reference={"corners": corners, "count": np.array(2.0)},
                      student={"corners": corners, "count": np.array(3.0)}, passed=False,
                      message="line one\nline two", printed="debug")
    text = comparison_markdown(side)
    assert text.startswith("✗") and "```\nline one\nline two\n```" in text
    assert "`yours/corners` and `reference/corners`" in text and "| value | 3 | 2 | 1 |" in text
    assert "**Your code printed:**" in text and "debug" in text

    drawn = side_by_side_state(side, {"images": images})
    assert set(drawn) == {"yours/images", "yours/corners", "reference/images", "reference/corners"}
    assert drawn["yours/corners"].image == "yours/images" and drawn["yours/images"] is images
    assert side_by_side_state(side, {}) == {}  # nothing to draw the points on


def test_uploads_are_checked_like_rest_submissions():
    assert upload_text("mine.py", "x = 1\n".encode("utf-8-sig")) == "x = 1\n"
    for name, content, kind in (("mine.txt", b"x = 1\n", "unsupported_media_type"),
                                ("mine.py", b"", "invalid_value"), ("", b"x", "invalid_value"),
                                ("mine.py", b"x\x00", "unsupported_media_type"),
                                ("mine.py", b"\xff\xfe", "unsupported_media_type"),
                                ("mine.py", b"x" * (DEFAULT_MAX_SUBMISSION_BYTES + 1), "capacity")):
        with pytest.raises(LabError) as caught:
            upload_text(name, content)
        assert caught.value.kind == kind, (name, content[:10])


def test_the_viewer_app_offers_the_lessons_folder_by_default():
    assert isinstance(ViewerApp().lessons, LessonCatalog)
    assert ViewerApp(lessons=False).lessons is None
    catalog = LessonCatalog(FIXTURES / "lessons")
    assert ViewerApp(lessons=catalog).lessons is catalog
