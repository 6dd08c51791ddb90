"""The parent side of the sandbox: run a student's file in a contained child process and call its functions.

One :class:`Sandbox` is one submission: a child process (:mod:`lab.lessons.child`) started with
``python -I`` in an empty temporary directory, a scrubbed environment, its own process group, and
inputs and outputs passed as pickles through two pipes. The child sets its own resource limits,
drops to ``nobody`` when started as root and the Python installation is readable by it, and
installs an audit hook before any student code runs (see :mod:`lab.lessons.child`).

The parent never trusts what comes back: replies are read with a deadline (a call that does not
return in time gets the whole process group killed), their size is capped, they are unpickled by
an unpickler that only builds NumPy arrays, plain Python values and :mod:`lab.core.values` types,
and typed values are rebuilt so their own checks run. What the code prints is kept up to a cap.

A call that does not produce a value raises :class:`SubmissionFailure` whose ``kind`` says why:
``raised`` (the code raised), ``blocked`` (it tried something the sandbox refuses), ``memory``,
``timeout``, ``cpu``, ``crashed`` (the process died), ``protocol`` (a value that cannot come
back), ``load`` (the file could not be loaded), ``missing`` (no such function).
"""

from __future__ import annotations

import dataclasses
import io
import os
import pickle
import select
import shutil
import signal
import stat
import subprocess
import sys
import sysconfig
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lab.lessons.child import HEADER
from lab.lessons.format import Limits

#: Modules the child imports before it locks itself down (the types step inputs use).
PRELOAD = ("lab.core.values", "lab.core.errors")

#: Parts of the lab a submission may import (values and errors the signatures use).
ALLOWED_LAB = ("lab.core",)

_BOOT = ("import sys; sys.path.append({root!r}); from lab.lessons.child import main; main()")


class SubmissionFailure(Exception):
    """A call of the student's code that produced no value, and why (``kind``)."""

    def __init__(self, kind: str, message: str, *, type_name: str = "", traceback: str = "", printed: str = "",
                 violations: tuple[str, ...] = ()) -> None:
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
    """Keeps the first ``limit`` bytes the child writes to its stdout/stderr descriptors, discards the rest."""

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
    """(uid, gid) of ``nobody`` when running as root and it can run the Python installation, else None."""
    if os.geteuid() != 0:
        return None
    try:
        import pwd

        entry = pwd.getpwnam("nobody")
    except (KeyError, ImportError):
        return None
    paths = [Path(sys.executable).resolve(), *(Path(p) for p in _python_roots()), Path(_lab_dir())]
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


def _python_roots() -> list[str]:
    paths = sysconfig.get_paths()
    roots = {paths[k] for k in ("stdlib", "platstdlib", "purelib", "platlib") if k in paths}
    roots.update(p for p in sys.path if p and (("site-packages" in p or "dist-packages" in p) and os.path.isdir(p)
                                                or p.startswith((sys.base_prefix, sys.prefix))))
    return sorted(roots)


def _lab_dir() -> str:
    import lab

    return str(Path(lab.__file__).resolve().parent)


def sandbox_paths(extra_deny: tuple[str, ...] = ()) -> dict[str, list[str]]:
    """What the child may read (the Python installation, lab/core) and must never read (the lab, lessons, tests)."""
    lab_dir = Path(_lab_dir())
    from lab.lessons.format import lessons_root

    deny = [str(lab_dir), str(lessons_root()), str(lab_dir.parent / "tests"), *extra_deny]
    allow = [str(lab_dir / "__init__.py"), str(lab_dir / "core"), os.devnull, "/dev/urandom"]
    return {"read_roots": _python_roots(), "deny_roots": deny, "allow_roots": allow}


# --- unpickling what the child sends --------------------------------------------------------------
_SAFE_GLOBALS = {
    ("builtins", "complex"), ("builtins", "set"), ("builtins", "frozenset"), ("builtins", "bytearray"),
    ("builtins", "slice"), ("builtins", "range"),
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy._core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "scalar"), ("numpy.core.multiarray", "scalar"),
    ("numpy._core.numeric", "_frombuffer"), ("numpy.core.numeric", "_frombuffer"),
}


class _SafeUnpickler(pickle.Unpickler):
    """Builds only NumPy arrays and scalars, plain Python values and lab.core value types."""

    def find_class(self, module: str, name: str) -> Any:
        from lab.core.values import VALUE_TYPES

        if (module, name) in _SAFE_GLOBALS:
            return super().find_class(module, name)
        if module == "lab.core.values" and name in VALUE_TYPES:
            return VALUE_TYPES[name]
        if module == "numpy.dtypes" and name.endswith("DType"):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"a {module}.{name}")


