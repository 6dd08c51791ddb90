"""The attacks of issue 13, each contained by the operating-system sandbox even with the audit hook switched off.

Every submission here first switches off the audit hook from inside (the one line that used to
disable the whole sandbox), so what holds is bubblewrap: the namespaces, the read-only root without
the lab's reference code, the unprivileged user, the data-only wire format. Checked at three levels:
the sandbox on its own (what the code can see and do), the grader (it scores 0 with a clear
message), and the REST service (other submissions untouched, the token never shown, the server up,
nothing outliving grading).
"""

from __future__ import annotations

import os
import socket
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from lab.api.lessons import build_app
from lab.lessons import isolation
from lab.lessons.format import LessonCatalog, Limits
from lab.lessons.grader import grade
from lab.lessons.sandbox import Sandbox, SubmissionFailure
from lab.lessons.service import LessonService
from lab.lessons.store import SubmissionQueue

from lesson_helpers import (FIXTURES, HOOK_OFF, REPO, HostWatch, host_processes_left, toy_lessons_that_fork,
                            unique_sleep, wait_done)

LIMITS = Limits(call_timeout_s=10.0, cpu_seconds=20.0, memory_mb=400.0, output_kb=8.0, result_mb=4.0,
                file_size_mb=1.0, processes=4)
MARKER = "vision-lab-attack-marker"

ATTACKS = HOOK_OFF + r'''
import os, signal, socket, sqlite3, time

def whoami():
    return {"uid": os.getuid(), "euid": os.geteuid(), "gid": os.getgid(), "pid": os.getpid(),
            "ppid": os.getppid(), "root": sorted(os.listdir("/")), "hostname": os.uname().nodename}

def shell(command):
    return os.system(command)

def read(path):
    try:
        with open(path, "rb") as handle:
            return handle.read(20000).decode("latin-1")
    except Exception as exc:
        return f"refused {type(exc).__name__}: {exc}"

def listing(path):
    try:
        return sorted(os.listdir(path))
    except Exception as exc:
        return f"refused {type(exc).__name__}"

def environ_of_every_process():
    seen = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/environ", "rb") as handle:
                    seen.append(handle.read().decode("latin-1"))
            except Exception:
                pass
    return "\n".join(seen)

def attach(database):
    try:
        connection = sqlite3.connect(":memory:")
        connection.execute(f"ATTACH DATABASE '{database}' AS other")
        connection.execute("UPDATE other.scores SET score = 20")
        connection.commit()
        return "attached"
    except Exception as exc:
        return f"refused {type(exc).__name__}: {exc}"

def file_storage(path):
    import cv2
    try:
        storage = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
        storage.write("x", 1)
        storage.release()
    except Exception as exc:
        return f"refused {type(exc).__name__}"
    return os.path.exists(path)

def symlink_race(target):
    os.symlink(target, "innocent.txt")
    return read("innocent.txt")

def kill_parent():
    results = []
    for pid in (os.getppid(), 1):
        try:
            signal.pidfd_send_signal(os.pidfd_open(pid), signal.SIGKILL)
            results.append(f"sent to {pid}")
        except Exception as exc:
            results.append(f"{pid}: {type(exc).__name__}")
    time.sleep(1)
    return results

def daemon(tag):
    pid = os.fork()
    if pid == 0:
        os.setsid()
        os.execv("/bin/sleep", ["sleep", tag])
    return pid

def fork_bomb():
    children = 0
    try:
        for _ in range(64):
            if os.fork() == 0:
                time.sleep(30)
                os._exit(0)
            children += 1
    except OSError as exc:
        return children, exc.errno
    return children, 0

def connect(port):
    try:
        socket.create_connection(("127.0.0.1", port), timeout=2).close()
        return "connected"
    except Exception as exc:
        return f"refused {type(exc).__name__}"

def forge(kind):
    """Write a reply frame of our own to the grader's pipe, then answer normally."""
    import struct
    fd = int(sys.argv[2])
    if kind == "pickle":   # the frame that segfaulted the old grader: an object array by numpy's reconstructors
        import pickle
        body = pickle.dumps(np.empty(3, dtype=object))
    elif kind == "object_dtype":
        document = b'{"kind":"ok","value":{"$array":[0,24],"dtype":"|O8","shape":[3]}}'
        body = struct.pack(">Q", len(document)) + document + bytes(24)
    elif kind == "lying_shape":
        document = b'{"kind":"ok","value":{"$array":[0,8],"dtype":"<f8","shape":[100000,100000]}}'
        body = struct.pack(">Q", len(document)) + document + bytes(8)
    else:
        body = struct.pack(">Q", 2**40)
    os.write(fd, struct.pack(">Q", len(body)) + body)
    return np.zeros(3)

import numpy as np
'''


