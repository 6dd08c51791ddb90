"""The sandboxed child process that runs a student's code (the parent side is
:mod:`lab.lessons.sandbox`).

Started as ``python -I -c "...main()" REQUEST_FD RESPONSE_FD`` inside the operating-system sandbox of
:mod:`lab.lessons.isolation` (its own namespaces, a read-only root holding only the Python
installation and ``lab/core``, an empty tmpfs as working directory), with a scrubbed environment,
its stdin on /dev/null and its stdout/stderr on a pipe the parent drains and caps. It reads its
setup from the parent, writes the submission into its working directory, then, before any student
code runs:

1. imports NumPy and the few ``lab.core`` modules the step signatures use (to rebuild inputs);
2. sets resource limits (RLIMIT_CPU, RLIMIT_AS, RLIMIT_FSIZE, RLIMIT_NOFILE, RLIMIT_NPROC, no core);
3. only under ``--unsafe-sandbox`` (no namespaces) and started as root: becomes ``nobody`` when it
   can (inside the sandbox the user was already switched by bubblewrap);
4. installs an audit hook (PEP 578), defence in depth only (code can switch it off; the namespaces
   are what contain it), that refuses: importing the lab's reference implementation
   or data (anything under ``lab`` but ``lab.core``) and the lesson or test folders; opening
   files outside its directory, except for reading the Python installation and ``lab/core``;
   sockets; creating processes (fork, exec, spawn, subprocess, os.system); signalling other
   processes; loading native code with ctypes.

Then it executes the submission's source as module ``submission`` and serves calls. Messages are
data only (:mod:`lab.lessons.wire`: JSON and raw numeric buffers, never pickles), each a dict with
a ``kind``. Parent -> child: ``{"kind": "call", "name", "args", "kwargs"}``. Child -> parent:
``{"kind": "ready", "functions", "printed", "violations"}`` after loading, ``{"kind": "ok", "value",
"printed", "violations", "dropped"}`` or ``{"kind": "error" | "load_error", "failure": {"kind",
"type_name", "message", "traceback", "printed", "violations"}}``. The child exits when its request
pipe closes (the parent went away).

This module is imported by the parent too (for the framing helpers); it imports nothing heavy.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
from typing import Any

from lab.lessons.wire import FRAME as HEADER
from lab.lessons.wire import WireError, decode, encode, frame


# --- framing (shared with the parent) -----------------------------------------------------------
def read_exact(fd: int, size: int) -> bytes | None:
    """``size`` bytes from ``fd``; None on end of file."""
    chunks = []
    while size:
        chunk = os.read(fd, min(size, 1 << 20))
        if not chunk:
            return None
        chunks.append(chunk)
        size -= len(chunk)
    return b"".join(chunks)


def read_frame(fd: int) -> bytes | None:
    header = read_exact(fd, HEADER.size)
    if header is None:
        return None
    (size,) = HEADER.unpack(header)
    return read_exact(fd, size)


def write_frame(fd: int, payload: bytes) -> None:
    data = memoryview(frame(payload))
    while data:
        written = os.write(fd, data)
        data = data[written:]


# --- the child ----------------------------------------------------------------------------------
class SandboxViolation(PermissionError):
    """Something the sandbox does not allow (reading files elsewhere, sockets, processes)."""


class BlockedImport(ImportError):
    """Importing the reference implementation, the hidden data or the lesson's files."""