def _rebuild(value: Any, depth: int = 0) -> Any:
    """Typed values rebuilt through their constructors (unpickling skips their checks)."""
    from lab.core.values import VALUE_TYPES

    if depth > 20:
        raise ValueError("a value nested too deeply")
    if type(value) in VALUE_TYPES.values():
        return type(value)(**{f.name: _rebuild(getattr(value, f.name), depth + 1) for f in dataclasses.fields(value)})
    if isinstance(value, tuple):
        return tuple(_rebuild(v, depth + 1) for v in value)
    if isinstance(value, list):
        return [_rebuild(v, depth + 1) for v in value]
    if isinstance(value, dict):
        return {k: _rebuild(v, depth + 1) for k, v in value.items()}
    return value


def decode_reply(payload: bytes) -> tuple:
    message = _SafeUnpickler(io.BytesIO(payload)).load()
    if not isinstance(message, tuple) or not message or not isinstance(message[0], str):
        raise pickle.UnpicklingError("a malformed reply")
    return message


# --- the sandbox --------------------------------------------------------------------------------
class Sandbox:
    """A student's file loaded in a contained child process; :meth:`call` runs one of its functions.

    Use as a context manager or call :meth:`close`. After the child dies (a timeout, the CPU
    limit, a crash) the next :meth:`call` starts a fresh one.
    """

    def __init__(self, source: str, *, limits: Limits | None = None, filename: str = "submission.py",
                 preload: tuple[str, ...] = PRELOAD, deny: tuple[str, ...] = ()) -> None:
        self.source = source
        self.limits = limits or Limits()
        self.filename = filename
        self.preload = preload
        self.deny = deny
        self.functions: dict[str, dict[str, Any]] = {}
        self.load_printed = ""
        self.starts = 0
        self.pids: list[int] = []  # every child started (tests check none outlives the sandbox)
        self._process: subprocess.Popen | None = None
        self._workdir: str | None = None
        self._request_fd: int | None = None
        self._response_fd: int | None = None
        self._drain: _Drain | None = None
        self._drain_thread: threading.Thread | None = None
        self._killed = False
        self._timeout = 0.0

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

    def start(self, *, timeout: float | None = None) -> dict[str, dict[str, Any]]:
        """Start the child and load the file; returns its functions, raises SubmissionFailure(kind="load")."""
        self.close()
        self.starts += 1
        timeout = self.limits.call_timeout_s if timeout is None else timeout
        deadline = time.monotonic() + max(timeout, 0.0)
        self._timeout = timeout
        workdir = tempfile.mkdtemp(prefix="vision-lab-submission-")
        self._workdir = workdir
        script = Path(workdir) / self.filename
        script.write_text(self.source, encoding="utf-8")
        nobody = _nobody()
        if nobody is not None:
            os.chown(workdir, *nobody)
            os.chown(script, *nobody)
        os.chmod(workdir, 0o700)
        request_read, request_write = os.pipe()
        response_read, response_write = os.pipe()
        threads = "1"
        env = {"PATH": "/usr/bin:/bin", "HOME": workdir, "TMPDIR": workdir, "LANG": "C.UTF-8", "LC_ALL": "C.UTF-8",
               "OMP_NUM_THREADS": threads, "OPENBLAS_NUM_THREADS": threads, "MKL_NUM_THREADS": threads,
               "NUMEXPR_NUM_THREADS": threads, "OPENCV_FOR_THREADS_NUM": threads}
        root = str(Path(_lab_dir()).parent)
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-I", "-c", _BOOT.format(root=root), str(request_read), str(response_write)],
                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=workdir, env=env,
                pass_fds=(request_read, response_write), start_new_session=True, close_fds=True)
        finally:
            os.close(request_read)
            os.close(response_write)
        self.pids.append(self._process.pid)
        self._request_fd, self._response_fd = request_write, response_read
        os.set_blocking(request_write, False)
        self._killed = False
        self._drain = _Drain(int(self.limits.output_kb * 1024))
        self._drain_thread = threading.Thread(target=self._drain.run, args=(self._process.stdout,), daemon=True,
                                              name="sandbox-output")
        self._drain_thread.start()
        limits = {k: float(v) for k, v in dataclasses.asdict(self.limits).items()}
        setup = {"workdir": workdir, "source": self.source, "filename": self.filename, "preload": list(self.preload),
                 "limits": limits, "nobody": nobody, "allowed_lab": list(ALLOWED_LAB),
                 "output_chars": int(self.limits.output_kb * 1024), **sandbox_paths(self.deny)}
        try:
            self._send(pickle.dumps(setup, protocol=pickle.HIGHEST_PROTOCOL), deadline)
            reply = self._receive(deadline, what="loading your file")
        except SubmissionFailure as failure:
            raise SubmissionFailure("load", f"your file could not be loaded: {failure.message}",
                                    printed=failure.printed) from None
        if reply[0] == "load_error":
            _, kind, type_name, message, traceback, printed, violations = reply
            self.close()
            reason = "it tried something the sandbox does not allow" if kind == "blocked" else f"it raised {type_name}"
            raise SubmissionFailure("load", f"your file could not be loaded: {reason}: {message}",
                                    type_name=type_name, traceback=traceback, printed=printed,
                                    violations=tuple(violations))
        if reply[0] != "ready" or not isinstance(reply[1], dict):
            self.kill()
            raise SubmissionFailure("load", "your file could not be loaded: the sandbox answered out of turn")
        self.functions = reply[1]
        self.load_printed = reply[2] if isinstance(reply[2], str) else ""
        return self.functions

    def kill(self) -> None:
        """Kill the child's whole process group (it has its own session)."""
        process = self._process
        if process is None:
            return
        self._killed = True
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:  # pragma: no cover - a zombie the kernel holds on to
            pass

    def close(self) -> None:
        """Stop the child and remove its directory (safe to call twice)."""
        if self._process is not None:
            for fd_name in ("_request_fd", "_response_fd"):
                fd = getattr(self, fd_name)
                if fd is not None:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
                    setattr(self, fd_name, None)
            if self._process.poll() is None:
                try:
                    self._process.wait(timeout=0.5)  # it exits on its own when its request pipe closes
                except subprocess.TimeoutExpired:
                    self.kill()
            else:
                try:
                    os.killpg(self._process.pid, signal.SIGKILL)  # anything it left behind in its group
                except (ProcessLookupError, PermissionError):
                    pass
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
        payload = pickle.dumps(("call", name, tuple(args), dict(kwargs or {})), protocol=pickle.HIGHEST_PROTOCOL)
        self._send(payload, deadline)
        reply = self._receive(deadline, what=f"{name}()")
        seconds = time.monotonic() - started
        if reply[0] == "ok" and len(reply) == 5:
            _, value, printed, violations, dropped = reply
            try:
                value = _rebuild(value)
            except Exception as exc:  # a typed value whose own checks refuse it
                raise SubmissionFailure("protocol", f"{name} returned an invalid value: {exc}", printed=printed,
                                        violations=tuple(violations)) from None
            raw = (self._drain.total if self._drain is not None else 0) - raw_before
            cap = int(self.limits.output_kb * 1024)
            flooded = int(dropped) + max(0, raw - cap)
            if raw:
                printed = f"{printed}\n{self.output()}" if printed else self.output()
            return CallResult(value, printed, tuple(violations), seconds, flooded)
        if reply[0] == "error" and len(reply) == 7:
            _, kind, type_name, message, traceback, printed, violations = reply
            raise SubmissionFailure(str(kind), str(message), type_name=str(type_name), traceback=str(traceback),
                                    printed=str(printed), violations=tuple(violations))
        self.kill()
        raise SubmissionFailure("protocol", "the sandbox answered out of turn (did your code write to the "
                                            "grader's pipe?)")

    def _send(self, payload: bytes, deadline: float) -> None:
        data = memoryview(HEADER.pack(len(payload)) + payload)
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

    def _receive(self, deadline: float, *, what: str) -> tuple:
        header = self._read(HEADER.size, deadline, what)
        (size,) = HEADER.unpack(header)
        limit = int(self.limits.result_mb * 2**20)
        if size > limit:
            self.kill()
            raise SubmissionFailure("protocol", f"{what} returned {size / 2**20:.1f} MB of data; the limit is "
                                                f"{self.limits.result_mb:g} MB")
        payload = self._read(size, deadline, what)
        try:
            return decode_reply(payload)
        except Exception as exc:
            reason = str(exc) if isinstance(exc, pickle.UnpicklingError) else type(exc).__name__
            raise SubmissionFailure("protocol", f"{what} returned a value the grader does not accept ({reason}); "
                                                f"return numpy arrays, numbers, or the lab.core values the "
                                                f"signature names") from None

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
        return SubmissionFailure("timeout", f"{what} did not finish within the time limit{seconds} (an infinite "
                                            f"loop, or much slower than it needs to be)", printed=self.output())

    def _death(self) -> SubmissionFailure:
        """Why the child went away, from its exit status."""
        process = self._process
        code = None
        if process is not None:
            try:
                code = process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.kill()
                code = process.returncode
        printed = self.output()
        if code is not None and code < 0:
            sig = -code
            if sig in (signal.SIGXCPU, signal.SIGKILL) and not self._killed:
                return SubmissionFailure("cpu", f"your code used more than {self.limits.cpu_seconds:g} s of CPU "
                                                f"time and was stopped", printed=printed)
            if sig in (signal.SIGSEGV, signal.SIGBUS, signal.SIGABRT):
                return SubmissionFailure("crashed", f"the process running your code crashed "
                                                    f"({signal.Signals(sig).name}); running out of memory (limit "
                                                    f"{self.limits.memory_mb:g} MB) inside a library does this",
                                         printed=printed)
            name = signal.Signals(sig).name if sig in signal.Signals._value2member_map_ else str(sig)
            return SubmissionFailure("crashed", f"the process running your code was killed ({name})", printed=printed)
        return SubmissionFailure("crashed", f"your code ended the process running it (exit status {code}); do not "
                                            f"call exit() or os._exit()", printed=printed)
