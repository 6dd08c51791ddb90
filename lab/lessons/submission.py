"""A submission as it arrives: check an uploaded file is Python source text that parses, before it is stored.

Shared by every front end that takes a submission (REST ``POST .../submissions``, the viewer's lesson
upload): the file's size, name, encoding and syntax are checked here, once; parsing runs in a limited
child process so a hostile file cannot stall or crash the server.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading

from lab.core.errors import CapacityExceeded, InvalidValue, LabError


class UnsupportedUpload(LabError):
    """An upload that is not Python source text."""

    status = 415
    kind = "unsupported_media_type"



def check_upload(payload: bytes, filename: str, *, limit: int) -> str:
    """The uploaded file as text, or a 4xx error: too large (413), not Python text (415), not parsable
    (422)."""
    if len(payload) > limit:
        raise CapacityExceeded("file", f"the file is larger than {limit} bytes, the most a submission may be")
    if not filename.lower().endswith(".py"):
        raise UnsupportedUpload("file", f"a submission is a Python file ending in .py, got {filename!r}")
    if not payload.strip():
        raise InvalidValue("file", "the file is empty")
    if b"\x00" in payload:
        raise UnsupportedUpload("file", "the file contains NUL bytes: it is not Python source text")
    try:
        text = payload.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise UnsupportedUpload("file", f"the file is not UTF-8 text (byte {exc.start}): save it as UTF-8 "
                                        "Python source") from None
    check_syntax(text, filename)
    return text


#: The child that parses a submission: ``ast.parse`` of stdin, the outcome as one JSON line.
_PARSE_SCRIPT = """
import ast, json, resource, sys
resource.setrlimit(resource.RLIMIT_AS, (%d, %d))
resource.setrlimit(resource.RLIMIT_CPU, (%d, %d))
source = sys.stdin.buffer.read().decode("utf-8")
try:
    ast.parse(source, filename=sys.argv[1])
    out = {"ok": True}
except SyntaxError as exc:
    out = {"ok": False, "kind": type(exc).__name__, "line": exc.lineno, "msg": exc.msg}
except (RecursionError, MemoryError) as exc:
    out = {"ok": False, "kind": type(exc).__name__, "line": None, "msg": str(exc)}
sys.stdout.write(json.dumps(out))
"""
#: Memory (bytes) and CPU seconds the parsing child may use; a 256 KiB file parses in about a second.
PARSE_MEMORY_BYTES = 1024 * 2**20
PARSE_SECONDS = 10
#: Parsing children running at once (more uploads wait for one to finish).
_PARSES = threading.BoundedSemaphore(2)


def check_syntax(text: str, filename: str) -> None:
    """Parse ``text`` as Python (``ast.parse``) in a child process; InvalidValue (422) on ``file`` if it
    does not parse.

    The child (``python -I``, memory and CPU limited, two at a time) keeps the server's process
    and its event loop free while a large file parses (the parser holds the GIL for its whole
    run), and turns the parser's RecursionError or MemoryError on deeply nested code into an error
    naming the file rather than a crash.
    """
    script = _PARSE_SCRIPT % (PARSE_MEMORY_BYTES, PARSE_MEMORY_BYTES, PARSE_SECONDS, PARSE_SECONDS)
    try:
        with _PARSES:
            done = subprocess.run([sys.executable, "-I", "-S", "-c", script, filename],
                                  input=text.encode("utf-8"), capture_output=True, timeout=2 * PARSE_SECONDS,
                                  check=False)
        outcome = json.loads(done.stdout or b"{}")
    except (subprocess.TimeoutExpired, ValueError):  # a child stopped by its limits writes nothing parsable
        outcome = {}
    if outcome.get("ok"):
        return
    kind = outcome.get("kind")
    if kind in ("SyntaxError", "IndentationError", "TabError"):
        raise InvalidValue("file", f"{filename} line {outcome.get('line')}: {kind}: {outcome.get('msg')}")
    cause = kind or f"out of time or memory after {PARSE_SECONDS} s"
    raise InvalidValue("file", f"{filename} is too deeply nested or too long for Python's parser ({cause}): "
                               "split long expressions into several statements")


__all__ = ["PARSE_MEMORY_BYTES", "PARSE_SECONDS", "UnsupportedUpload", "check_syntax", "check_upload"]
