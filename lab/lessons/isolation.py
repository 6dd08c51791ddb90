"""Isolation by the operating system: each submission in its own Linux namespaces, with bubblewrap.

The audit hook of :mod:`lab.lessons.child` is Python watching Python, and a submission can switch
it off from inside. What contains a submission is the kernel: :func:`bwrap_command` starts the
child under `bubblewrap <https://github.com/containers/bubblewrap>`_ (``bwrap``, the tool Flatpak
uses) with

- new PID, IPC, UTS, network and cgroup namespaces: it sees only its own processes, cannot signal
  the server (or anything outside), and has no network but its own empty loopback;
- a new mount namespace whose root is read-only and holds only the system libraries (``/usr``),
  the Python installation, ``lab/core`` with the child's own three files, a private ``/proc`` and
  a minimal ``/dev``, and one empty writable working directory, a size-capped tmpfs at
  :data:`WORKDIR` that vanishes with the sandbox. Not there: the rest of the lab (the reference
  modules, the lessons and their hidden data, the tests), the database, the host's ``/proc``,
  ``/etc``, ``/home``, ``/tmp``;
- an unprivileged user: when the server runs as root the child is switched (``setpriv``) to a
  user id of its own from :data:`UID_BASE` up, so ``RLIMIT_NPROC`` binds and no file of root's is
  its own; otherwise a new user namespace maps it to ``nobody``. No capabilities, no new
  privileges (``PR_SET_NO_NEW_PRIVS``);
- a cleared environment (only the few variables the child needs), ``--new-session`` (no
  terminal to inject into), ``--die-with-parent``: when the grader kills bwrap, or dies, the whole
  namespace dies with it, so nothing a submission starts, ``setsid`` or not, outlives grading.

Resource limits (CPU, address space, file size, open files, processes) are set by the child
before any student code runs, and the parent keeps the wall-clock deadline.

:func:`check` runs a tiny probe in the sandbox once per process and raises
:class:`SandboxUnavailable` (naming the fix) when bwrap is missing or namespaces are refused
(some containers do). The operator may then pass ``--unsafe-sandbox`` (:func:`allow_unsafe`):
submissions run with the audit hook only, which is for trusted code, never for a class.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import threading
from dataclasses import dataclass
from pathlib import Path

from lab.core.errors import LabError

#: The submission's working directory inside the sandbox (a tmpfs).
WORKDIR = "/submission"

#: First user id given to sandboxes when the server runs as root (one id per sandbox).
UID_BASE = 1_900_000_000
_UID_SPAN = 50_000_000

#: The lab files the child needs, relative to the ``lab`` package: nothing else of the lab is mounted.
CHILD_FILES = ("__init__.py", "core", "lessons/__init__.py", "lessons/child.py", "lessons/wire.py")

_SYSTEM_DIRS = ("/usr", "/bin", "/sbin", "/lib", "/lib32", "/lib64", "/libx32")
_SYSTEM_FILES = ("/etc/ld.so.cache", "/etc/ld.so.conf", "/etc/ld.so.conf.d", "/etc/localtime")

FIX = ("install bubblewrap (Debian/Ubuntu: apt-get install bubblewrap; Fedora: dnf install bubblewrap) and "
       "allow namespaces (in Docker: docker run --cap-add SYS_ADMIN --security-opt apparmor=unconfined "
       "--security-opt seccomp=unconfined ...; as a non-root user on Ubuntu 24.04 also sysctl "
       "kernel.apparmor_restrict_unprivileged_userns=0), or, for trusted code only, pass --unsafe-sandbox")


class SandboxUnavailable(LabError):
    """The operating-system sandbox cannot run here, so untrusted code is not graded (HTTP 503; CLI
    exit 2)."""

    status = 503
    kind = "sandbox_unavailable"

    def __init__(self, reason: str) -> None:
        super().__init__("sandbox", reason)


@dataclass(frozen=True)
class Isolation:
    """How a submission is contained.

    ``mode``: ``"bwrap"`` (namespaces, the default) or ``"unsafe"`` (the audit hook only: trusted
    code). ``bwrap``: the bubblewrap executable. ``tmpfs_mb``: size of the writable working
    directory.
    """

    mode: str = "bwrap"
    bwrap: str = "bwrap"
    tmpfs_mb: int = 64

    def __post_init__(self) -> None:
        if self.mode not in ("bwrap", "unsafe"):
            raise ValueError(f"isolation mode must be 'bwrap' or 'unsafe', got {self.mode!r}")


_unsafe_allowed = False
_probe_lock = threading.Lock()
_probe_results: dict[Isolation, str | None] = {}
_uids = itertools.count()


def allow_unsafe(allowed: bool = True) -> None:
    """The operator's ``--unsafe-sandbox``: run submissions with the audit hook only (trusted code)."""
    global _unsafe_allowed
    _unsafe_allowed = bool(allowed)


