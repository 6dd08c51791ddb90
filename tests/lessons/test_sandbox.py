"""The sandbox on its own: calls, values, limits, isolation, and what happens when the child misbehaves."""

from __future__ import annotations

import os
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from lab.core import Image, ImageSet, Points2D
from lab.lessons.format import Limits
from lab.lessons.isolation import WORKDIR, Isolation
from lab.lessons.sandbox import WORKDIR_PREFIX, Sandbox, SubmissionFailure, remove_stale_workdirs

FAST = Limits(call_timeout_s=3.0, cpu_seconds=5.0, memory_mb=300.0, output_kb=4.0, result_mb=1.0, file_size_mb=1.0)

SOURCE = '''
import os
import sys
import numpy as np
from lab.core import Image, ImageSet, Points2D

print("loaded")

def double(x, *, factor=2):
    print("doubling", x.shape)
    return x * factor

def brighten(images):
    return ImageSet(tuple(Image(np.clip(im.pixels + 0.5, 0, 1), im.name) for im in images.images))

def draw(*, rng):
    return rng.normal(size=4)

def facts():
    import resource
    return {"env": dict(os.environ), "cwd": os.getcwd(), "files": sorted(os.listdir(".")),
            "uid": os.getuid(), "path": list(sys.path),
            "limits": {name: resource.getrlimit(getattr(resource, name)) for name in
                       ("RLIMIT_CPU", "RLIMIT_AS", "RLIMIT_FSIZE", "RLIMIT_NOFILE", "RLIMIT_NPROC", "RLIMIT_CORE")}}

def forged_points():
    p = Points2D(np.zeros((2, 2)))
    object.__setattr__(p, "xy", np.array([[np.nan, 0.0], [1.0, 2.0]]))
    return p

def loop():
    while True:
        pass

def write_here():
    with open("notes.txt", "w") as handle:
        handle.write("mine")
    return open("notes.txt").read()
'''


@pytest.fixture()
def sandbox():
    with Sandbox(SOURCE, limits=FAST) as box:
        box.start()
        yield box


def test_call_returns_the_value_and_what_was_printed(sandbox):
    result = sandbox.call("double", (np.arange(3.0),), {"factor": 3})
    np.testing.assert_array_equal(result.value, [0.0, 3.0, 6.0])
    assert result.printed == "doubling (3,)\n" and result.flooded == 0
    assert sandbox.load_printed == "loaded\n"
    assert set(sandbox.functions) >= {"double", "brighten", "draw", "facts"}
    assert sandbox.functions["double"] == {"positional": ["x"], "keyword": ["factor"], "varargs": False}


def test_typed_values_and_random_generators_travel_both_ways(sandbox):
    images = ImageSet((Image(np.zeros((2, 3), np.float32), "a"), Image(np.ones((2, 3), np.float32), "b")))
    out = sandbox.call("brighten", (images,)).value
    assert isinstance(out, ImageSet) and out.names == ("a", "b")
    np.testing.assert_allclose(out[0].pixels, 0.5)
    expected = np.random.default_rng(7).normal(size=4)
    np.testing.assert_array_equal(sandbox.call("draw", (), {"rng": np.random.default_rng(7)}).value, expected)


def test_typed_values_are_rebuilt_so_their_checks_run(sandbox):
    with pytest.raises(SubmissionFailure) as caught:
        sandbox.call("forged_points")
    assert caught.value.kind == "protocol" and "NaN" in caught.value.message


def test_the_child_runs_scrubbed_in_an_empty_directory_with_limits(sandbox, monkeypatch):
    facts = sandbox.call("facts").value
    assert "VISION_LAB_SECRET" not in facts["env"] and set(facts["env"]) <= {
        "PATH", "HOME", "TMPDIR", "LANG", "LC_ALL", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
        "NUMEXPR_NUM_THREADS", "OPENCV_FOR_THREADS_NUM", "NUMBA_NUM_THREADS", "LC_CTYPE",
        "PWD",  # set by bubblewrap's --chdir
        "LD_LIBRARY_PATH"}  # set by OpenCV's own start-up inside the child, not inherited
    assert facts["files"] == ["submission.py"] and facts["cwd"] == facts["env"]["HOME"] == WORKDIR
    assert facts["uid"] != 0
    limits = facts["limits"]
    assert limits["RLIMIT_CORE"] == (0, 0)
    assert limits["RLIMIT_FSIZE"][0] == 2**20
    assert limits["RLIMIT_NOFILE"][0] <= 64
    assert limits["RLIMIT_NPROC"][0] == 1
    assert limits["RLIMIT_CPU"][0] <= 5 + 10  # the budget plus what start-up used
    assert 0 < limits["RLIMIT_AS"][0] < 8 * 2**30


def test_the_parent_environment_does_not_leak(monkeypatch):
    monkeypatch.setenv("VISION_LAB_SECRET", "hunter2")
    with Sandbox(SOURCE, limits=FAST) as box:
        assert "VISION_LAB_SECRET" not in box.call("facts").value["env"]


def _host_workdirs() -> set[Path]:
    return set(Path(tempfile.gettempdir()).glob(WORKDIR_PREFIX + "*"))


