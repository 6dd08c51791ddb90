"""The texture pipeline's datasets, in the order the viewer lists them (the first is the default).

The loaders live in :mod:`lab.data.textures` (the data layer; its tests and the viewer's import them
from there): scikit-image's brick, grass and gravel, procedural textures with known statistics, and
a user's image file. Each gives ``sample`` and ``transfer_target``.
"""

from __future__ import annotations

from lab.data.textures import brick, grass, gravel, image_file, procedural

DATASETS = (brick, grass, gravel, procedural, image_file)

__all__ = ["DATASETS", "brick", "grass", "gravel", "image_file", "procedural"]
