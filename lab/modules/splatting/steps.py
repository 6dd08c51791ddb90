"""The steps of the Gaussian splatting module, in pipeline order: each reads state by name and returns what
it writes.

1. :func:`initialize_gaussians`  at a reconstruction's points or random points in the scene box, scaled by
                                 their neighbours' distances
2. :func:`train_splats`          the Gaussians fitted to the training views (a generator step)
3. :func:`render_held_out`       the held-out views rendered (evaluated: PSNR, SSIM, by the NeRF module's
                                 evaluation)
4. :func:`render_view`           one held-out view, and the Gaussians one of its pixels is made of
5. :func:`render_path`           novel views along an orbit (a generator step)

Reference: B. Kerbl, G. Kopanas, T. Leimkühler, G. Drettakis, "3D Gaussian splatting for real-time
radiance field rendering", SIGGRAPH 2023.
"""

from __future__ import annotations

import math
import time
from collections.abc import Generator
from typing import Annotated, Literal

import numpy as np
import torch

from lab.core import (Cameras, Curve, GaussianSplats, Image, ImageSet, InvalidControl, InvalidValue,
                      PointCloud, Progress, Range, Warnings, metric, step_result)
from lab.modules.nerf import SceneBounds, orbit_path, training_views
from lab.modules.splatting.contributions import PixelContributions, pixel_contributions
from lab.modules.splatting.gaussians import view_of
from lab.modules.splatting.rasterize import render, render_image
from lab.modules.splatting.sh import C0, MAX_SH_DEGREE
from lab.modules.splatting.training import SplatTrainingOptions, SplatTrainingRun, train_gaussians
from lab.modules.splatting.values import SplatModel, as_model, check_count

BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


# ----------------------------------------------------------------------------------------------------
# 1. Initialisation
# ----------------------------------------------------------------------------------------------------
@step_result
class InitResult:
    """Result of :func:`initialize_gaussians`."""

    gaussians: SplatModel
    splats: GaussianSplats
    count: int = metric("Gaussians")
    mean_scale: float = metric("mean initial scale (scene units)")


def initial_model(points: np.ndarray, colors: np.ndarray, *, opacity: float = 0.1) -> SplatModel:
    """Gaussians at ``points`` (N, 3) with base ``colors`` (N, 3) in [0, 1] (the code's
    ``create_from_pcd``): isotropic, of scale the root mean square distance to the 3 nearest other points,
    unrotated, of opacity ``opacity``, spherical harmonics of degree 0 only."""
    from scipy.spatial import cKDTree

    n = len(points)
    check_count(n, "points")
    if n < 4:
        raise InvalidValue("points", f"need at least 4 points to scale the Gaussians by their neighbours, "
                                     f"got {n}")
    distances, _ = cKDTree(points).query(points, k=4)
    scale = np.sqrt(np.maximum(np.mean(distances[:, 1:] ** 2, axis=1), 1e-14))
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, 0] = (np.asarray(colors) - 0.5) / C0
    quats = np.zeros((n, 4), np.float32)
    quats[:, 0] = 1.0
    return SplatModel(points, np.repeat(np.log(scale)[:, None], 3, axis=1), quats,
                      np.full(n, math.log(opacity / (1 - opacity))), sh, sh_degree=0)


