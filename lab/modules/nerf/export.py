"""What the NeRF pipeline exports: the extracted mesh as PLY or GLB (trimesh), the orbit's frames as a GIF.

``PIPELINE.exports`` holds :data:`EXPORTS`; a front end runs what each reads (``mesh``, made by
:func:`~lab.modules.nerf.extract_mesh`; ``path_frames``, made by :func:`~lab.modules.nerf.render_path`)
and calls ``write(state, metrics, out)``. The mesh keeps the scene's frame and units (no axis swap: a
``transforms.json`` world has no known up; glTF viewers take +y as up). The GIF is written by imageio
(installed with scikit-image); MP4 would need imageio's ffmpeg plugin, which the lab does not require.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lab.core import Export, ImageSet, InvalidValue, Mesh, MissingInput
from lab.modules.nerf.mesh import mesh_trimesh

Writer = Callable[[Mapping[str, Any], Mapping[str, Mapping[str, Any]], Path], Path]

#: Frames per second of the exported GIF.
GIF_FPS = 12


def _value(state: Mapping[str, Any], name: str, kind: type, step: str) -> Any:
    value = state.get(name)
    if value is None:
        raise MissingInput(name, f"no {name} yet: run {step} first")
    if not isinstance(value, kind):
        raise InvalidValue(name, f"expected {kind.__name__}, got {type(value).__name__}")
    return value


def _mesh_writer(file_type: str) -> Writer:
    def write(state: Mapping[str, Any], metrics: Mapping[str, Mapping[str, Any]], out: Path) -> Path:
        mesh = _value(state, "mesh", Mesh, "extract_mesh")
        target = Path(out)
        target.parent.mkdir(parents=True, exist_ok=True)
        mesh_trimesh(mesh).export(str(target), file_type=file_type)
        return target

    write.__name__ = f"write_{file_type}"
    return write


def write_gif(state: Mapping[str, Any], metrics: Mapping[str, Mapping[str, Any]], out: Path) -> Path:
    """``path_frames`` as an animated GIF looping forever at :data:`GIF_FPS`."""
    import imageio.v3 as iio

    frames = _value(state, "path_frames", ImageSet, "render_path")
    pixels = np.stack([np.round(np.clip(f.pixels, 0, 1) * 255).astype(np.uint8) for f in frames.images])
    target = Path(out)
    target.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(target, pixels, extension=".gif", duration=1000.0 / GIF_FPS, loop=0)
    return target


#: The formats ``vision-lab export nerf --format ...`` writes.
EXPORTS = (
    Export("ply", "the extracted mesh with vertex colours as a PLY file (trimesh), in the scene's frame",
           ("mesh",), _mesh_writer("ply")),
    Export("glb", "the extracted mesh with vertex colours as a binary glTF (trimesh), in the scene's frame",
           ("mesh",), _mesh_writer("glb")),
    Export("gif", "the orbit's novel views as an animated GIF (imageio)", ("path_frames",), write_gif),
)

__all__ = ["EXPORTS", "GIF_FPS", "write_gif"]