def unsafe_allowed() -> bool:
    return _unsafe_allowed


def default_isolation() -> Isolation:
    """What a new sandbox uses: bubblewrap, or the audit hook alone when the operator allowed it."""
    return Isolation(mode="unsafe") if _unsafe_allowed else Isolation()


# --- what is mounted --------------------------------------------------------------------------------
def lab_dir() -> Path:
    import lab

    return Path(lab.__file__).resolve().parent


def python_roots() -> list[str]:
    """Folders of the Python installation the child imports from (stdlib, site-packages, prefixes)."""
    paths = sysconfig.get_paths()
    roots = {paths[k] for k in ("stdlib", "platstdlib", "purelib", "platlib") if k in paths}
    roots.update(p for p in sys.path
                 if p and ((("site-packages" in p or "dist-packages" in p) and os.path.isdir(p))
                           or p.startswith((sys.base_prefix, sys.prefix))))
    return sorted(roots)


def _mounted_roots() -> list[str]:
    """The Python folders to bind, outermost only, without those the system folders already hold."""
    candidates = {os.path.realpath(p) for p in (sys.base_prefix, sys.prefix, *python_roots())
                  if os.path.isdir(p)}
    candidates.add(os.path.realpath(os.path.dirname(os.path.realpath(sys.executable))))
    system = [os.path.realpath(d) for d in _SYSTEM_DIRS if os.path.isdir(d)]
    kept: list[str] = []
    for path in sorted(candidates, key=len):
        if not any(_under(path, root) for root in (*system, *kept)):
            kept.append(path)
    return kept


def _under(path: str, root: str) -> bool:
    return path == root or path.startswith(root.rstrip("/") + "/")


def _parents(path: str) -> list[str]:
    parts = Path(path).parts[1:-1]
    return ["/" + "/".join(parts[:i]) for i in range(1, len(parts) + 1)]


def _sandbox_uid() -> int:
    return UID_BASE + (os.getpid() * 1009 + next(_uids)) % _UID_SPAN