def initialize_gaussians(bounds: SceneBounds, sfm_points: PointCloud | None = None, *,
                         source: Literal["auto", "random", "points"] = "auto",
                         points: Annotated[int, Range(4, 200000)] = 1000,
                         opacity: Annotated[float, Range(0.001, 0.99)] = 0.1,
                         fill_random: bool = True,
                         rng: np.random.Generator) -> InitResult:
    """The first Gaussians (Kerbl et al. 2023, section 5; the code's ``create_from_pcd``): at the points of
    a reconstruction where the dataset brings them (``sfm_points``, the paper's start from COLMAP's sparse
    points; at most ``points`` of them, drawn at random, in their colours), else at random points of the
    scene box with random colours (the paper's start for its synthetic scenes, section 7.1: 100k uniform
    points); each isotropic, scaled by its neighbours' distances (:func:`initial_model`). On a CPU fewer
    start better: a training iteration costs what the Gaussians overlapping each pixel cost, and the density
    control adds Gaussians where the views need them (measured on the synthetic object, 30 s of training:
    1000 points 27.5 dB held-out after 668 iterations, 5000 points 13.4 dB after 69).

    The box is the cube of half-side ``bounds.radius`` about ``bounds.center``. Where the dataset brings
    fewer than ``points`` points, ``fill_random`` draws the rest at random in the box (the paper's random
    start beside the reconstruction's): a sparse reconstruction covers a smooth object unevenly (the SfM
    module's 447 points of the object scene lie on its textured faces), and the density control is slow
    to grow Gaussians where none started; the random ones that find nothing to explain are pruned.

    Args:
        source: "points" the dataset's points, "random" the box, "auto" the points where there are some.
        points: Gaussians to start from.
        opacity: their initial opacity.
        fill_random: fill up to ``points`` with random points of the box where the dataset has fewer
            (off: only the dataset's points).
    """
    if not isinstance(bounds, SceneBounds):
        raise InvalidValue("bounds", f"expected SceneBounds, got {type(bounds).__name__}")
    if sfm_points is not None and not isinstance(sfm_points, PointCloud):
        raise InvalidValue("sfm_points", f"expected a PointCloud, got {type(sfm_points).__name__}")
    if source == "points" and sfm_points is None:
        raise InvalidControl("source", "this dataset brings no points to start from: choose random or auto")
    xyz, colors = np.zeros((0, 3)), np.zeros((0, 3))
    if source != "random" and sfm_points is not None:
        xyz, colors = _drawn_points(sfm_points, points, rng)
    if len(xyz) == 0 or (fill_random and len(xyz) < points):
        more = points - len(xyz)
        xyz = np.concatenate([xyz, bounds.center + bounds.radius * rng.uniform(-1.0, 1.0, (more, 3))])
        colors = np.concatenate([colors, rng.uniform(0.0, 1.0, (more, 3))])
    model = initial_model(xyz, colors, opacity=opacity)
    return InitResult(model, model.splats(), len(model), float(np.exp(model.log_scales).mean()))