@pytest.fixture()
def attacks():
    with Sandbox(ATTACKS, limits=LIMITS) as box:
        box.start()
        yield box


def test_with_the_hook_off_the_child_is_unprivileged_alone_and_sees_no_host(attacks):
    facts = attacks.call("whoami").value
    assert facts["uid"] != 0 and facts["euid"] != 0 and facts["gid"] != 0
    assert facts["ppid"] in (0, 1) and facts["pid"] < 16 and facts["hostname"] == "sandbox"
    lab = isolation.lab_dir()
    # the root holds the system folders, its directory, and only the paths down to Python and the lab
    expected = {"bin", "dev", "etc", "lib", "lib32", "lib64", "libx32", "proc", "sbin", "submission", "usr",
                lab.parts[1], Path(sys.base_prefix).resolve().parts[1], Path(sys.prefix).resolve().parts[1]}
    assert set(facts["root"]) <= expected, set(facts["root"]) - expected
    assert set(attacks.call("listing", ("/etc",)).value) <= {"ld.so.cache", "ld.so.conf", "ld.so.conf.d", "localtime"}
    secret = Path(tempfile.mkdtemp()) / "host-secret.txt"  # beside the lab when it lives under /tmp (CI's clones)
    secret.write_text("host secret")
    try:
        assert attacks.call("read", (str(secret),)).value.startswith("refused FileNotFoundError")
    finally:
        secret.unlink()
        secret.parent.rmdir()
    assert sorted(attacks.call("listing", (str(lab),)).value) == ["__init__.py", "core", "lessons"]
    assert attacks.call("listing", (str(lab / "lessons"),)).value == ["__init__.py", "child.py", "wire.py"]
    for hidden in (lab / "modules" / "calibration" / "steps.py", REPO / "lessons" / "01-calibration" / "tasks.toml",
                   Path("/etc/shadow"), Path("/etc/passwd"), Path("/root/.bash_history")):
        assert attacks.call("read", (str(hidden),)).value.startswith("refused FileNotFoundError"), hidden


def test_shell_commands_run_unprivileged_and_write_nothing_outside(attacks, tmp_path):
    outside = Path(tempfile.gettempdir()) / MARKER
    outside.unlink(missing_ok=True)
    assert attacks.call("shell", (f"touch {outside} {tmp_path}/marker",)).value != 0  # a read-only root
    assert attacks.call("shell", ("id -u > /submission/uid",)).value == 0
    assert not outside.exists() and not (tmp_path / "marker").exists()
    assert attacks.call("read", ("/submission/uid",)).value.strip() not in ("", "0")


def test_the_server_environment_and_token_are_out_of_sight(monkeypatch):
    monkeypatch.setenv("VISION_LAB_INSTRUCTOR_TOKEN", "token-that-must-stay-secret")
    with Sandbox(ATTACKS, limits=LIMITS) as box:
        seen = box.call("environ_of_every_process").value
        assert "token-that-must-stay-secret" not in seen and "VISION_LAB" not in seen
        assert "token-that-must-stay-secret" not in box.call("read", (f"/proc/{os.getppid()}/environ",)).value