class CappedText(io.TextIOBase):
    """A text stream that keeps the first ``limit`` characters written to it and counts the rest."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.parts: list[str] = []
        self.kept = 0
        self.dropped = 0

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        text = str(text)
        room = self.limit - self.kept
        if room > 0:
            self.parts.append(text[:room])
            self.kept += min(room, len(text))
        self.dropped += max(0, len(text) - max(room, 0))
        return len(text)

    def take(self) -> str:
        """What was written since the last call, and how many characters were dropped (the caller reads
        ``last_dropped``)."""
        text = "".join(self.parts)
        if self.dropped:
            text += f"\n... ({self.dropped} more characters not kept)"
        self.last_dropped = self.dropped
        self.parts, self.kept, self.dropped = [], 0, 0
        return text

    last_dropped = 0


_BLOCKED_EVENTS = {
    "os.fork": "creating a process (fork)", "os.forkpty": "creating a process (forkpty)",
    "os.posix_spawn": "creating a process (posix_spawn)", "os.exec": "running a program (exec)",
    "os.spawn": "running a program (spawn)", "os.system": "running a shell command (os.system)",
    "os.startfile": "running a program", "subprocess.Popen": "running a program (subprocess)",
    "os.kill": "signalling a process (os.kill)", "os.killpg": "signalling a process group (os.killpg)",
    "signal.pthread_kill": "signalling a thread", "os.setuid": "changing user", "os.setgid": "changing group",
    "socket.__new__": "opening a network socket", "socket.connect": "connecting to the network",
    "socket.bind": "binding a network port", "socket.getaddrinfo": "looking up a host name",
    "socket.gethostbyname": "looking up a host name", "socket.sendto": "sending over the network",
    "ctypes.dlopen": "loading a native library with ctypes",
    "ctypes.dlsym": "calling native code with ctypes",
    "ctypes.call_function": "calling native code with ctypes",
    "ctypes.cdata": "reading raw memory with ctypes",
    "sys.remote_exec": "attaching to a process", "os.chroot": "changing the root directory",
}

# Events whose first argument is a path the code may only touch inside its own directory.
_PATH_EVENTS = {"os.remove", "os.rename", "os.rmdir", "os.mkdir", "os.symlink", "os.link", "os.chmod",
                "os.chown", "os.truncate", "os.utime", "os.listdir", "os.scandir", "os.chdir", "os.chflags",
                "os.lchflags", "os.mkfifo", "os.mknod", "os.setxattr", "os.removexattr", "os.listxattr",
                "os.getxattr", "shutil.rmtree", "shutil.copyfile", "shutil.move", "shutil.copytree",
                "glob.glob", "sqlite3.connect"}
_READ_ONLY_PATH_EVENTS = {"os.listdir", "os.scandir", "glob.glob", "os.listxattr", "os.getxattr", "os.chdir"}


class Guard:
    """The audit hook: which modules may be imported, which files read or written, which events refused.

    Files: anything inside ``workdir``; for reading, ``allow_roots`` (lab/core), then nothing under
    ``deny_roots`` (the lab package, lessons, tests), then anything under ``read_roots`` (the Python
    installation). Modules: ``lab`` and ``allowed_lab`` only, and no ``lessons`` or ``tests``.
    """

    def __init__(self, *, workdir: str, read_roots: list[str], deny_roots: list[str], allow_roots: list[str],
                 allowed_lab: list[str]) -> None:
        self.workdir = os.path.realpath(workdir)
        self.read_roots = [os.path.realpath(r) for r in read_roots]
        self.deny_roots = [os.path.realpath(r) for r in deny_roots]
        self.allow_roots = [os.path.realpath(r) for r in allow_roots]
        self.allowed_lab = tuple(allowed_lab)
        self.violations: list[str] = []
        self.active = False

    def _record(self, what: str) -> None:
        if len(self.violations) < 20 and what not in self.violations:
            self.violations.append(what)

    def _module_allowed(self, name: str) -> bool:
        top = name.split(".", 1)[0]
        if top == "lab":
            return name == "lab" or any(name == a or name.startswith(a + ".") for a in self.allowed_lab)
        return top not in ("lessons", "tests", "_posixsubprocess", "_cffi_backend", "cffi", "dbm", "_dbm",
                           "_gdbm")

    @staticmethod
    def _under(path: str, root: str) -> bool:
        return path == root or path.startswith(root.rstrip(os.sep) + os.sep)

    def _path_allowed(self, path: str, writing: bool) -> bool:
        if self._under(path, self.workdir):
            return True
        if writing:
            return False
        if any(self._under(path, a) for a in self.allow_roots):
            return True
        if any(self._under(path, d) for d in self.deny_roots):
            return False
        return any(self._under(path, r) for r in self.read_roots)

    def _resolve(self, path: Any) -> str | None:  # what an audit event passes: any object
        if isinstance(path, int):
            return None  # an already open descriptor
        if isinstance(path, bytes):
            path = os.fsdecode(path)
        path = os.fspath(path)  # a TypeError for what is not a path, as open() raises
        return os.path.realpath(os.path.join(self.workdir, path) if not os.path.isabs(path) else path)

    def _check_resolved(self, resolved: str, writing: bool) -> None:
        if not self._path_allowed(resolved, writing):
            what = f"{'writing' if writing else 'reading'} {resolved}"
            self._record(what)
            raise SandboxViolation(f"{what} is not allowed: a submission may only use files in its own "
                                   f"(empty) working directory")

    def check_path(self, path: object, *, writing: bool) -> None:
        """Refuse ``path`` unless allowed (for libraries that open files without an audit event)."""
        resolved = self._resolve(path)
        if resolved is not None:
            self._check_resolved(resolved, writing)

    def __call__(self, event: str, args: tuple) -> None:
        if not self.active:
            return
        self.active = False  # no recursion while checking
        try:
            self._check(event, args)
        finally:
            self.active = True

    def _check(self, event: str, args: tuple) -> None:
        if event == "import":
            name = args[0]
            if isinstance(name, str) and not self._module_allowed(name):
                self._record(f"import {name}")
                raise BlockedImport(f"importing {name!r} is not allowed in a submission: the lab's reference "
                                    "implementation, data and lesson files are off limits; write the step "
                                    "yourself with numpy, scipy or cv2")
            return
        if event == "open":
            path, mode, flags = (*tuple(args), None, None)[:3]
            if path is None:
                return
            resolved = self._resolve(path)
            if resolved is None:
                return
            writing = False
            if isinstance(mode, str):
                writing = any(c in mode for c in "wax+")
            if isinstance(flags, int):
                modes = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_TRUNC
                writing = writing or bool(flags & modes)
            self._check_resolved(resolved, writing)
            return
        reason = _BLOCKED_EVENTS.get(event)
        if reason is None and event.startswith("os.exec"):
            reason = "running a program (exec)"
        if reason is not None:
            self._record(reason)
            raise SandboxViolation(f"{reason} is not allowed in a submission")
        if event in _PATH_EVENTS and args:
            for index in ((0, 1) if event in ("os.rename", "os.symlink", "os.link", "shutil.move",
                                              "shutil.copyfile", "shutil.copytree") else (0,)):
                if index >= len(args) or args[index] is None or isinstance(args[index], int):
                    continue
                try:
                    resolved = self._resolve(args[index])
                except TypeError:
                    continue
                writing = event not in _READ_ONLY_PATH_EVENTS
                if resolved is not None and not self._path_allowed(resolved, writing):
                    what = f"{event} on {resolved}"
                    self._record(what)
                    raise SandboxViolation(f"{what} is not allowed: a submission may only use its own "
                                           "directory")


#: OpenCV functions that open files themselves (no audit event): the first argument is a path.
_CV2_PATH_FUNCTIONS = ("imread", "imreadmulti", "imreadanimation", "imreadWithMetadata", "imcount", "imwrite",
                       "imwritemulti", "imwriteanimation", "imwriteWithMetadata", "readOpticalFlow",
                       "writeOpticalFlow", "loadMesh", "loadPointCloud", "saveMesh", "savePointCloud",
                       "VideoCapture", "VideoWriter", "FileStorage", "CascadeClassifier")


def _guard_cv2(guard: Guard) -> None:
    """Wrap OpenCV's file functions so their paths pass the same check as ``open``."""
    import functools

    try:
        import cv2
    except ImportError:
        return
    for name in _CV2_PATH_FUNCTIONS:
        original = getattr(cv2, name, None)
        if original is None:
            continue

        def checked(*args, __original=original, __name=name, **kwargs):
            path = args[0] if args else kwargs.get("filename")
            if isinstance(path, (str, bytes, os.PathLike)):
                guard.check_path(path, writing=__name.startswith(("imwrite", "write", "save", "VideoWriter",
                                                                   "FileStorage")))
            return __original(*args, **kwargs)

        with contextlib.suppress(AttributeError, TypeError):
            functools.update_wrapper(checked, original)
        setattr(cv2, name, checked)