def _drawn_points(cloud: PointCloud, most: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """At most ``most`` of ``cloud``'s points (finite: a PointCloud is) drawn without replacement, with their
    colours (grey where it has none)."""
    keep = np.arange(len(cloud))
    if len(cloud) > most:
        keep = np.sort(rng.choice(len(cloud), most, replace=False))
    colors = np.full((len(cloud), 3), 0.5) if cloud.colors is None else np.clip(cloud.colors, 0.0, 1.0)
    return cloud.xyz[keep], colors[keep]


# ----------------------------------------------------------------------------------------------------
# 2. Training
# ----------------------------------------------------------------------------------------------------
@step_result
class TrainResult:
    """Result of :func:`train_splats`."""

    model: SplatModel
    splats: GaussianSplats
    loss_curve: Curve
    psnr_curve: Curve
    density_curve: Curve
    preview: Image
    warnings: Warnings
    final_loss: float = metric("mean loss over the last 10 % of iterations")
    train_psnr: float = metric("mean PSNR of the training views over the last 10 % of iterations", unit="dB")
    iterations: int = metric("optimizer steps taken")
    train_seconds: float = metric("training time, previews excluded", unit="s")
    gaussians_count: int = metric("Gaussians at the end")
    clones: int = metric("Gaussians cloned by the density control")
    splits: int = metric("Gaussians split by the density control")
    prunes: int = metric("Gaussians pruned by the density control")


def train_splats(gaussians: SplatModel, images: ImageSet, cameras: Cameras, *,
                 iterations: Annotated[int, Range(1, 1000000)] = 3000,
                 budget_seconds: Annotated[float, Range(0.0, 36000.0)] = 60.0,
                 sh_degree: Annotated[int, Range(0, MAX_SH_DEGREE)] = 3,
                 sh_every: Annotated[int, Range(0, 100000)] = 300,
                 densify_from: Annotated[int, Range(0, 100000)] = 100,
                 densify_every: Annotated[int, Range(0, 100000)] = 100,
                 densify_until: Annotated[float, Range(0.0, 1.0)] = 0.6,
                 grad_threshold: Annotated[float, Range(0.0, 1.0)] = 0.0002,
                 percent_dense: Annotated[float, Range(0.0, 1.0)] = 0.01,
                 min_opacity: Annotated[float, Range(0.0, 1.0)] = 0.005,
                 opacity_reset_every: Annotated[int, Range(0, 100000)] = 1500,
                 ssim_weight: Annotated[float, Range(0.0, 1.0)] = 0.2,
                 preview_every: Annotated[int, Range(10, 100000)] = 100,
                 background: Literal["white", "black"] = "white",
                 rng: np.random.Generator, device: str = "cpu") -> Generator[Progress, None, TrainResult]:
    """Fit the Gaussians to the training views (Kerbl et al. 2023, sections 5 and 7.1; :mod:`.training`).

    Each iteration renders one training view with the fast rasterizer over ``background``, takes
    ``(1 - ssim_weight) L1 + ssim_weight D-SSIM`` (eq. 7) and an Adam step on every parameter (the means'
    learning rate decaying a hundredfold over the run). Every ``sh_every`` iterations the colour gains a
    spherical-harmonic degree, up to ``sh_degree``. Every ``densify_every`` iterations from
    ``densify_from`` on, until ``densify_until`` of the run, Gaussians whose mean view-space positional
    gradient exceeds ``grad_threshold`` are cloned (if at most ``percent_dense`` of the scene extent) or
    split, and those under ``min_opacity`` pruned; opacities are reset to 0.01 every
    ``opacity_reset_every``. The paper's schedule (30k iterations: densify from 500 to 15k every 100,
    reset every 3k, a degree every 1k) is scaled here to runs of minutes. Stops after ``iterations`` or
    ``budget_seconds`` (0: no limit). Yields the loss every 10 iterations and a preview of training view
    0 every ``preview_every``.

    Args:
        iterations: most optimizer steps.
        budget_seconds: most seconds of training (0: only the iterations count).
        sh_degree: the highest spherical-harmonic degree of the colours.
        sh_every: iterations between two raises of the degree (0: stay at degree 0).
        densify_from: first iteration of the density control.
        densify_every: iterations between two density controls (0: none).
        densify_until: fraction of the run after which the set of Gaussians stays as it is.
        grad_threshold: mean view-space positional gradient (NDC) above which a Gaussian is densified.
        percent_dense: largest scale, as a fraction of the scene extent, of a Gaussian cloned, not split.
        min_opacity: Gaussians less opaque are pruned.
        opacity_reset_every: iterations between two opacity resets (0: none).
        ssim_weight: lambda, the weight of D-SSIM in the loss.
        preview_every: iterations between two previews.
        background: the colour behind the Gaussians (white for object datasets).
    """
    pixels = training_views(images, cameras).astype(np.float32)
    start = as_model(gaussians)
    initial = SplatModel(start.means, start.log_scales, start.quats, start.opacity_logits, start.sh,
                         sh_degree=start.sh_degree, background=np.asarray(BACKGROUNDS[background]))
    options = SplatTrainingOptions(iterations, budget_seconds, sh_degree, sh_every, densify_from,
                                   densify_every, densify_until, grad_threshold, percent_dense, min_opacity,
                                   opacity_reset_every, ssim_weight, preview_every)
    run = yield from train_gaussians(initial, pixels, cameras, options, preview_view=0, rng=rng,
                                     device=device)
    warnings = _check_run(run, iterations, budget_seconds)
    tail = max(1, run.iterations // 10)
    loss_curve, psnr_curve, density_curve = _curves(run)
    preview = render_model(run.model, cameras, 0, device=device)
    events = run.events
    return TrainResult(run.model, run.model.splats(), loss_curve, psnr_curve, density_curve,
                       Image(preview, name="training view 0"), warnings, float(run.losses[-tail:].mean()),
                       float(np.minimum(run.psnrs[-tail:], 99.0).mean()), run.iterations, run.seconds,
                       len(run.model), sum(e.clones for e in events), sum(e.splits for e in events),
                       sum(e.prunes for e in events))


def _check_run(run: SplatTrainingRun, iterations: int, budget_seconds: float) -> tuple[str, ...]:
    """A warning for a run that stopped before its iterations and its budget (cancelled: the Gaussians
    trained so far are the result)."""
    if run.iterations < iterations and not 0 < budget_seconds <= run.seconds:
        return (f"stopped after {run.iterations} of {iterations} iterations: the Gaussians trained so far "
                "are kept",)
    return ()


def _curves(run: SplatTrainingRun) -> tuple[Curve, Curve, Curve]:
    """The loss and training-view PSNR (running means over a twentieth of the run) and, per density control,
    the Gaussians cloned, split, pruned and held."""
    window = max(1, run.iterations // 20)
    kernel = np.ones(window) / window
    x = np.arange(len(run.losses) - window + 1, dtype=np.float64) + window
    loss = Curve(x, np.convolve(run.losses, kernel, mode="valid"), title="training loss", xlabel="iteration",
                 ylabel="0.8 L1 + 0.2 D-SSIM", labels=(f"loss (mean of {window})",))
    psnr = Curve(x, np.convolve(np.minimum(run.psnrs, 99.0), kernel, mode="valid"), title="training PSNR",
                 xlabel="iteration", ylabel="dB", labels=(f"training view PSNR (mean of {window})",))
    events = run.events
    steps = np.asarray([e.iteration for e in events], np.float64)
    counts = np.asarray([[e.clones for e in events], [e.splits for e in events], [e.prunes for e in events],
                         [e.count for e in events]], np.float64).reshape(4, len(events))
    density = Curve(steps, counts, title="adaptive density control", xlabel="iteration", ylabel="Gaussians",
                    labels=("cloned", "split", "pruned", "held"))
    return loss, psnr, density


# ----------------------------------------------------------------------------------------------------
# 3-4. Rendering
# ----------------------------------------------------------------------------------------------------
def render_model(model: SplatModel, cameras: Cameras, index: int, *, device: str = "cpu") -> np.ndarray:
    """Camera ``index`` of ``cameras`` rendered from ``model`` (no gradient): RGB float32 ``(H, W, 3)`` in
    [0, 1]."""
    model = as_model(model, "model")
    if torch.device(device).type == "cpu":           # all compiled (rasterize.render_image)
        pixels = render_image(model.means, model.log_scales, model.quats, model.opacity_logits, model.sh,
                              view_of(cameras, index), sh_degree=model.sh_degree, background=model.background)
        return np.clip(pixels, 0.0, 1.0)
    t = model.tensors(device=device)
    with torch.no_grad():
        image = render(t["means"], t["log_scales"], t["quats"], t["opacity_logits"], t["sh"],
                       view_of(cameras, index, device=device), sh_degree=model.sh_degree,
                       background=torch.as_tensor(model.background, device=device)).image
    return np.clip(image.cpu().numpy(), 0.0, 1.0).astype(np.float32)


@step_result
class HeldOutResult:
    """Result of :func:`render_held_out`."""

    test_renders: ImageSet
    held_out_cameras: Cameras
    render_seconds: float = metric("time to render every held-out view", unit="s")


def render_held_out(model: SplatModel, test_cameras: Cameras, *, device: str = "cpu") -> HeldOutResult:
    """Render every held-out view with the fast rasterizer, for evaluation (PSNR and SSIM against the
    truth, :func:`lab.modules.nerf.evaluate_held_out`). ``held_out_cameras`` are the held-out cameras
    carrying their renders (a click on a pixel of one lists the Gaussians it is made of,
    :func:`render_view`)."""
    if not isinstance(test_cameras, Cameras) or len(test_cameras) == 0:
        raise InvalidValue("test_cameras", "expected the held-out Cameras")
    started = time.perf_counter()
    renders = [render_model(model, test_cameras, i, device=device) for i in range(len(test_cameras))]
    seconds = time.perf_counter() - started
    images = ImageSet(tuple(Image(r, name=f"held-out {i}") for i, r in enumerate(renders)))
    carrying = Cameras(test_cameras.K, test_cameras.R, test_cameras.t, test_cameras.width,
                       test_cameras.height, dist=test_cameras.dist, image="test_renders")
    return HeldOutResult(images, carrying, seconds)


#: Most Gaussians of a pixel listed in its chart (front to back).
PIXEL_LIST = 40


@step_result
class ViewResult:
    """Result of :func:`render_view`."""

    rendered: Image
    pixel_gaussians: Curve
    pixel_splats: PointCloud
    render_seconds: float = metric("time to render the view", unit="s")
    pixel_count: int = metric("Gaussians composited into the chosen pixel")
    pixel_transmittance: float = metric("transmittance left for the background at the chosen pixel")


def render_view(model: SplatModel, test_cameras: Cameras, *,
                view: Annotated[int, Range(0, 1000)] = 0, pixel_u: Annotated[int, Range(-1, 10000)] = -1,
                pixel_v: Annotated[int, Range(-1, 10000)] = -1, device: str = "cpu") -> ViewResult:
    """Render held-out camera ``view``, and list the Gaussians pixel ``(pixel_u, pixel_v)`` is made of
    (:func:`~.contributions.pixel_contributions`): front to back, each one's alpha, the transmittance
    ``T_i`` it meets and its weight ``w_i = alpha_i T_i`` (eq. 3; the first :data:`PIXEL_LIST` charted),
    their centres drawn in 3D (``pixel_splats``). A click on a held-out view's pixel runs this step for it.

    Args:
        view: the held-out camera.
        pixel_u: column of the pixel whose Gaussians are listed (-1: the centre column).
        pixel_v: row of that pixel (-1: the centre row).
    """
    model = as_model(model, "model")
    if not 0 <= view < len(test_cameras):
        raise InvalidControl("view", f"must be in [0, {len(test_cameras) - 1}], got {view}")
    u = test_cameras.width // 2 if pixel_u < 0 else pixel_u
    v = test_cameras.height // 2 if pixel_v < 0 else pixel_v
    started = time.perf_counter()
    image = render_model(model, test_cameras, view, device=device)
    seconds = time.perf_counter() - started
    found = pixel_contributions(model, test_cameras, view, u, v)
    return ViewResult(Image(image, name=f"held-out view {view}"), _pixel_chart(found),
                      PointCloud(model.means[found.ids].astype(np.float64)), seconds, len(found),
                      found.remaining)


def _pixel_chart(found: PixelContributions) -> Curve:
    """Bars of alpha, transmittance and weight per Gaussian of a pixel, front to back (one empty bar where
    no Gaussian covers it)."""
    shown = min(len(found), PIXEL_LIST)
    title = f"Gaussians of pixel ({found.u}, {found.v}), front to back"
    if shown == 0:
        return Curve(np.zeros(1), np.zeros((3, 1)), kind="bar", title=f"no Gaussian covers pixel ({found.u}, "
                     f"{found.v}): the background", xlabel="Gaussian", ylabel="",
                     labels=("alpha", "T before", "weight"), categories=("none",))
    if shown < len(found):
        title += f" (the first {shown} of {len(found)})"
    return Curve(np.arange(shown, dtype=np.float64),
                 np.stack([found.alphas[:shown], found.before[:shown], found.weights[:shown]]), kind="bar",
                 title=title, xlabel="Gaussian (index in the model)", ylabel="",
                 labels=("alpha", "T before", "weight alpha T"),
                 categories=tuple(f"#{i}" for i in found.ids[:shown]))


# ----------------------------------------------------------------------------------------------------
# 5. Novel views along a path
# ----------------------------------------------------------------------------------------------------
@step_result
class PathResult:
    """Result of :func:`render_path`."""

    path_frames: ImageSet
    path_cameras: Cameras
    render_seconds: float = metric("time to render every frame", unit="s")


def render_path(model: SplatModel, cameras: Cameras, bounds: SceneBounds, *,
                frames: Annotated[int, Range(2, 360)] = 24, scale: Annotated[float, Range(0.05, 4.0)] = 1.0,
                device: str = "cpu") -> Generator[Progress, None, PathResult]:
    """Novel views along an orbit about the scene centre at the training cameras' mean height and distance
    (the NeRF module's :func:`~lab.modules.nerf.orbit_path`, so both modules fly the same path), rendered
    by the fast rasterizer at ``scale`` times the training resolution. ``path_cameras`` carry their frames;
    the frames are exported as an animated GIF (``vision-lab export splatting --format gif``). Yields each
    frame as it is rendered.

    Args:
        frames: views along the full turn.
        scale: their resolution as a fraction of the training cameras'.
    """
    model = as_model(model, "model")
    if not isinstance(cameras, Cameras) or len(cameras) == 0:
        raise InvalidValue("cameras", "expected the training Cameras (the orbit follows their height)")
    path = orbit_path(cameras, bounds.center, frames, scale=scale)
    rendered: list[Image] = []
    started = time.perf_counter()
    for i in range(frames):
        rendered.append(Image(render_model(model, path, i, device=device), name=f"frame {i}"))
        yield Progress(iteration=i + 1, total=frames, message=f"frame {i + 1} of {frames}",
                       values={"frame": rendered[-1]})
    seconds = time.perf_counter() - started
    carrying = Cameras(path.K, path.R, path.t, path.width, path.height, image="path_frames")
    return PathResult(ImageSet(tuple(rendered)), carrying, seconds)


__all__ = ["BACKGROUNDS", "PIXEL_LIST", "HeldOutResult", "InitResult", "PathResult", "TrainResult",
           "ViewResult", "initial_model", "initialize_gaussians", "render_held_out", "render_model",
           "render_path", "render_view", "train_splats"]
