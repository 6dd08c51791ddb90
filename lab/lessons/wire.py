"""The sandbox's wire format: data only, never code. What crosses between the grader and the child.

Pickle can build any object, so a child that writes its own bytes to the result pipe could make
the grader run code or crash it (an object-dtype array forged through ``numpy``'s reconstructors
segfaulted it). Nothing here is unpickled. A message is one frame::

    8 bytes  big-endian length N of the rest
    8 bytes  big-endian length J of the JSON document
    J bytes  UTF-8 JSON: the structure, numbers and strings
    N-8-J    the raw little-endian buffers of the arrays, back to back

and the JSON is a tree of plain JSON values plus a few tagged objects (one key starting with
``$``):

==========================  ====================================================================
``{"$array": [o, n], "dtype": "<f8", "shape": [..]}``  a NumPy array: ``n`` bytes at offset ``o``
                                                       of the buffers; numeric dtypes only
``{"$scalar": {array}}``    a NumPy scalar (a 0-d array node)
``{"$tuple": [...]}``       a tuple (lists are JSON arrays)
``{"$dict": [[k, v], ..]}`` a dict (keys: str, int, float, bool or None)
``{"$complex": [re, im]}``  a Python complex
``{"$float": "nan"}``       a non-finite float (``nan``, ``inf``, ``-inf``)
``{"$value": name, "fields": {..}}``  a :data:`lab.core.values.VALUE_TYPES` value, rebuilt
                                       through its constructor so its own checks run
``{"$rng": state}``         a ``numpy.random.Generator`` (its bit generator's ``state``)
==========================  ====================================================================

:func:`decode` trusts nothing: sizes are checked against the frame before anything is allocated,
array dtypes come from a fixed list of little-endian numeric types, shapes must match their
buffers exactly, nesting is bounded, and every failure is a :class:`WireError` naming what was
wrong. This module imports only the standard library and NumPy (the child imports it before it
locks itself down); :mod:`lab.core.values` is imported when a typed value is met.
"""

from __future__ import annotations

import dataclasses
import json
import math
import struct
from typing import Any

import numpy as np

FRAME = struct.Struct(">Q")

#: Array element types that may cross (NumPy ``dtype.str``), little-endian or byte-order free.
DTYPES = ("|b1", "|i1", "<i2", "<i4", "<i8", "|u1", "<u2", "<u4", "<u8", "<f2", "<f4", "<f8", "<c8", "<c16")

#: Deepest nesting of containers accepted (a step's values are a few levels deep).
MAX_DEPTH = 48

#: Most dimensions an array may have.
MAX_NDIM = 32

_BIT_GENERATORS = ("PCG64", "PCG64DXSM", "Philox", "SFC64", "MT19937")
_NON_FINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


class WireError(ValueError):
    """A value that cannot be sent, or bytes that are not a valid message."""


# --- encoding ---------------------------------------------------------------------------------------
def encode(value: Any) -> bytes:
    """``value`` as the payload of one frame (without the leading length; see :func:`frame`)."""
    buffers: list[bytes] = []
    offset = [0]
    tree = _encode(value, buffers, offset, 0)
    document = json.dumps(tree, allow_nan=False, separators=(",", ":")).encode("utf-8")
    return FRAME.pack(len(document)) + document + b"".join(buffers)


def frame(payload: bytes) -> bytes:
    """A payload with its length in front: what goes on the pipe."""
    return FRAME.pack(len(payload)) + payload


