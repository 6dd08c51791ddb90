"""Neural radiance fields made watchable on a CPU: rays, positional encoding, volume rendering, hierarchical
sampling and training, step by step.

Reference: B. Mildenhall, P. P. Srinivasan, M. Tancik, J. T. Barron, R. Ramamoorthi, R. Ng, "NeRF:
Representing scenes as neural radiance fields for view synthesis", ECCV 2020 (section 4: volume
rendering, eqs. 1-3; section 5.1: positional encoding; section 5.2: hierarchical volume sampling;
section 5.3: training; appendix A: the network).

Conventions: cameras are the lab's OpenCV cameras (``X_c = R X_w + t``, pixel (0, 0) the centre of
the top-left pixel); OpenGL ``transforms.json`` poses are converted by the one reader
(:mod:`lab.data.transforms_json`) at the edge. A ray's direction has camera-frame z = 1, so depths
``t`` along it are camera depths Z (those of the shared renderer). Networks run in float32 on
``device`` (CPU by default, CUDA when the runner gives it); randomness comes from the step's ``rng``.

The package (this file is its only import surface):

    steps.py       the steps in pipeline order, each with its result class
    values.py      the values between steps: SceneBounds, RayBundle, EncodingConfig, NerfCheckpoint
    rays.py        rays from poses, stratified samples
    encoding.py    the positional encoding gamma(p)
    rendering.py   volume rendering (weights, colour, depth, opacity) and inverse-CDF sampling
    model.py       the NeRF MLP and rendering rays and images through it
    grid.py        the accelerated variant: a voxel grid trained coarse to fine, empty space skipped
    training.py    the training loop (a generator yielding progress and previews)
    preview.py     the training preview that follows a camera (the viewer's: lab/viewer/interactions/nerf.py)
    warmup.py      the 2D warm-up: a coordinate MLP fitting one image, with and without the encoding
    path.py        the orbit of novel views about the scene centre
    mesh.py        the density's level set by marching cubes, coloured by head-on rays
    export.py      the exports: the mesh as PLY / GLB, the orbit's frames as a GIF
    reference.py   slow readable loop versions of the fast functions: the tests' oracles
    evaluate.py    PSNR, SSIM, depth error of held-out views
    datasets.py    a synthetic object (exact depth) and the NeRF-synthetic layout
    basics.py      lesson 05's teaching pipeline (``lab.modules.nerf.basics:PIPELINE``, not registered): the
                   encoding, ray directions, weights and inverse-CDF sampling as steps on float64 arrays

State names:
    images          ImageSet        the training views (RGB, composited on white)
    cameras         Cameras         their cameras (carrying ``images``)
    test_cameras    Cameras         the held-out poses
    bounds          SceneBounds     near / far depths, the centre and radius positions are normalized by
    pixel_supersample int           rays per pixel along each axis a dataset's pixel is the mean of (held-out
                                    views are rendered so; absent: one ray through each pixel centre)
    rays            RayBundle       one ray per training pixel, with its colour
    ray_lines       Segments3D      a few of them, near to far, in their pixel's colour
    encoding        EncodingConfig  L for positions and directions, identity or not
    encoding_plot   Curve           p and sin(2^k pi p) over [-1, 1]
    fit_psnr        Curve           the 2D warm-up: PSNR over Adam steps without the encoding and per L
    fit_images      ImageSet        its target and fitted images
    model           NerfCheckpoint  the trained network's weights and configuration (method mlp)
                    | GridCheckpoint  or the trained grid's values (method grid)
    loss_curve      Curve           the photometric loss over iterations
    psnr_curve      Curve           the batch PSNR over iterations
    preview         Image           training view 0 rendered by the final model (at most 64 px)
    test_renders    ImageSet        every held-out view rendered
    test_depth      (V, H, W)       their expected depths
    test_opacity    (V, H, W)       their opacities
    held_out_cameras Cameras        the held-out cameras carrying ``test_renders`` (click a pixel: its ray)
    rendered, depth_map, opacity_map  Image   one held-out view, its depth (near black, far white), opacity
    ray_weights     Curve           the weights w_i along one pixel's ray
    ray_samples     PointCloud      that ray's samples in 3D, grey (weight 0) to red (its largest weight)
    path_frames     ImageSet        novel views along an orbit about the scene centre
    path_cameras    Cameras         their cameras (carrying ``path_frames``)
    mesh            Mesh            the density's level set, vertex-coloured (world units)
Truth: ``test_images`` ``(V, H, W, 3)``; the synthetic object also ``test_depths``, ``train_depths``.
"""