def _remove_process_creation() -> None:
    """``_posixsubprocess.fork_exec`` raises no audit event: take it away (importing it again is refused).

    ``subprocess`` is imported first so that it still loads; ``subprocess.Popen`` raises its own
    audit event, which the guard refuses with a clear message.
    """
    try:
        import _posixsubprocess
        import subprocess
    except ImportError:
        return

    def refused(*args, **kwargs):
        raise SandboxViolation("running a program (subprocess) is not allowed in a submission")

    subprocess._fork_exec = refused  # type: ignore[attr-defined]
    if hasattr(_posixsubprocess, "fork_exec"):
        del _posixsubprocess.fork_exec


def _set_limits(limits: dict[str, float], nobody: tuple[int, int] | None) -> None:
    import resource
    import signal

    def cap(which: int, value: float) -> None:
        value = int(value)
        _soft, hard = resource.getrlimit(which)
        if hard != resource.RLIM_INFINITY:
            value = min(value, hard)
        resource.setrlimit(which, (value, value if which != resource.RLIMIT_CPU else value + 1))

    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a too large file is an OSError, not a dead process
    usage = resource.getrusage(resource.RUSAGE_SELF)
    used = usage.ru_utime + usage.ru_stime
    cap(resource.RLIMIT_CPU, used + 1 + limits["cpu_seconds"])
    cap(resource.RLIMIT_CORE, 0)
    cap(resource.RLIMIT_FSIZE, limits["file_size_mb"] * 2**20)
    cap(resource.RLIMIT_NOFILE, max(limits["open_files"], _open_descriptors() + 4))
    cap(resource.RLIMIT_AS, _address_space() + limits["memory_mb"] * 2**20)
    cap(resource.RLIMIT_NPROC, limits["processes"])
    if nobody is not None and os.geteuid() == 0:
        uid, gid = nobody
        os.setgroups([])
        os.setgid(gid)
        os.setuid(uid)