def _encode(value: Any, buffers: list[bytes], offset: list[int], depth: int) -> Any:
    if depth > MAX_DEPTH:
        raise WireError(f"a value nested more than {MAX_DEPTH} levels deep")
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int) and not isinstance(value, np.integer):
        return int(value)
    if isinstance(value, float) and not isinstance(value, np.floating):
        return value if math.isfinite(value) else {"$float": "nan" if math.isnan(value) else
                                                   ("inf" if value > 0 else "-inf")}
    if isinstance(value, complex):
        return {"$complex": [_encode(value.real, buffers, offset, depth + 1),
                             _encode(value.imag, buffers, offset, depth + 1)]}
    if isinstance(value, np.generic):
        return {"$scalar": _encode_array(np.asarray(value), buffers, offset)}
    if isinstance(value, np.ndarray):
        return _encode_array(value, buffers, offset)
    if isinstance(value, np.random.Generator):
        return {"$rng": _encode(value.bit_generator.state, buffers, offset, depth + 1)}
    if isinstance(value, (list, tuple)):
        items = [_encode(v, buffers, offset, depth + 1) for v in value]
        return items if isinstance(value, list) else {"$tuple": items}
    if isinstance(value, dict):
        pairs = []
        for key, item in value.items():
            if not (key is None or isinstance(key, (str, int, float, bool))) or isinstance(key, np.generic):
                raise WireError(f"a dict key of type {type(key).__name__} (use str or int keys)")
            pairs.append([_encode(key, buffers, offset, depth + 1),
                          _encode(item, buffers, offset, depth + 1)])
        return {"$dict": pairs}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        from lab.core.values import VALUE_TYPES

        name = type(value).__name__
        if VALUE_TYPES.get(name) is type(value):
            return {"$value": name,
                    "fields": {f.name: _encode(getattr(value, f.name), buffers, offset, depth + 1)
                               for f in dataclasses.fields(value)}}
    raise WireError(f"an object of type {type(value).__module__}.{type(value).__qualname__}")


def _encode_array(array: np.ndarray, buffers: list[bytes], offset: list[int]) -> dict[str, Any]:
    dtype = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
    if dtype.str not in DTYPES:
        raise WireError(f"an array of dtype {array.dtype} (only bool, integer, float and complex arrays)")
    if array.ndim > MAX_NDIM:
        raise WireError(f"an array of {array.ndim} dimensions")
    data = np.ascontiguousarray(array, dtype=dtype).tobytes()
    node = {"$array": [offset[0], len(data)], "dtype": dtype.str, "shape": list(array.shape)}
    buffers.append(data)
    offset[0] += len(data)
    return node


