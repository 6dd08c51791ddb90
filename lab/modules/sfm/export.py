"""What the SfM pipeline exports: its bundle-adjusted model as a COLMAP text model or a transforms.json.

``PIPELINE.exports`` holds :data:`EXPORTS`; a front end runs what they read (``adjusted_model``,
made by :func:`~lab.modules.sfm.bundle_adjust_all`) and calls ``write(state, metrics, out)``, which
writes with :func:`lab.data.exports.write_reconstruction` and returns the path written.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from lab.core import Export, MissingInput
from lab.data.exports import write_reconstruction
from lab.data.reconstruction import SparseModel

#: The state value the exports write: the model after the final bundle adjustment.
EXPORTED_MODEL = "adjusted_model"

Writer = Callable[[Mapping[str, Any], Mapping[str, Mapping[str, Any]], Path], Path]


def exported_model(state: Mapping[str, Any]) -> SparseModel:
    """The model the exports write (``adjusted_model``); :class:`MissingInput` before bundle_adjust_all
    ran."""
    model = state.get(EXPORTED_MODEL)
    if model is None:
        raise MissingInput(EXPORTED_MODEL,
                           "no bundle-adjusted reconstruction yet: run bundle_adjust_all first")
    return model


def writer(fmt: str) -> Writer:
    """``write(state, metrics, out)`` in format ``fmt``, a key of
    :data:`lab.data.exports.RECONSTRUCTION_FORMATS`."""

    def write(state: Mapping[str, Any], metrics: Mapping[str, Mapping[str, Any]], out: Path) -> Path:
        return write_reconstruction(out, exported_model(state), fmt)

    write.__name__ = f"write_{fmt.replace('-', '_')}"
    return write


#: The formats ``vision-lab export sfm --format ...`` writes.
EXPORTS = (
    Export("colmap", "the bundle-adjusted reconstruction as a COLMAP text model: cameras.txt, images.txt and "
                     "points3D.txt in the folder out", (EXPORTED_MODEL,), writer("colmap")),
    Export("transforms-json",
           "the bundle-adjusted cameras as a nerfstudio / instant-ngp transforms.json (OpenGL "
           "camera-to-world) at the file out, frames at images/<name>", (EXPORTED_MODEL,),
           writer("transforms-json")),
)