from __future__ import annotations

from lab.core import Pipeline
from lab.modules.nerf.datasets import hemisphere_cameras, nerf_synthetic, object_scene, synthetic_object
from lab.modules.nerf.encoding import encoding_size, positional_encoding
from lab.modules.nerf.export import EXPORTS
from lab.modules.nerf.evaluate import EVALUATIONS, depth_error, evaluate_held_out, image_psnr, image_ssim
from lab.modules.nerf.model import (DENSITY_SHIFT, NerfMLP, RayRendering, network_from, render_image,
                                    render_rays)
from lab.modules.nerf.rays import camera_rays, cameras_rays, pixel_centres, scaled_cameras, stratified_samples
from lab.modules.nerf.reference import (camera_rays_reference, positional_encoding_reference,
                                        sample_pdf_reference, stratified_samples_reference,
                                        volume_render_reference)
from lab.modules.nerf.grid import GridCheckpoint, GridField, render_grid
from lab.modules.nerf.rendering import (PackedRendering, VolumeRendering, hierarchical_samples,
                                        interval_lengths, sample_pdf, volume_render, volume_render_packed)
from lab.modules.nerf.mesh import density_lattice, iso_surface, lattice_points, mesh_trimesh
from lab.modules.nerf.path import mean_up, orbit_path
from lab.modules.nerf.sfm_dataset import sfm_reconstruction
from lab.modules.nerf.steps import (FieldRenderer, encode_positions, extract_mesh, fit_image_2d,
                                    generate_rays, render_held_out, render_path, render_view, train_nerf,
                                    training_views)
from lab.modules.nerf.values import EncodingConfig, FieldConfig, NerfCheckpoint, RayBundle, SceneBounds
from lab.modules.nerf.warmup import CoordinateMLP, fit_image

#: State names the viewer may read by name: the cameras and what they carry, the model and its bounds,
#: the training preview, one view's depth and opacity, the orbit, the mesh and the held-out cameras.
VIEWS = ("cameras", "images", "test_cameras", "bounds", "model", "preview", "rendered", "depth_map",
         "opacity_map", "path_cameras", "path_frames", "mesh", "held_out_cameras")

PIPELINE = Pipeline.build(
    name="nerf",
    title="Neural radiance fields",
    summary="NeRF step by step on a CPU: rays through every pixel, the positional encoding (and why: one "
            "image fitted with and without it), an MLP of density and colour trained by volume rendering "
            "(stratified and hierarchical samples) or, much faster, a voxel grid trained coarse to fine, "
            "then held-out views rendered and compared (PSNR, SSIM, depth error), novel views along an orbit "
            "and a coloured mesh by marching cubes.",
    steps=[generate_rays, encode_positions, fit_image_2d, train_nerf, render_held_out, render_view,
           render_path, extract_mesh],
    datasets=[synthetic_object, nerf_synthetic, sfm_reconstruction],
    evaluations=EVALUATIONS,
    exports=EXPORTS,
    views=VIEWS,
)

__all__ = [
    "DENSITY_SHIFT", "EVALUATIONS", "EXPORTS", "PIPELINE", "VIEWS", "CoordinateMLP", "EncodingConfig",
    "FieldConfig", "FieldRenderer", "GridCheckpoint", "GridField", "NerfCheckpoint", "NerfMLP",
    "PackedRendering", "RayBundle", "RayRendering", "SceneBounds", "VolumeRendering", "camera_rays",
    "camera_rays_reference", "cameras_rays", "density_lattice", "depth_error", "encode_positions",
    "encoding_size", "evaluate_held_out", "extract_mesh", "fit_image", "fit_image_2d", "generate_rays",
    "hemisphere_cameras", "hierarchical_samples", "image_psnr", "image_ssim", "interval_lengths",
    "iso_surface", "lattice_points", "mean_up", "mesh_trimesh", "nerf_synthetic", "network_from",
    "object_scene", "orbit_path", "pixel_centres", "positional_encoding", "positional_encoding_reference",
    "render_grid", "render_held_out", "render_image", "render_path", "render_rays", "render_view",
    "sample_pdf", "sample_pdf_reference", "scaled_cameras", "sfm_reconstruction", "stratified_samples",
    "stratified_samples_reference", "synthetic_object", "train_nerf", "training_views", "volume_render",
    "volume_render_packed", "volume_render_reference",
]