def bwrap_command(command: list[str], *, isolation: Isolation, env: dict[str, str]) -> list[str]:
    """``command`` wrapped in bubblewrap as the module docstring describes (the list to exec)."""
    args = [isolation.bwrap, "--unshare-pid", "--unshare-ipc", "--unshare-net", "--unshare-uts",
            "--unshare-cgroup-try", "--hostname", "sandbox", "--die-with-parent", "--new-session",
            "--clearenv"]
    root = os.geteuid() == 0
    if not root:
        args += ["--unshare-user", "--uid", "65534", "--gid", "65534"]
    made: list[str] = []

    def ensure_parents(path: str) -> None:
        for parent in _parents(path):
            if parent not in made and not any(_under(parent, m) for m in mounted):
                args.extend(["--perms", "0755", "--dir", parent])
                made.append(parent)

    mounted: list[str] = []
    for path in _SYSTEM_DIRS:
        if os.path.islink(path):
            args += ["--symlink", os.readlink(path), path]
        elif os.path.isdir(path):
            args += ["--ro-bind", path, path]
            mounted.append(path)
    for path in _SYSTEM_FILES:
        if os.path.exists(path):
            ensure_parents(path)
            args += ["--ro-bind", path, path]
    for path in _mounted_roots():
        ensure_parents(path)
        args += ["--ro-bind", path, path]
        mounted.append(path)
    lab = str(lab_dir())
    ensure_parents(lab)
    args += ["--perms", "0755", "--tmpfs", lab]  # hides the lab when it lies inside site-packages
    for name in CHILD_FILES:
        source = os.path.join(lab, name)
        if name.count("/") and os.path.dirname(source) not in made:
            args += ["--perms", "0755", "--dir", os.path.dirname(source)]
            made.append(os.path.dirname(source))
        args += ["--ro-bind", source, source]
    args += ["--remount-ro", lab]
    from lab.lessons.format import lessons_root

    for hidden in (str(lessons_root()), str(lab_dir().parent / "tests")):
        if any(_under(os.path.realpath(hidden), m) for m in mounted) and os.path.isdir(hidden):
            args += ["--tmpfs", hidden, "--remount-ro", hidden]
    args += ["--proc", "/proc", "--dev", "/dev",
             "--perms", "0777", "--size", str(int(isolation.tmpfs_mb) * 2**20), "--tmpfs", WORKDIR,
             "--remount-ro", "/", "--chdir", WORKDIR, "--cap-drop", "ALL"]
    for key, value in env.items():
        args += ["--setenv", key, value]
    if root:
        setpriv = shutil.which("setpriv") or "/usr/bin/setpriv"
        uid = str(_sandbox_uid())
        args += ["--cap-add", "CAP_SETUID", "--cap-add", "CAP_SETGID", "--cap-add", "CAP_SETPCAP", "--",
                 setpriv, f"--reuid={uid}", f"--regid={uid}", "--clear-groups", "--inh-caps=-all",
                 "--bounding-set=-all", "--"]
    else:
        args += ["--"]
    return args + command


# --- the probe ----------------------------------------------------------------------------------
_PROBE = ("import json, os, sys; sys.path.append({root!r}); import lab.lessons.child, numpy; "
          "print(json.dumps({{'uid': os.getuid(), 'pid': os.getpid(), 'lab_modules': "
          "os.path.exists({modules!r}), 'writable': os.access({workdir!r}, os.W_OK)}}))")


def probe(isolation: Isolation, *, timeout: float = 60.0) -> str | None:
    """Run a tiny child in the sandbox; None when it works and holds, else why not (one line)."""
    if shutil.which(isolation.bwrap) is None:
        return f"bubblewrap ({isolation.bwrap!r}) is not installed"
    if os.geteuid() == 0 and shutil.which("setpriv") is None:
        return "setpriv (util-linux) is not installed; it drops the sandbox to an unprivileged user"
    lab = lab_dir()
    code = _PROBE.format(root=str(lab.parent), modules=str(lab / "modules"), workdir=WORKDIR)
    command = bwrap_command([sys.executable, "-I", "-c", code], isolation=isolation,
                            env={"PATH": "/usr/bin:/bin", "LANG": "C.UTF-8", "HOME": WORKDIR})
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout,
                              stdin=subprocess.DEVNULL)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"bubblewrap could not start a sandbox ({type(exc).__name__}: {exc})"
    if done.returncode != 0:
        said = (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
        return f"bubblewrap could not start a sandbox: {said[:300]}"
    try:
        facts = json.loads(done.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return f"the sandbox probe printed {done.stdout[:200]!r}"
    if facts.get("uid") == 0 or facts.get("lab_modules") or not facts.get("writable") \
            or facts.get("pid", 99) > 16:
        return f"the sandbox does not hold (probe saw {facts})"
    return None


def check(isolation: Isolation) -> None:
    """Raise :class:`SandboxUnavailable` unless ``isolation`` works here (probed once per process)."""
    if isolation.mode == "unsafe":
        return
    with _probe_lock:
        if isolation not in _probe_results:
            _probe_results[isolation] = probe(isolation)
        problem = _probe_results[isolation]
    if problem is not None:
        raise SandboxUnavailable(f"student code is not run without the operating-system sandbox: {problem}. "
                                 f"Fix: {FIX}")


__all__ = ["CHILD_FILES", "FIX", "UID_BASE", "WORKDIR", "Isolation", "SandboxUnavailable", "allow_unsafe",
           "bwrap_command", "check", "default_isolation", "lab_dir", "probe", "python_roots",
           "unsafe_allowed"]
