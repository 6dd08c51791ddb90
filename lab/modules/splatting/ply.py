"""The standard 3D Gaussian splatting PLY: the layout of the paper's code (``GaussianModel.save_ply`` and
``load_ply``), which common splat viewers read.

One ``vertex`` element, binary little-endian, every property a ``float`` (float32), in this order:
``x y z`` (the mean), ``nx ny nz`` (zeros), ``f_dc_0..2`` (the degree-0 coefficient per channel),
``f_rest_0..44`` (the 15 higher coefficients, channel-major: ``f_rest_{15 c + k}`` is channel ``c``'s
``k + 1``-th coefficient, the code's ``transpose(1, 2).flatten``), ``opacity`` (the logit), ``scale_0..2``
(log-scales) and ``rot_0..3`` (the quaternion ``(w, x, y, z)``, not normalized): the raw parameters, so a
reader applies the activations (sigmoid, exp, normalization) itself.

The reader takes the properties by name in any order (float or double, more properties ignored) and
``f_rest`` of 0, 9, 24 or 45 coefficients; a file always gets 45 from the writer, and a re-imported model's
degree is the highest with a nonzero coefficient.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lab.core import InvalidValue
from lab.modules.splatting.sh import MAX_SH_DEGREE, sh_count
from lab.modules.splatting.values import SplatModel, check_count

REST = 3 * (sh_count(MAX_SH_DEGREE) - 1)
#: The property names of a vertex, in the order the paper's code writes them.
PROPERTIES = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
              *(f"f_rest_{i}" for i in range(REST)),
              "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
_TYPES = {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "uchar": "u1", "uint8": "u1",
          "char": "i1", "int8": "i1", "ushort": "u2", "uint16": "u2", "short": "i2", "int16": "i2",
          "uint": "u4", "uint32": "u4", "int": "i4", "int32": "i4"}
#: Largest header read, in bytes.
MAX_HEADER = 1 << 16


def ply_vertices(model: SplatModel) -> np.ndarray:
    """The model's Gaussians as the structured array ``(N,)`` of :data:`PROPERTIES` (float32)."""
    n = len(model)
    rest = model.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, REST)
    columns = np.concatenate([model.means, np.zeros((n, 3), np.float32), model.sh[:, 0, :], rest,
                              model.opacity_logits[:, None], model.log_scales, model.quats], axis=1)
    vertices = np.empty(n, dtype=[(name, "<f4") for name in PROPERTIES])
    for k, name in enumerate(PROPERTIES):
        vertices[name] = columns[:, k]
    return vertices


def write_ply(model: SplatModel, path: str | os.PathLike[str]) -> Path:
    """Write ``model`` to ``path`` in the INRIA layout (the module docstring); returns the path."""
    out = Path(path)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(model)}"]
    header += [f"property float {name}" for name in PROPERTIES] + ["end_header"]
    with open(out, "wb") as stream:
        stream.write(("\n".join(header) + "\n").encode("ascii"))
        stream.write(ply_vertices(model).tobytes())
    return out


def _header(data: bytes, where: str) -> tuple[int, int, list[tuple[str, str]]]:
    """``(offset of the body, vertex count, [(name, dtype)])`` of a binary little-endian PLY's header."""
    end = data.find(b"end_header\n", 0, MAX_HEADER)
    if not data.startswith(b"ply\n") or end < 0:
        raise InvalidValue(where, "not a PLY file (no 'ply' line or no 'end_header' in the first 64 KB)")
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise InvalidValue(where, "only binary little-endian PLY files are read (3D Gaussian splatting's)")
    count, properties, element = -1, [], ""
    for line in lines:
        words = line.split()
        if words[:1] == ["element"] and len(words) == 3:
            element = words[1]
            if element == "vertex":
                count = int(words[2])
            elif count < 0:
                raise InvalidValue(where, f"element {element!r} comes before 'vertex': not a splat file")
        elif words[:1] == ["property"] and element == "vertex":
            if len(words) != 3 or words[1] not in _TYPES:
                raise InvalidValue(where, f"unsupported vertex property {line!r} (list or unknown type)")
            properties.append((words[2], "<" + _TYPES[words[1]]))
    if count < 0:
        raise InvalidValue(where, "the file has no vertex element")
    return end + len(b"end_header\n"), count, properties


def read_ply(path: str | os.PathLike[str]) -> SplatModel:
    """The Gaussians of a PLY in the INRIA layout (the module docstring), with a clear
    :class:`InvalidValue` for a missing property, a short file or non-finite values."""
    where = "path"
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise InvalidValue(where, f"cannot read {os.fspath(path)!r}: {exc}") from None
    offset, count, properties = _header(data, where)
    check_count(count, where)
    names = [name for name, _ in properties]
    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    if len(rest) not in (3 * (sh_count(d) - 1) for d in range(MAX_SH_DEGREE + 1)):
        raise InvalidValue(where, f"{len(rest)} f_rest properties: expected 0, 9, 24 or 45 (degrees 0 to 3)")
    needed = [n for n in PROPERTIES if not n.startswith(("f_rest_", "n"))]
    missing = [n for n in needed if n not in names]
    if missing:
        raise InvalidValue(where, f"the vertex element lacks {', '.join(missing)}: not a 3D Gaussian "
                                  "splatting file")
    dtype = np.dtype(properties)
    if len(data) - offset < count * dtype.itemsize:
        raise InvalidValue(where, f"the file ends early: {count} vertices of {dtype.itemsize} bytes need "
                                  f"{count * dtype.itemsize} bytes, {len(data) - offset} follow the header")
    v = np.frombuffer(data, dtype=dtype, count=count, offset=offset)

    def take(*columns: str) -> np.ndarray:
        if not columns:
            return np.zeros((count, 0), np.float32)
        return np.stack([v[c].astype(np.float32) for c in columns], axis=1)

    per_channel = len(rest) // 3
    sh = np.zeros((count, sh_count(MAX_SH_DEGREE), 3), np.float32)
    sh[:, 0] = take("f_dc_0", "f_dc_1", "f_dc_2")
    sh[:, 1:1 + per_channel] = take(*rest).reshape(count, 3, per_channel).transpose(0, 2, 1)
    used = [d for d in range(1, MAX_SH_DEGREE + 1) if np.any(sh[:, sh_count(d - 1):sh_count(d)] != 0)]
    return SplatModel(take("x", "y", "z"), take("scale_0", "scale_1", "scale_2"),
                      take("rot_0", "rot_1", "rot_2", "rot_3"), v["opacity"].astype(np.float32), sh,
                      sh_degree=max(used, default=0))


__all__ = ["PROPERTIES", "ply_vertices", "read_ply", "write_ply"]
