"""The parent side of the sandbox: run a student's file in a contained child process and call its functions.

One :class:`Sandbox` is one submission: a child process (:mod:`lab.lessons.child`) started with
``python -I`` inside the operating-system sandbox of :mod:`lab.lessons.isolation` (bubblewrap:
its own PID, mount, network, IPC and UTS namespaces, a read-only root holding only the Python
installation and ``lab/core``, an empty size-capped tmpfs as its directory, an unprivileged user),
a scrubbed environment, and inputs and outputs passed through two pipes. The child sets its own
resource limits and installs an audit hook before any student code runs (defence in depth).
Without bubblewrap a sandbox refuses to start (:class:`~lab.lessons.isolation.SandboxUnavailable`)
unless the operator allowed ``--unsafe-sandbox`` (trusted code: the audit hook alone, a temporary
folder on the host).

The parent never trusts what comes back: replies are read with a deadline (a call that does not
return in time gets the whole namespace killed), their size is capped before anything is read,
they are data only (:mod:`lab.lessons.wire`: JSON and numeric buffers, nothing is unpickled) and
typed values are rebuilt through their constructors so their own checks run. A malformed reply is
a failed call, never a crash. What the code prints is kept up to a cap.

A call that does not produce a value raises :class:`SubmissionFailure` whose ``kind`` says why:
``raised`` (the code raised), ``blocked`` (it tried something the sandbox refuses), ``memory``,
``timeout``, ``cpu``, ``crashed`` (the process died; the message names the signal), ``protocol``
(a value that cannot come back, or a malformed reply), ``load`` (the file could not be loaded),
``missing`` (no such function).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import io
import os
import select
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lab.lessons import isolation as isolation_module
from lab.lessons.format import Limits
from lab.lessons.isolation import WORKDIR, Isolation, default_isolation, lab_dir, python_roots
from lab.lessons.wire import FRAME as HEADER
from lab.lessons.wire import WireError, decode, encode, frame

#: Modules the child imports before it locks itself down (the types step inputs use).
PRELOAD = ("lab.core.values", "lab.core.errors")

#: Parts of the lab a submission may import (values and errors the signatures use).
ALLOWED_LAB = ("lab.core",)

#: Host folders of ``--unsafe-sandbox`` runs start with this (and the server's pid), so a restart can remove
#: what a crash left behind (:func:`remove_stale_workdirs`).
WORKDIR_PREFIX = "vision-lab-submission-"

_BOOT = ("import sys; sys.path.append({root!r}); from lab.lessons.child import main; main()")


class SubmissionFailure(Exception):
    """A call of the student's code that produced no value, and why (``kind``)."""

    def __init__(self, kind: str, message: str, *, type_name: str = "", traceback: str = "",
                 printed: str = "", violations: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.kind = kind
        self.message = message
        self.type_name = type_name
        self.traceback = traceback
        self.printed = printed
        self.violations = tuple(violations)


@dataclass(frozen=True)
class CallResult:
    """What a call returned, what it printed, and what it tried that the sandbox refused."""

    value: Any
    printed: str = ""
    violations: tuple[str, ...] = ()
    seconds: float = 0.0
    flooded: int = 0  # characters printed beyond the cap during the call


@dataclass
class _Drain:
    """Keeps the first ``limit`` bytes the child writes to its stdout/stderr descriptors, discards the
    rest."""

    limit: int
    data: bytearray = field(default_factory=bytearray)
    dropped: int = 0
    total: int = 0

    def run(self, stream: io.BufferedReader) -> None:
        try:
            while True:
                chunk = stream.read1(65536)
                if not chunk:
                    return
                self.total += len(chunk)
                room = self.limit - len(self.data)
                if room > 0:
                    self.data += chunk[:room]
                self.dropped += max(0, len(chunk) - max(room, 0))
        except (OSError, ValueError):
            return

    def text(self) -> str:
        text = self.data.decode("utf-8", "replace")
        return text + (f"\n... ({self.dropped} more bytes not kept)" if self.dropped else "")


def _nobody() -> tuple[int, int] | None:
    """``--unsafe-sandbox`` only: (uid, gid) of ``nobody`` when running as root and it can run Python,
    else None."""
    if os.geteuid() != 0:
        return None
    try:
        import pwd

        entry = pwd.getpwnam("nobody")
    except (KeyError, ImportError):
        return None
    paths = [Path(sys.executable).resolve(), *(Path(p) for p in python_roots()), lab_dir()]
    return (entry.pw_uid, entry.pw_gid) if all(_world_usable(p) for p in paths) else None


def _world_usable(path: Path) -> bool:
    """Every folder above ``path`` can be entered by anyone and ``path`` can be read by anyone."""
    try:
        for parent in list(path.parents)[::-1]:
            if not os.stat(parent).st_mode & stat.S_IXOTH:
                return False
        return bool(os.stat(path).st_mode & stat.S_IROTH)
    except OSError:
        return False


def sandbox_paths(extra_deny: tuple[str, ...] = ()) -> dict[str, list[str]]:
    """What the audit hook lets the child read (the Python installation, lab/core) and never read (the
    rest)."""
    lab = lab_dir()
    from lab.lessons.format import lessons_root

    deny = [str(lab), str(lessons_root()), str(lab.parent / "tests"), *extra_deny]
    allow = [str(lab / "__init__.py"), str(lab / "core"), str(lab / "lessons" / "child.py"),
             str(lab / "lessons" / "wire.py"), os.devnull, "/dev/urandom"]
    return {"read_roots": python_roots(), "deny_roots": deny, "allow_roots": allow}


def remove_stale_workdirs(root: str | None = None) -> int:
    """Remove the ``--unsafe-sandbox`` folders of processes that are gone (a crash); returns how many."""
    removed = 0
    base = Path(root or tempfile.gettempdir())
    for path in base.glob(WORKDIR_PREFIX + "*"):
        owner = path.name[len(WORKDIR_PREFIX):].split("-", 1)[0]
        if owner.isdigit() and (int(owner) == os.getpid() or _process_alive(int(owner))):
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed += 1
    return removed


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


_launcher: concurrent.futures.ThreadPoolExecutor | None = None
_launcher_lock = threading.Lock()


def _launch(command: list[str], **options: Any) -> subprocess.Popen:
    """``subprocess.Popen`` from one long-lived thread of this process.

    bubblewrap's ``--die-with-parent`` is the kernel's parent-death signal, which fires when the
    *thread* that started the child ends, not the process: a sandbox started from a short-lived
    thread (a viewer upload, a request) would die with it. Starting every child from this one
    thread ties the sandboxes' lifetime to the process, as meant.
    """
    global _launcher
    with _launcher_lock:
        if _launcher is None:
            _launcher = concurrent.futures.ThreadPoolExecutor(max_workers=1,
                                                              thread_name_prefix="sandbox-launcher")
        launcher = _launcher

    def popen() -> subprocess.Popen:
        return subprocess.Popen(command, **options)

    return launcher.submit(popen).result()


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


# --- reading the child's replies ----------------------------------------------------------------
def _text(message: dict[str, Any], key: str, limit: int = 200_000) -> str:
    value = message.get(key, "")
    if not isinstance(value, str):
        raise WireError(f"a reply whose {key!r} is not text")
    return value[:limit]


def _texts(message: dict[str, Any], key: str) -> tuple[str, ...]:
    value = message.get(key, [])
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise WireError(f"a reply whose {key!r} is not a list of text")
    return tuple(v[:500] for v in value[:50])


def _failure_of(message: dict[str, Any]) -> SubmissionFailure:
    failure = message.get("failure")
    if not isinstance(failure, dict):
        raise WireError("an error reply without its failure")
    kind = _text(failure, "kind", 20)
    if kind not in ("raised", "blocked", "memory", "protocol"):
        raise WireError(f"a failure of unknown kind {kind!r}")
    return SubmissionFailure(kind, _text(failure, "message", 4000),
                             type_name=_text(failure, "type_name", 200),
                             traceback=_text(failure, "traceback", 8000), printed=_text(failure, "printed"),
                             violations=_texts(failure, "violations"))


def _functions_of(message: dict[str, Any]) -> dict[str, dict[str, Any]]:
    functions = message.get("functions")
    if not isinstance(functions, dict) or len(functions) > 1000:
        raise WireError("a ready reply without its functions")
    checked: dict[str, dict[str, Any]] = {}
    for name, signature in functions.items():
        if not (isinstance(name, str) and isinstance(signature, dict)
                and all(isinstance(signature.get(k), list) and all(isinstance(v, str) for v in signature[k])
                        for k in ("positional", "keyword"))
                and isinstance(signature.get("varargs"), bool)):
            raise WireError("a malformed function signature")
        checked[name] = {"positional": list(signature["positional"]), "keyword": list(signature["keyword"]),
                         "varargs": signature["varargs"]}
    return checked


def decode_reply(payload: bytes) -> dict[str, Any]:
    """A child's reply, checked to be a dict with a known ``kind``; raises :class:`WireError`."""
    message = decode(payload)
    if not isinstance(message, dict) or message.get("kind") not in ("ready", "load_error", "ok", "error"):
        raise WireError("a malformed reply")
    return message


# --- the sandbox --------------------------------------------------------------------------------
class Sandbox:
    """A student's file loaded in a contained child process; :meth:`call` runs one of its functions.

    Use as a context manager or call :meth:`close`. After the child dies (a timeout, the CPU
    limit, a crash) the next :meth:`call` starts a fresh one. ``isolation`` defaults to
    :func:`~lab.lessons.isolation.default_isolation` (bubblewrap unless the operator allowed
    ``--unsafe-sandbox``); :meth:`start` raises
    :class:`~lab.lessons.isolation.SandboxUnavailable` when it cannot run here.
    """

    def __init__(self, source: str, *, limits: Limits | None = None, filename: str = "submission.py",
                 preload: tuple[str, ...] = PRELOAD, deny: tuple[str, ...] = (),
                 isolation: Isolation | None = None) -> None:
        self.source = source
        self.limits = limits or Limits()
        self.filename = filename
        self.preload = preload
        self.deny = deny
        self.isolation = isolation or default_isolation()
        self.functions: dict[str, dict[str, Any]] = {}
        self.load_printed = ""
        self.starts = 0
        self.pids: list[int] = []  # every child started (tests check none outlives the sandbox)
        self._process: subprocess.Popen | None = None
        self._workdir: str | None = None  # the host folder (--unsafe-sandbox only)
        self._request_fd: int | None = None
        self._response_fd: int | None = None
        self._drain: _Drain | None = None
        self._drain_thread: threading.Thread | None = None
        self._killed = False
        self._timeout = 0.0
        self._cpu_seconds = 0.0
        self._max_rss_mb = 0.0

    # --- lifecycle ---------------------------------------------------------------------------
    def __enter__(self) -> Sandbox:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def alive(self) -> bool:
        return self._process is not None and self._process.poll() is None

    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    def _command(self, request_read: int, response_write: int) -> tuple[list[str], dict[str, str], str, str]:
        """The child's command line, environment, working directory inside and outside."""
        threads = "1"
        bwrap = self.isolation.mode == "bwrap"
        if bwrap:
            inside, outside = WORKDIR, "/"
        else:
            outside = inside = tempfile.mkdtemp(prefix=f"{WORKDIR_PREFIX}{os.getpid()}-")
            self._workdir = outside
            nobody = _nobody()
            if nobody is not None:
                os.chown(outside, *nobody)
            os.chmod(outside, 0o700)
        env = {"PATH": "/usr/bin:/bin", "HOME": inside, "TMPDIR": inside, "LANG": "C.UTF-8",
               "LC_ALL": "C.UTF-8", "OMP_NUM_THREADS": threads, "OPENBLAS_NUM_THREADS": threads,
               "MKL_NUM_THREADS": threads, "NUMEXPR_NUM_THREADS": threads, "OPENCV_FOR_THREADS_NUM": threads,
               "NUMBA_NUM_THREADS": threads}
        command = [sys.executable, "-I", "-B", "-c", _BOOT.format(root=str(lab_dir().parent)),
                   str(request_read), str(response_write)]
        if bwrap:
            command = isolation_module.bwrap_command(command, isolation=self.isolation, env=env)
            env = {"PATH": env["PATH"], "LANG": env["LANG"]}
        return command, env, inside, outside

    def start(self, *, timeout: float | None = None) -> dict[str, dict[str, Any]]:
        """Start the child and load the file; returns its functions, raises SubmissionFailure(kind="load")."""
        isolation_module.check(self.isolation)
        self.close()
        self.starts += 1
        timeout = self.limits.call_timeout_s if timeout is None else timeout
        deadline = time.monotonic() + max(timeout, 0.0)
        self._timeout = timeout
        request_read, request_write = os.pipe()
        response_read, response_write = os.pipe()
        try:
            command, env, inside, outside = self._command(request_read, response_write)
            self._process = _launch(
                command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                cwd=outside, env=env, pass_fds=(request_read, response_write), start_new_session=True,
                close_fds=True)
        except BaseException:
            for fd in (request_write, response_read):
                os.close(fd)
            raise
        finally:
            os.close(request_read)
            os.close(response_write)
        self.pids.append(self._process.pid)
        self._request_fd, self._response_fd = request_write, response_read
        os.set_blocking(request_write, False)
        self._killed = False
        self._cpu_seconds = self._max_rss_mb = 0.0
        self._drain = _Drain(int(self.limits.output_kb * 1024))
        self._drain_thread = threading.Thread(target=self._drain.run, args=(self._process.stdout,),
                                              daemon=True, name="sandbox-output")
        self._drain_thread.start()
        limits = {k: float(v) for k, v in dataclasses.asdict(self.limits).items()}
        setup = {"workdir": inside, "source": self.source, "filename": self.filename,
                 "preload": list(self.preload), "limits": limits,
                 "nobody": None if self.isolation.mode == "bwrap" else _nobody(),
                 "allowed_lab": list(ALLOWED_LAB), "output_chars": int(self.limits.output_kb * 1024),
                 **sandbox_paths(self.deny)}
        try:
            self._send(encode(setup), deadline)
            reply = self._receive(deadline, what="loading your file")
            if reply["kind"] == "load_error":
                failure = _failure_of(reply)
            elif reply["kind"] == "ready":
                self.functions = _functions_of(reply)
                self.load_printed = _text(reply, "printed")
                return self.functions
            else:
                raise WireError("a reply out of turn")
        except SubmissionFailure as error:  # not named failure: that is the load error read above
            self.kill()
            raise SubmissionFailure("load", f"your file could not be loaded: {error.message}",
                                    printed=error.printed) from None
        except WireError as exc:
            self.kill()
            raise SubmissionFailure("load", f"your file could not be loaded: the sandbox sent "
                                            f"{exc}") from None
        self.close()
        reason = ("it tried something the sandbox does not allow" if failure.kind == "blocked"
                  else f"it raised {failure.type_name}")
        raise SubmissionFailure("load", f"your file could not be loaded: {reason}: {failure.message}",
                                type_name=failure.type_name, traceback=failure.traceback,
                                printed=failure.printed, violations=failure.violations)

    def _reap(self, timeout: float) -> int | None:
        """Wait up to ``timeout`` s for the child; its exit code (negative: a signal), with CPU time and
        peak memory."""
        process = self._process
        if process is None:
            return None
        if process.returncode is not None:
            return process.returncode
        end = time.monotonic() + timeout
        while True:
            try:
                pid, status, usage = os.wait4(process.pid, os.WNOHANG)
            except ChildProcessError:  # reaped already by Popen.poll()
                code = process.poll()
                return None if code is None else self._signal_code(code)
            if pid:
                code = self._signal_code(os.waitstatus_to_exitcode(status))
                process.returncode = code
                self._cpu_seconds = usage.ru_utime + usage.ru_stime
                self._max_rss_mb = usage.ru_maxrss / 1024
                return code
            if time.monotonic() >= end:
                return None
            time.sleep(0.01)

    def _signal_code(self, code: int) -> int:
        """An exit code with bubblewrap's 128 + N turned into -N, as for a child killed by signal N."""
        return 128 - code if self.isolation.mode == "bwrap" and code > 128 else code

    def kill(self) -> None:
        """Kill the child's whole process group; under bubblewrap its namespace dies with it."""
        process = self._process
        if process is None:
            return
        self._killed = True
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(process.pid, signal.SIGKILL)
        self._reap(10)

    def close(self) -> None:
        """Stop the child and remove its directory (safe to call twice)."""
        if self._process is not None:
            for fd_name in ("_request_fd", "_response_fd"):
                fd = getattr(self, fd_name)
                if fd is not None:
                    with contextlib.suppress(OSError):
                        os.close(fd)
                    setattr(self, fd_name, None)
            if self._reap(0.5) is None:  # it exits on its own when its request pipe closes
                self.kill()
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self._process.pid, signal.SIGKILL)  # anything it left behind in its group
            if self._process.stdout is not None:
                self._process.stdout.close()
            if self._drain_thread is not None:
                self._drain_thread.join(timeout=2)
            self._process = None
        if self._workdir is not None:
            shutil.rmtree(self._workdir, ignore_errors=True)
            self._workdir = None

    def output(self) -> str:
        """What the child wrote straight to its stdout/stderr descriptors (capped)."""
        return self._drain.text() if self._drain is not None else ""

    # --- calls -------------------------------------------------------------------------------
    def call(self, name: str, args: tuple = (), kwargs: dict[str, Any] | None = None, *,
             timeout: float | None = None) -> CallResult:
        """Run ``name(*args, **kwargs)`` in the child; raises :class:`SubmissionFailure`."""
        timeout = self.limits.call_timeout_s if timeout is None else timeout
        started = time.monotonic()
        if not self.alive:
            self.start(timeout=timeout)
        if name not in self.functions:
            raise SubmissionFailure("missing", f"your file defines no function {name!r}"
                                    + (f"; it defines {sorted(self.functions)}" if self.functions else ""))
        deadline = started + max(timeout, 0.0)
        self._timeout = timeout
        raw_before = self._drain.total if self._drain is not None else 0
        self._send(encode({"kind": "call", "name": name, "args": tuple(args), "kwargs": dict(kwargs or {})}),
                   deadline)
        reply = self._receive(deadline, what=f"{name}()")
        seconds = time.monotonic() - started
        try:
            if reply["kind"] == "error":
                raise _failure_of(reply)
            if reply["kind"] != "ok" or "value" not in reply:
                raise WireError("a reply out of turn")
            printed, violations = _text(reply, "printed"), _texts(reply, "violations")
            dropped = reply.get("dropped", 0)
            if not isinstance(dropped, int) or isinstance(dropped, bool):
                raise WireError("a malformed reply")
        except WireError as exc:
            self.kill()
            raise SubmissionFailure("protocol", f"{name}() got a malformed reply from the sandbox ({exc}); "
                                                "did your code write to the grader's pipe?") from None
        raw = (self._drain.total if self._drain is not None else 0) - raw_before
        cap = int(self.limits.output_kb * 1024)
        flooded = max(0, dropped) + max(0, raw - cap)
        if raw:
            printed = f"{printed}\n{self.output()}" if printed else self.output()
        return CallResult(reply["value"], printed, violations, seconds, flooded)

    def _send(self, payload: bytes, deadline: float) -> None:
        data = memoryview(frame(payload))
        fd = self._request_fd
        assert fd is not None
        while data:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.kill()
                raise self._timeout_failure("sending the inputs")
            _, writable, _ = select.select([], [fd], [], remaining)
            if not writable:
                continue
            try:
                written = os.write(fd, data)
            except BlockingIOError:
                continue
            except (BrokenPipeError, OSError):
                raise self._death() from None
            data = data[written:]

    def _receive(self, deadline: float, *, what: str) -> dict[str, Any]:
        header = self._read(HEADER.size, deadline, what)
        (size,) = HEADER.unpack(header)
        limit = int(self.limits.result_mb * 2**20)
        if size > limit:
            self.kill()
            raise SubmissionFailure("protocol", f"{what} returned {size / 2**20:.1f} MB of data; the limit "
                                                f"is {self.limits.result_mb:g} MB")
        payload = self._read(size, deadline, what)
        try:
            return decode_reply(payload)
        except WireError as exc:
            self.kill()
            raise SubmissionFailure("protocol", f"{what} returned a value the grader does not accept "
                                                f"({exc}); return numpy arrays of numbers, numbers, or the "
                                                "lab.core values the signature names") from None

    def _read(self, size: int, deadline: float, what: str) -> bytes:
        fd = self._response_fd
        assert fd is not None
        chunks = bytearray()
        while len(chunks) < size:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.kill()
                raise self._timeout_failure(what)
            readable, _, _ = select.select([fd], [], [], remaining)
            if not readable:
                continue
            chunk = os.read(fd, min(size - len(chunks), 1 << 20))
            if not chunk:
                raise self._death()
            chunks += chunk
        return bytes(chunks)

    def _timeout_failure(self, what: str) -> SubmissionFailure:
        seconds = f" of {self._timeout:.3g} s" if self._timeout else ""
        return SubmissionFailure("timeout", f"{what} did not finish within the time limit{seconds} (an "
                                            "infinite loop, or much slower than it needs to be)",
                                 printed=self.output())

    def _death(self) -> SubmissionFailure:
        """Why the child went away, from its exit status, CPU time and peak memory."""
        code = self._reap(5)
        if code is None:
            self.kill()
            code = self._process.returncode if self._process is not None else None
        printed = self.output()
        if code is not None and code < 0:
            sig = -code
            cpu_limit = self.limits.cpu_seconds
            if sig == signal.SIGXCPU or (sig == signal.SIGKILL and not self._killed
                                         and self._cpu_seconds >= cpu_limit):
                return SubmissionFailure("cpu", f"your code used more than {cpu_limit:g} s of CPU time and "
                                                f"was stopped ({_signal_name(sig)})", printed=printed)
            message = f"the process running your code was killed by {_signal_name(sig)}"
            if sig in (signal.SIGSEGV, signal.SIGBUS, signal.SIGABRT, signal.SIGKILL):
                near = self._max_rss_mb >= 0.8 * self.limits.memory_mb
                message += (f"; it used {self._max_rss_mb:.0f} MB at most"
                            + (", near" if near else ", and")
                            + f" the memory limit is {self.limits.memory_mb:g} MB"
                            + ": running out of memory inside a library ends a process this way")
            return SubmissionFailure("crashed", message, printed=printed)
        return SubmissionFailure("crashed", f"your code ended the process running it (exit status {code}); "
                                            "do not call exit() or os._exit()", printed=printed)
