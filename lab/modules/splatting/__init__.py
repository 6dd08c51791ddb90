"""3D Gaussian splatting on a CPU: the representation, its projection, tile binning and depth sorting,
front-to-back compositing, and their gradients.

Reference: B. Kerbl, G. Kopanas, T. Leimkühler, G. Drettakis, "3D Gaussian splatting for real-time
radiance field rendering", ACM TOG 42(4), SIGGRAPH 2023 (section 4: the representation, eqs. 4-6;
section 6: the tile rasterizer; the supplement and the authors' code for the constants).

The package (this file is its only import surface):

    gaussians.py   parameters and their activations, Sigma = R S S^T R^T, projection (J W Sigma W^T J^T)
    sh.py          the real spherical harmonics up to degree 3 (view-dependent colour)
    rasterize.py   the fast rasterizer: tile binning, depth sort, compiled compositing and its backward;
                   render_image, the same all compiled for rendering without gradients
    _kernels.py    the compiled loops: compositing (vectorized), its backward, binning, projection (private)
    reference.py   the readable per-Gaussian, per-pixel rasterizer in torch autograd: the tests' oracle
    values.py      SplatModel: the Gaussians' raw parameters between steps (drawn as GaussianSplats)
    losses.py      0.8 L1 + 0.2 D-SSIM
    density.py     Adam with per-parameter learning rates; clone, split, prune, opacity reset
    training.py    the training loop (a generator yielding progress and previews)
    contributions.py  the Gaussians one pixel is made of, with their alpha, transmittance and weight
    steps.py       the steps in pipeline order
    ply.py         the standard 3D Gaussian splatting PLY (the INRIA layout), written and read
    datasets.py    the synthetic object with surface points to start from
    basics.py      BASICS, lesson 06's pipeline: SH colour, Sigma', alphas, compositing, one step each
Datasets and evaluation are the NeRF module's (the same scenes, the same held-out PSNR and SSIM, and
``sfm_reconstruction``: the SfM module's exported reconstruction, its registered views and its points to
start from), plus the synthetic object with points (``object_with_points``).

State names:
    images, cameras, test_cameras, bounds   the NeRF module's datasets' (training views, held-out poses)
    sfm_points      PointCloud      points to start from (object_with_points, sfm_reconstruction; optional)
    gaussians       SplatModel      the initial Gaussians
    splats          GaussianSplats  them drawn; train_splats replaces it by the trained ones
    model           SplatModel      the trained Gaussians
    loss_curve, psnr_curve  Curve   the loss and the training-view PSNR over iterations
    density_curve   Curve           cloned, split, pruned and held Gaussians per density control
    preview         Image           training view 0 rendered by the trained Gaussians
    test_renders    ImageSet        every held-out view rendered
    held_out_cameras  Cameras       the held-out cameras carrying them
    rendered        Image           one held-out view
    pixel_gaussians Curve           alpha, transmittance and weight of the Gaussians of one of its pixels
    pixel_splats    PointCloud      their centres
    path_frames     ImageSet        novel views along an orbit about the scene centre
    path_cameras    Cameras         their cameras (carrying ``path_frames``)
Truth: ``test_images`` ``(V, H, W, 3)`` (the NeRF module's datasets).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lab.core import Export, MissingInput, Pipeline
from lab.modules.nerf import EVALUATIONS, nerf_synthetic, sfm_reconstruction, synthetic_object
from lab.modules.nerf import EXPORTS as NERF_EXPORTS
from lab.modules.splatting.basics import BASICS
from lab.modules.splatting.contributions import PixelContributions, pixel_contributions
from lab.modules.splatting.datasets import object_with_points, surface_points
from lab.modules.splatting.density import LEARNING_RATES, DensityEvent, TrainedGaussians, position_lr
from lab.modules.splatting.gaussians import (DILATION, NEAR_PLANE, TILE_SIZE, Projected, View,
                                             activated_opacities, covariances, image_covariances, project,
                                             quaternion_rotations, tile_rects, view_colors, view_of)
from lab.modules.splatting.rasterize import (MAX_TILE_PAIRS, Binning, Rendering, bin_gaussians,
                                             rasterize_image, render)
from lab.modules.splatting.reference import (GaussianInImage, composite_pixel_reference,
                                             project_one_reference, render_reference, rotation_reference)
from lab.modules.splatting.ply import PROPERTIES, ply_vertices, read_ply, write_ply
from lab.modules.splatting.losses import SSIM_WEIGHT, photometric_loss, ssim
from lab.modules.splatting.sh import MAX_SH_DEGREE, rgb_to_sh, sh_basis, sh_colors, sh_count, sh_to_rgb
from lab.modules.splatting.steps import (PIXEL_LIST, initial_model, initialize_gaussians, render_held_out,
                                         render_model, render_path, render_view, train_splats)
from lab.modules.splatting.training import SplatTrainingOptions, scene_extent, train_gaussians
from lab.modules.splatting.values import MAX_GAUSSIANS, SplatModel, as_model, model_from_tensors


def _export_ply(state: Mapping[str, Any], metrics: Mapping[str, Mapping[str, Any]], out: Path) -> Path:
    model = state.get("model")
    if model is None:
        raise MissingInput("model", "no trained model yet: run train_splats first")
    target = Path(out)
    target.parent.mkdir(parents=True, exist_ok=True)
    return write_ply(as_model(model, "model"), target)


#: The formats ``vision-lab export splatting --format ...`` writes: the trained Gaussians as the standard
#: PLY, the orbit's frames as a GIF (the NeRF module's writer).
EXPORTS = (
    Export("ply", "the trained Gaussians as a 3D Gaussian splatting PLY (the INRIA layout splat viewers "
                  "read)", ("model",), _export_ply),
    *(e for e in NERF_EXPORTS if e.format == "gif"),
)

#: State names the viewer may read by name: the cameras and what they carry, the Gaussians, the held-out
#: renders and one view's pixel list, the orbit.
VIEWS = ("cameras", "images", "test_cameras", "bounds", "gaussians", "model", "splats", "preview",
         "test_renders", "held_out_cameras", "rendered", "pixel_gaussians", "pixel_splats", "path_cameras",
         "path_frames")

PIPELINE = Pipeline.build(
    name="splatting",
    title="Gaussian splatting",
    summary="3D Gaussian splatting step by step on a CPU: Gaussians started at random points of the scene "
            "(or at a reconstruction's points), projected with the Jacobian of the perspective map, sorted "
            "per tile and composited front to back by a differentiable tile rasterizer, trained with L1 + "
            "D-SSIM and adaptive density control (clone, split, prune), then held-out views rendered and "
            "compared (PSNR, SSIM) on the NeRF module's scenes, the Gaussians of a clicked pixel listed, "
            "novel views along an orbit, and the standard splat PLY exported.",
    steps=[initialize_gaussians, train_splats, render_held_out, render_view, render_path],
    datasets=[synthetic_object, object_with_points, nerf_synthetic, sfm_reconstruction],
    evaluations=EVALUATIONS,
    exports=EXPORTS,
    views=VIEWS,
)

__all__ = [
    "BASICS", "DILATION", "EXPORTS", "LEARNING_RATES", "MAX_GAUSSIANS", "MAX_SH_DEGREE", "MAX_TILE_PAIRS",
    "NEAR_PLANE", "PIPELINE", "PIXEL_LIST", "PROPERTIES", "SSIM_WEIGHT", "TILE_SIZE", "VIEWS", "Binning",
    "DensityEvent", "GaussianInImage", "PixelContributions", "Projected", "Rendering", "SplatModel",
    "SplatTrainingOptions", "TrainedGaussians", "View", "activated_opacities", "as_model", "bin_gaussians",
    "composite_pixel_reference", "covariances", "image_covariances", "initial_model", "initialize_gaussians",
    "model_from_tensors", "object_with_points", "photometric_loss", "pixel_contributions", "ply_vertices",
    "position_lr", "project", "project_one_reference", "quaternion_rotations", "rasterize_image", "read_ply",
    "render", "render_held_out", "render_model", "render_path", "render_reference", "render_view",
    "rgb_to_sh", "rotation_reference", "scene_extent", "sh_basis", "sh_colors", "sh_count", "sh_to_rgb",
    "ssim", "surface_points", "tile_rects", "train_gaussians", "train_splats", "view_colors", "view_of",
    "write_ply",
]
