"""3D Gaussian splatting on a CPU: the representation, its projection, tile binning and depth sorting,
front-to-back compositing, and their gradients.

Reference: B. Kerbl, G. Kopanas, T. Leimkühler, G. Drettakis, "3D Gaussian splatting for real-time
radiance field rendering", ACM TOG 42(4), SIGGRAPH 2023 (section 4: the representation, eqs. 4-6;
section 6: the tile rasterizer; the supplement and the authors' code for the constants).

The package (this file is its only import surface):

    gaussians.py   parameters and their activations, Sigma = R S S^T R^T, projection (J W Sigma W^T J^T)
    sh.py          the real spherical harmonics up to degree 3 (view-dependent colour)
    rasterize.py   the fast rasterizer: tile binning, depth sort, compiled compositing and its backward
    _kernels.py    the compiled compositing loops (private)
    reference.py   the readable per-Gaussian, per-pixel rasterizer in torch autograd: the tests' oracle
"""

from __future__ import annotations

from lab.modules.splatting.gaussians import (DILATION, NEAR_PLANE, TILE_SIZE, Projected, View,
                                             activated_opacities, covariances, image_covariances, project,
                                             quaternion_rotations, tile_rects, view_colors, view_of)
from lab.modules.splatting.rasterize import (MAX_TILE_PAIRS, Binning, Rendering, bin_gaussians,
                                             rasterize_image, render)
from lab.modules.splatting.reference import (GaussianInImage, composite_pixel_reference,
                                             project_one_reference, render_reference, rotation_reference)
from lab.modules.splatting.sh import MAX_SH_DEGREE, rgb_to_sh, sh_basis, sh_colors, sh_count, sh_to_rgb

__all__ = [
    "DILATION", "MAX_SH_DEGREE", "MAX_TILE_PAIRS", "NEAR_PLANE", "TILE_SIZE", "Binning", "GaussianInImage",
    "Projected", "Rendering", "View", "activated_opacities", "bin_gaussians", "composite_pixel_reference",
    "covariances", "image_covariances", "project", "project_one_reference", "quaternion_rotations",
    "rasterize_image", "render", "render_reference", "rgb_to_sh", "rotation_reference", "sh_basis",
    "sh_colors", "sh_count", "sh_to_rgb", "tile_rects", "view_colors", "view_of",
]