def test_sqlite_attach_cannot_reach_the_database(attacks, tmp_path):
    database = tmp_path / "submissions.sqlite"
    with sqlite3.connect(database) as connection:
        connection.execute("CREATE TABLE scores (student TEXT, score REAL)")
        connection.execute("INSERT INTO scores VALUES ('victim', 0)")
    assert attacks.call("attach", (str(database),)).value.startswith("refused")
    with sqlite3.connect(database) as connection:
        assert connection.execute("SELECT score FROM scores").fetchall() == [(0.0,)]


def test_opencv_and_symlinks_cannot_write_or_read_outside(attacks):
    target = Path(tempfile.gettempdir()) / f"{MARKER}.yml"
    target.unlink(missing_ok=True)
    assert attacks.call("file_storage", (str(target),)).value is not True
    assert not target.exists()
    assert attacks.call("file_storage", ("/submission/mine.yml",)).value is True  # its own directory works
    assert attacks.call("symlink_race", ("/etc/shadow",)).value.startswith("refused")


def test_signals_cannot_reach_the_server(attacks):
    me = os.getpid()
    try:  # its parent is pid 1 of its own namespace (bubblewrap's), which ignores signals from inside
        print(attacks.call("kill_parent").value)
    except SubmissionFailure as failure:  # or the sandbox ended: either way the grader is untouched
        assert failure.kind == "crashed"
    assert os.getpid() == me and Path(f"/proc/{me}").exists()
    assert attacks.call("whoami").value["uid"] != 0


def test_nothing_it_starts_outlives_it(attacks):
    tag = f"{time.time() % 1000 + 1000:.6f}"
    attacks.call("daemon", (tag,))
    attacks.close()
    assert host_processes_left(tag) == []


def test_fork_bombs_stop_at_the_process_limit(attacks):
    children, errno = attacks.call("fork_bomb").value
    assert children < LIMITS.processes and errno != 0


def test_no_network_to_the_server(attacks):
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    try:
        assert attacks.call("connect", (listener.getsockname()[1],)).value.startswith("refused")
    finally:
        listener.close()


@pytest.mark.parametrize("kind", ["pickle", "object_dtype", "lying_shape", "huge"])
def test_forged_reply_frames_are_a_failed_call_never_a_crash(attacks, kind):
    with pytest.raises(SubmissionFailure) as caught:
        attacks.call("forge", (kind,))
    assert caught.value.kind == "protocol"
    assert attacks.call("whoami").value["uid"] != 0  # the grader carries on with a fresh child


def test_the_reference_cannot_be_imported_with_the_hook_off(calibration_lesson):
    cheat = HOOK_OFF + ("from lab.modules.calibration import estimate_homographies, "
                        "estimate_intrinsics, estimate_extrinsics\n")
    report = grade(calibration_lesson, cheat, seed=3)
    assert report.score == 0
    assert "No module named 'lab.modules'" in report.tests[0].output


# --- through the REST service ---------------------------------------------------------------------
SERVICE_ATTACK = HOOK_OFF + r'''
import os, signal, sqlite3, glob, time
import numpy as np

def make_noisy(images, *, sigma=0.05, rng):
    seen = []
    for path in glob.glob("/proc/*/environ"):
        try:
            seen.append(open(path, "rb").read().decode("latin-1"))
        except Exception:
            pass
    print("\n".join(seen))
    for database in DATABASES:
        try:
            connection = sqlite3.connect(":memory:")
            connection.execute(f"ATTACH DATABASE '{database}' AS other")
            connection.execute("UPDATE other.submissions SET score = 6")
            connection.commit()
        except Exception as exc:
            print("attach refused", exc)
    os.system("touch MARKER; sleep DAEMON_SECONDS &")
    try:
        signal.pidfd_send_signal(os.pidfd_open(os.getppid()), signal.SIGKILL)
    except OSError as exc:  # refused (the namespace's init): the sleep below must happen either way
        print("kill refused", exc)
    time.sleep(1.0)  # the test sees its daemon on the host meanwhile: the check below can fail
    return images

def mean_intensity(noisy, *, scale=1):
    return np.array([os.getuid()], dtype=float)
'''