def _address_space() -> int:
    with open("/proc/self/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    return 0


def _open_descriptors() -> int:
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return 16


def _signature(func) -> dict:
    import inspect

    try:
        signature = inspect.signature(func)
    except (TypeError, ValueError):
        return {"positional": [], "keyword": [], "varargs": True}
    params = list(signature.parameters.values())
    return {"positional": [p.name for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)],
            "keyword": [p.name for p in params if p.kind == p.KEYWORD_ONLY],
            "varargs": any(p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD) for p in params)}


def _student_traceback(exc: BaseException, filename: str) -> str:
    """The traceback from the first frame of the submission on (the child's own frames hidden)."""
    import traceback

    frames = traceback.StackSummary.extract(traceback.walk_tb(exc.__traceback__), lookup_lines=False)
    first = next((i for i, f in enumerate(frames) if f.filename == filename), None)
    mine = os.path.realpath(__file__)
    kept = traceback.StackSummary.from_list([f for f in (frames[first:] if first is not None else frames[-1:])
                                             if os.path.realpath(f.filename) != mine])
    lines = kept.format() + traceback.format_exception_only(type(exc), exc)
    text = "Traceback (most recent call last):\n" + "".join(lines)
    return text[-4000:]


def _kind_of(exc: BaseException) -> str:
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, (SandboxViolation, BlockedImport)):
            return "blocked"
        if isinstance(exc, MemoryError):
            return "memory"
        exc = exc.__cause__ or exc.__context__  # type: ignore[assignment]
    return "raised"


def _failure(exc: BaseException, filename: str, capture: CappedText, guard: Guard) -> dict:
    return {"kind": _kind_of(exc), "type_name": type(exc).__name__, "message": str(exc)[:2000],
            "traceback": _student_traceback(exc, filename), "printed": capture.take(),
            "violations": list(guard.violations)}


def main() -> None:
    request_fd, response_fd = int(sys.argv[1]), int(sys.argv[2])
    setup_frame = read_frame(request_fd)
    if setup_frame is None:
        os._exit(3)
    setup = decode(setup_frame)
    os.chdir(setup["workdir"])
    filename = setup["filename"]
    with open(os.path.join(setup["workdir"], filename), "w", encoding="utf-8") as script:
        script.write(setup["source"])  # for tracebacks that show the student's lines
    import importlib

    import numpy  # noqa: F401  (the values students get and return)

    for module in setup["preload"]:
        importlib.import_module(module)
    capture = CappedText(int(setup["output_chars"]))
    guard = Guard(workdir=setup["workdir"], read_roots=setup["read_roots"], deny_roots=setup["deny_roots"],
                  allow_roots=setup["allow_roots"], allowed_lab=setup["allowed_lab"])
    import types

    module = types.ModuleType("submission")
    module.__file__ = filename
    sys.modules["submission"] = module
    _guard_cv2(guard)
    _remove_process_creation()
    _set_limits(setup["limits"], setup.get("nobody"))
    sys.stdout = sys.stderr = capture
    sys.addaudithook(guard)
    guard.active = True

    def reply(message: dict) -> None:
        try:
            payload = encode(message)
        except (WireError, TypeError, ValueError, OverflowError) as exc:  # a value that is not data
            payload = encode({"kind": "error", "failure": {
                "kind": "protocol", "type_name": type(exc).__name__,
                "message": "the value returned cannot be sent back to the grader: it contains "
                           f"{str(exc)[:300]}; return numpy arrays (numbers, not objects), numbers, strings, "
                           "lists, tuples, dicts or the lab.core values the signature names",
                "traceback": "", "printed": capture.take(), "violations": list(guard.violations)}})
        write_frame(response_fd, payload)

    try:
        code = compile(setup["source"], filename, "exec", dont_inherit=True)
        exec(code, module.__dict__)
    except BaseException as exc:  # SystemExit and KeyboardInterrupt included: report, never die silently
        reply({"kind": "load_error", "failure": _failure(exc, filename, capture, guard)})
        os._exit(0)
    functions = {name: _signature(value) for name, value in vars(module).items()
                 if callable(value) and getattr(value, "__module__", None) == "submission"}
    reply({"kind": "ready", "functions": functions, "printed": capture.take(),
           "violations": list(guard.violations)})
    while True:
        request_frame = read_frame(request_fd)
        if request_frame is None:
            os._exit(0)
        request = decode(request_frame)
        guard.violations.clear()
        try:
            result = getattr(module, request["name"])(*request["args"], **request["kwargs"])
        except BaseException as exc:
            reply({"kind": "error", "failure": _failure(exc, filename, capture, guard)})
            continue
        printed = capture.take()
        reply({"kind": "ok", "value": result, "printed": printed, "violations": list(guard.violations),
               "dropped": capture.last_dropped})


if __name__ == "__main__":
    main()