# --- decoding ---------------------------------------------------------------------------------------
def decode(payload: bytes | bytearray | memoryview) -> Any:
    """The value a payload holds; raises :class:`WireError` on anything malformed."""
    view = memoryview(payload).cast("B")
    if len(view) < FRAME.size:
        raise WireError("a message shorter than its header")
    (size,) = FRAME.unpack(view[:FRAME.size])
    if size > len(view) - FRAME.size:
        raise WireError(f"a JSON document of {size} bytes in a message of {len(view)}")
    try:
        tree = json.loads(bytes(view[FRAME.size:FRAME.size + size]).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise WireError(f"a message that is not valid JSON ({type(exc).__name__})") from None
    except ValueError as exc:  # e.g. an integer with too many digits
        raise WireError(f"a message with an invalid number ({exc})") from None
    return _decode(tree, view[FRAME.size + size:], 0)


def _decode(node: Any, buffers: memoryview, depth: int) -> Any:
    if depth > MAX_DEPTH:
        raise WireError(f"a value nested more than {MAX_DEPTH} levels deep")
    if node is None or isinstance(node, (bool, int, float, str)):
        return node
    if isinstance(node, list):
        return [_decode(v, buffers, depth + 1) for v in node]
    if not isinstance(node, dict) or len(node) == 0:
        raise WireError("a malformed node")
    if "$array" in node:
        return _decode_array(node, buffers)
    if "$value" in node:
        return _decode_value(node, buffers, depth)
    if len(node) != 1:
        raise WireError("a malformed node")
    ((tag, body),) = node.items()
    if tag == "$tuple" and isinstance(body, list):
        return tuple(_decode(v, buffers, depth + 1) for v in body)
    if tag == "$dict" and isinstance(body, list):
        result: dict[Any, Any] = {}
        for pair in body:
            if not (isinstance(pair, list) and len(pair) == 2):
                raise WireError("a malformed dict entry")
            key = _decode(pair[0], buffers, depth + 1)
            if not (key is None or isinstance(key, (str, int, float, bool))):
                raise WireError("a dict key that is not a str, int, float, bool or None")
            result[key] = _decode(pair[1], buffers, depth + 1)
        return result
    if tag == "$float" and body in _NON_FINITE:
        return _NON_FINITE[body]
    if tag == "$complex" and isinstance(body, list) and len(body) == 2:
        parts = [_decode(v, buffers, depth + 1) for v in body]
        if not all(isinstance(p, (int, float)) and not isinstance(p, bool) for p in parts):
            raise WireError("a malformed complex number")
        return complex(*parts)
    if tag == "$scalar" and isinstance(body, dict) and "$array" in body:
        array = _decode_array(body, buffers)
        if array.ndim != 0:
            raise WireError("a scalar that is not 0-dimensional")
        return array[()]
    if tag == "$rng":
        return _decode_rng(_decode(body, buffers, depth + 1))
    raise WireError(f"an unknown tag {str(tag)[:40]!r}")


def _decode_array(node: dict[str, Any], buffers: memoryview) -> np.ndarray:
    where, dtype, shape = node.get("$array"), node.get("dtype"), node.get("shape")
    if set(node) != {"$array", "dtype", "shape"}:
        raise WireError("a malformed array node")
    if dtype not in DTYPES:
        raise WireError(f"an array of dtype {str(dtype)[:20]!r} "
                        "(only bool, integer, float and complex arrays)")
    if not (isinstance(shape, list) and len(shape) <= MAX_NDIM
            and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)):
        raise WireError("an array with a malformed shape")
    if not (isinstance(where, list) and len(where) == 2
            and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in where)):
        raise WireError("an array with a malformed location")
    start, nbytes = where
    item = np.dtype(dtype).itemsize
    if math.prod(shape) * item != nbytes or start + nbytes > len(buffers):
        raise WireError(f"an array of shape {tuple(shape)} and dtype {dtype} whose data is not {nbytes} "
                        "bytes inside the message")
    array = np.frombuffer(buffers[start:start + nbytes], dtype=np.dtype(dtype)).reshape(shape)
    return array.astype(array.dtype.newbyteorder("="), copy=True)


def _decode_rng(state: Any) -> np.random.Generator:
    name = state.get("bit_generator") if isinstance(state, dict) else None
    if name not in _BIT_GENERATORS:
        raise WireError(f"a random generator of unknown kind {str(name)[:40]!r}")
    bit_generator = getattr(np.random, name)()
    try:
        bit_generator.state = state
    except (TypeError, ValueError, KeyError) as exc:
        raise WireError(f"a random generator with an invalid state ({exc})") from None
    return np.random.Generator(bit_generator)


def _decode_value(node: dict[str, Any], buffers: memoryview, depth: int) -> Any:
    from lab.core.values import VALUE_TYPES

    name, fields = node.get("$value"), node.get("fields")
    if set(node) != {"$value", "fields"} or not isinstance(fields, dict):
        raise WireError("a malformed typed value")
    cls = VALUE_TYPES.get(name) if isinstance(name, str) else None
    if cls is None:
        raise WireError(f"an unknown value type {str(name)[:40]!r}")
    names = {f.name for f in dataclasses.fields(cls)}
    if not set(fields) <= names:
        raise WireError(f"a {name} with unknown fields {sorted(set(fields) - names)[:5]}")
    values = {k: _decode(v, buffers, depth + 1) for k, v in fields.items()}
    try:
        return cls(**values)
    except Exception as exc:  # the type's own checks refuse it
        raise WireError(f"an invalid {name}: {exc}") from None


__all__ = ["DTYPES", "FRAME", "MAX_DEPTH", "WireError", "decode", "encode", "frame"]
