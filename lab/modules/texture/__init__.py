"""Texture synthesis three classic ways: parametric (Heeger–Bergen), pixel by pixel (Efros–Leung), by blocks
(quilting); texture transfer; the texture on a mesh.

References:
- D. J. Heeger and J. R. Bergen, "Pyramid-based texture analysis/synthesis", SIGGRAPH 1995
  (:mod:`~lab.modules.texture.parametric`).
- A. A. Efros and T. K. Leung, "Texture synthesis by non-parametric sampling", ICCV 1999
  (:mod:`~lab.modules.texture.efros_leung`; the slow readable oracle in
  :mod:`~lab.modules.texture.reference`).
- A. A. Efros and W. T. Freeman, "Image quilting for texture synthesis and transfer", SIGGRAPH 2001
  (:mod:`~lab.modules.texture.quilting`, :mod:`~lab.modules.texture.transfer`).

The package: :mod:`~lab.modules.texture.steps` (the steps in pipeline order), the math by topic beside
it, ``_kernels`` (the compiled loop), :mod:`~lab.modules.texture.evaluate` (metrics and evaluations),
:mod:`~lab.modules.texture.datasets`. Import from here: this module's ``__all__`` is the surface.

Conventions. Images are float32 ``(H, W)`` or ``(H, W, 3)`` in [0, 1]; pixel ``(row, col)``. A
window of odd side ``w`` around pixel ``(r, c)`` covers rows ``r - w//2 .. r + w//2``. Sample
windows lie wholly inside the sample: there are ``(h - w + 1) x (w_s - w + 1)`` of them, indexed
by their top-left corner (their centre is ``w//2`` further). Output sizes are ``(height, width)``.

State names:
    sample              Image               the texture to imitate (dataset or upload)
    transfer_target     Image               the picture texture transfer redraws (dataset)
    query_window        (w, w[, 3])         a partly known window (unknown pixels 0)  [lesson helper]
    query_mask          (w, w) bool         which pixels of the query are known
    query_origin        (2,) int64          top-left (row, col) of the sample window the query was cut from
    window_distances    (h-w+1, ws-w+1)     Gaussian-weighted masked SSD of the query to every sample window
    match_candidates    Points2D on sample  centres of the windows within (1 + epsilon) of the best
    chosen_match        (2,) int64          top-left (row, col) of the window drawn among the candidates
    overlap_left/right  Image               two blocks that overlap by a band of columns  [lesson helper]
    overlap_error       (B, O)              squared difference of the blocks in the overlap (summed over
                                            colour)
    cut_path            (B,) int64          the minimum-error cut: its column in every row of the overlap
    joined              Image               the two blocks joined along the cut
    parametric          Image               Heeger–Bergen's texture
    efros_leung         Image               Efros–Leung's texture
    efros_leung_trace   EfrosLeungTrace     fill order and source pixel of every output pixel
    quilting            Image               the quilted texture
    quilting_layout     QuiltLayout         every block: place, source, overlap error surface, cut
    quilting_seams      Segments2D          the cuts, drawn on ``quilting``
    transferred         Image               the target redrawn with the sample (texture transfer)
    textured_mesh       Mesh                a plane, cylinder or torus coloured by a texture through its UVs
    mesh_uv             (V, 2)              the UV coordinates of the mesh's vertices
"""

from __future__ import annotations

from lab.core import Pipeline
from lab.modules.texture._common import luminance
from lab.modules.texture.datasets import DATASETS
from lab.modules.texture.efros_leung import (MAX_EL_WORK, SIGMA_FRACTION, WEIGHT_SCALE, EfrosLeungTrace,
                                             PixelMatches, candidates_within, efros_leung,
                                             efros_leung_pixel_matches, fill_layer, gaussian_window,
                                             grow_efros_leung, integer_gaussian, onion_layer, pick_candidate,
                                             sample_levels)
from lab.modules.texture.evaluate import (EVALUATIONS, evaluate_efros_leung, evaluate_match,
                                          evaluate_parametric, evaluate_quilting, seam_score,
                                          texture_statistics_distance)
from lab.modules.texture.mesh import parametric_surface, sample_texture, textured_trimesh
from lab.modules.texture.parametric import build_pyramid, collapse_pyramid, heeger_bergen, match_histogram
from lab.modules.texture.quilting import (QuiltLayout, cut_segments, image_quilting, min_error_boundary_cut,
                                          overlap_error_surface, path_cost)
from lab.modules.texture.reference import efros_leung_reference, fill_layer_reference
from lab.modules.texture.steps import (EfrosLeungResult, JoinedBlocks, OverlapPair, ParametricResult,
                                       QueryWindow, QuiltResult, TexturedMesh, TransferResult, WindowMatch,
                                       join_blocks, match_window, min_error_cut, pick_overlap,
                                       pick_query_window, quilt, synthesize_efros_leung,
                                       synthesize_parametric, transfer_texture, window_distances,
                                       wrap_on_mesh)
from lab.modules.texture.transfer import correspondence_map

#: State names the viewer's texture interactions read by name (lab/viewer/interactions/texture.py): the
#: growth explorer, the quilt explorer and the textures the mesh viewer may wrap.
VIEWS = ("sample", "parametric", "efros_leung", "efros_leung_trace", "quilting", "quilting_layout",
         "transferred")

PIPELINE = Pipeline.build(
    name="texture",
    title="Texture synthesis",
    summary="Make more of a texture from a small sample three classic ways and watch each grow: "
            "Heeger-Bergen histogram matching on an oriented pyramid, Efros-Leung pixel-by-pixel sampling, "
            "and image quilting with minimum-error cuts; texture transfer; the result wrapped on a plane, "
            "cylinder or torus.",
    steps=[pick_query_window, window_distances, match_window, pick_overlap, min_error_cut, join_blocks,
           synthesize_parametric, synthesize_efros_leung, quilt, transfer_texture, wrap_on_mesh],
    datasets=DATASETS,
    evaluations=EVALUATIONS,
    views=VIEWS,
)

__all__ = [
    "EVALUATIONS", "MAX_EL_WORK", "PIPELINE", "SIGMA_FRACTION", "VIEWS", "WEIGHT_SCALE", "EfrosLeungResult",
    "EfrosLeungTrace", "JoinedBlocks", "OverlapPair", "ParametricResult", "PixelMatches", "QueryWindow",
    "QuiltLayout", "QuiltResult", "TexturedMesh", "TransferResult", "WindowMatch", "build_pyramid",
    "candidates_within", "collapse_pyramid", "correspondence_map", "cut_segments", "efros_leung",
    "efros_leung_pixel_matches", "efros_leung_reference", "evaluate_efros_leung", "evaluate_match",
    "evaluate_parametric", "evaluate_quilting", "fill_layer", "fill_layer_reference", "gaussian_window",
    "grow_efros_leung", "heeger_bergen", "image_quilting", "integer_gaussian", "join_blocks", "luminance",
    "match_histogram", "match_window", "min_error_boundary_cut", "min_error_cut", "onion_layer",
    "overlap_error_surface", "parametric_surface", "path_cost", "pick_candidate", "pick_overlap",
    "pick_query_window", "quilt", "sample_levels", "sample_texture", "seam_score", "synthesize_efros_leung",
    "synthesize_parametric", "texture_statistics_distance", "textured_trimesh", "transfer_texture",
    "window_distances", "wrap_on_mesh",
]