def test_files_in_its_own_directory_are_fine_and_gone_with_it():
    before = _host_workdirs()
    with Sandbox(SOURCE, limits=FAST) as box:
        assert box.call("write_here").value == "mine"
        assert "notes.txt" in box.call("facts").value["files"]
        assert _host_workdirs() == before  # a tmpfs inside the sandbox, nothing on the host
    with Sandbox(SOURCE, limits=FAST) as box:
        assert box.call("facts").value["files"] == ["submission.py"]  # a fresh directory every time


def test_unsafe_mode_uses_a_host_folder_and_removes_it():
    with Sandbox(SOURCE, limits=FAST, isolation=Isolation(mode="unsafe")) as box:
        assert box.call("write_here").value == "mine"
        workdir = Path(box.call("facts").value["cwd"])
        assert workdir.name.startswith(WORKDIR_PREFIX) and (workdir / "notes.txt").exists()
    assert not workdir.exists()


def test_stale_unsafe_folders_of_dead_processes_are_removed(tmp_path):
    dead = _dead_pid()
    (tmp_path / f"{WORKDIR_PREFIX}{dead}-abc").mkdir()
    (tmp_path / f"{WORKDIR_PREFIX}{dead}-abc" / "submission.py").write_text("secret = 1\n")
    (tmp_path / f"{WORKDIR_PREFIX}{os.getpid()}-mine").mkdir()
    assert remove_stale_workdirs(str(tmp_path)) == 1
    assert [p.name for p in tmp_path.iterdir()] == [f"{WORKDIR_PREFIX}{os.getpid()}-mine"]


def _dead_pid() -> int:
    process = subprocess.Popen(["true"])
    process.wait()
    return process.pid


def test_a_timeout_kills_the_process_group_and_the_next_call_starts_afresh(sandbox):
    first = sandbox.pid
    started = time.monotonic()
    with pytest.raises(SubmissionFailure) as caught:
        sandbox.call("loop", timeout=1.0)
    assert caught.value.kind == "timeout" and "1 s" in caught.value.message
    assert time.monotonic() - started < 6.0  # contained: the call returns soon after its limit
    assert not Path(f"/proc/{first}").exists()
    assert sandbox.call("double", (np.ones(2),)).value.tolist() == [2.0, 2.0]
    assert sandbox.starts == 2 and sandbox.pid != first


def test_cpu_limit_stops_a_busy_loop():
    limits = FAST.replace(cpu_seconds=1.0, call_timeout_s=60.0)
    with Sandbox(SOURCE, limits=limits) as box:
        started = time.monotonic()
        with pytest.raises(SubmissionFailure) as caught:
            box.call("loop")
        assert caught.value.kind == "cpu" and "CPU time" in caught.value.message
        assert time.monotonic() - started < 50.0  # before the 60 s wall clock, even on a loaded machine


def test_unknown_function_and_load_failures():
    with Sandbox(SOURCE, limits=FAST) as box:
        with pytest.raises(SubmissionFailure) as caught:
            box.call("triple", (1,))
        assert caught.value.kind == "missing" and "no function 'triple'" in caught.value.message
    with pytest.raises(SubmissionFailure) as caught:
        Sandbox("def f(:\n", limits=FAST).start()
    assert caught.value.kind == "load" and "SyntaxError" in caught.value.message
    with pytest.raises(SubmissionFailure) as caught:
        Sandbox("raise RuntimeError('at import')\n", limits=FAST).start()
    assert caught.value.kind == "load" and "at import" in caught.value.message and "line 1" in caught.value.traceback


def test_close_twice_and_no_process_left():
    box = Sandbox(SOURCE, limits=FAST)
    box.start()
    pid = box.pid
    box.close()
    box.close()
    assert not Path(f"/proc/{pid}").exists()


def test_points_round_trip(sandbox):
    # a plain typed value returned unchanged keeps its optional fields
    source = "import numpy as np\nfrom lab.core import Points2D\ndef same(p):\n    return p\n"
    with Sandbox(source, limits=FAST) as box:
        points = Points2D(np.array([[1.0, 2.0]]), view=np.array([3]), ids=np.array([4]))
        out = box.call("same", (points,)).value
        assert out.view.tolist() == [3] and out.ids.tolist() == [4]


def test_a_child_killed_by_a_signal_is_reported_as_such():
    source = ("import faulthandler, signal, numpy as np\n"
              "def segfault():\n    faulthandler._sigsegv()\n"
              "def hang_up():\n    signal.raise_signal(signal.SIGHUP)\n")
    with Sandbox(source, limits=FAST) as box:
        with pytest.raises(SubmissionFailure) as caught:
            box.call("segfault")
        assert caught.value.kind == "crashed" and "killed by SIGSEGV" in caught.value.message
        assert "memory limit is 300 MB" in caught.value.message  # the hint: a library out of memory does this
        with pytest.raises(SubmissionFailure) as caught:
            box.call("hang_up")
        assert caught.value.kind == "crashed" and "killed by SIGHUP" in caught.value.message
        assert "CPU" not in caught.value.message


def test_a_sandbox_started_from_a_thread_that_ends_stays_alive():
    # --die-with-parent follows the thread that started the child: every child is started from one long-lived thread
    import threading

    with Sandbox(SOURCE, limits=FAST) as box:
        starter = threading.Thread(target=box.start)
        starter.start()
        starter.join()
        time.sleep(0.3)
        assert box.alive and box.starts == 1
        assert box.call("double", (np.ones(2),)).value.tolist() == [2.0, 2.0] and box.starts == 1