def test_over_rest_an_attack_scores_zero_and_changes_nothing_else(tmp_path, monkeypatch):
    monkeypatch.setenv("VISION_LAB_INSTRUCTOR_TOKEN", "token-that-must-stay-secret")
    database = tmp_path / "db.sqlite"
    marker = Path(tempfile.gettempdir()) / MARKER
    marker.unlink(missing_ok=True)
    lessons = toy_lessons_that_fork(tmp_path / "lessons", LIMITS.processes)  # else it cannot start a daemon
    service = LessonService(catalog=LessonCatalog(lessons), queue=SubmissionQueue(f"sqlite:///{database}"),
                            poll_s=0.1, instructor_token="token-that-must-stay-secret")
    # its daemon is told from every other process on the machine by a duration of its own: a plain "sleep 300"
    # (a shell of someone else on a shared machine; here a decoy) is not the sandbox's leftover
    seconds, daemon = unique_sleep()
    attack = SERVICE_ATTACK.replace("DATABASES", repr([str(database), str(database.resolve())])) \
        .replace("MARKER", str(marker)).replace("DAEMON_SECONDS", seconds)
    decoy = subprocess.Popen(["sleep", "300"])
    try:
        with TestClient(build_app(service)) as client, HostWatch(daemon) as watch:
            victim = _submit(client, (FIXTURES / "lessons" / "00-toy" / "starter.py").read_text())
            victim_done = wait_done(client, victim)
            attacker_done = wait_done(client, _submit(client, attack), timeout=60.0)
            assert attacker_done["status"] == "done" and attacker_done["score"] == 0
            assert watch.seen, "the attack's daemon never ran on the host: the check below would prove nothing"
            assert host_processes_left(daemon) == []  # gone with its grading, the server still up
            assert wait_done(client, victim)["score"] == victim_done["score"] == 0
            assert client.get("/api/lessons").status_code == 200
            everything = client.get(f"/api/submissions/{victim}").text + client.get(
                f"/api/lessons/00-toy/submissions", headers={"Authorization": "Bearer token-that-must-stay-secret"}).text
            assert "token-that-must-stay-secret" not in everything + str(attacker_done)
        assert not marker.exists()
        assert decoy.poll() is None  # what is not the attack's is left alone, and not mistaken for it
    finally:
        decoy.kill()
        decoy.wait(timeout=10)


def _submit(client, source: str) -> str:
    response = client.post("/api/lessons/00-toy/submissions", files={"file": ("mine.py", source.encode(), "text/x-python")})
    assert response.status_code == 202, response.text
    return response.json()["id"]


def test_without_bubblewrap_grading_is_refused_with_the_fix(toy_lesson, monkeypatch):
    monkeypatch.setattr(isolation, "default_isolation", lambda: isolation.Isolation(bwrap="/nonexistent/bwrap"))
    with pytest.raises(isolation.SandboxUnavailable) as caught:
        grade(toy_lesson, "def make_noisy(images, *, sigma=0.05, rng):\n    return images\n")
    assert "bubblewrap" in caught.value.reason and "--unsafe-sandbox" in caught.value.reason
    assert caught.value.status == 503


def test_without_bubblewrap_the_service_refuses_submissions_and_loses_none(tmp_path, monkeypatch):
    monkeypatch.setattr(isolation, "default_isolation", lambda: isolation.Isolation(bwrap="/nonexistent/bwrap"))
    service = LessonService(catalog=LessonCatalog(FIXTURES / "lessons"),
                            queue=SubmissionQueue(f"sqlite:///{tmp_path / 'db.sqlite'}"), poll_s=0.1)
    with TestClient(build_app(service)) as client:
        response = client.post("/api/lessons/00-toy/submissions", files={"file": ("mine.py", b"x = 1\n", "text/x-python")})
        assert response.status_code == 503
        body = response.json()
        assert body["error"] == "sandbox_unavailable" and "apt-get install bubblewrap" in body["reason"]
        assert client.get("/api/lessons").status_code == 200
