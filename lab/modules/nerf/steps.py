"""The steps of the NeRF module, in pipeline order: each reads state by name and returns what it writes.

1. :func:`generate_rays`     a ray through every training pixel (OpenCV cameras, pixel centres)
2. :func:`encode_positions`  the positional encoding gamma(p), shown as curves
3. :func:`fit_image_2d`      the 2D warm-up: one image fitted with and without the encoding
4. :func:`train_nerf`        the MLP trained by volume rendering batches of rays (a generator step)
5. :func:`render_held_out`   the held-out views rendered (evaluated: PSNR, SSIM, depth error)
6. :func:`render_view`       one view with its depth and opacity, and the weights along one ray
7. :func:`render_path`       novel views along an orbit (frames, exported as a GIF)
8. :func:`extract_mesh`      the density's level set by marching cubes, coloured (exported as PLY, GLB)

Reference: B. Mildenhall, P. P. Srinivasan, M. Tancik, J. T. Barron, R. Ramamoorthi, R. Ng, "NeRF:
Representing scenes as neural radiance fields for view synthesis", ECCV 2020.
"""

from __future__ import annotations

import time
from collections.abc import Generator
from typing import Annotated, Literal

import numpy as np
import torch

from lab.core import (Cameras, CapacityExceeded, Curve, Image, ImageSet, InvalidControl, InvalidValue, Mesh,
                      PointCloud, Progress, Range, Segments3D, Warnings, metric, step_result)
from lab.core.threads import single_threaded
from lab.modules.nerf.encoding import encoding_size, positional_encoding
from lab.modules.nerf.evaluate import image_psnr
from lab.modules.nerf.grid import (GridCheckpoint, GridField, GridOptions, grid_checkpoint_from, grid_from,
                                   grid_step, render_grid, render_grid_image, train_grid_field)
from lab.modules.nerf.mesh import coloured_mesh, density_lattice, head_on_rays, iso_surface
from lab.modules.nerf.model import (ImageRendering, NerfMLP, checkpoint_from, network_from, render_image,
                                    render_rays)
from lab.modules.nerf.path import orbit_path
from lab.modules.nerf.preview import FollowedPreview, offering_preview
from lab.modules.nerf.rays import cameras_rays, scaled_cameras
from lab.modules.nerf.training import PreviewRays, TrainingOptions, TrainingRun, train_field, training_curves
from lab.modules.nerf.values import (EncodingConfig, FieldConfig, NerfCheckpoint, RayBundle, SceneBounds,
                                     as_bounds, as_encoding, as_rays)
from lab.modules.nerf.warmup import ImageFit, fit_image, fitting_target

#: Largest side of the preview rendered while training.
PREVIEW_SIDE = 64
#: Most samples (rays x samples per ray) one MLP batch may hold, and most activations (samples x width):
#: about a gigabyte of what the backward pass keeps.
MAX_BATCH_SAMPLES = 2**21
MAX_BATCH_ACTIVATIONS = 2**27

BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def training_views(images: ImageSet, cameras: Cameras) -> np.ndarray:
    """The training images as one float32 ``(V, H, W, 3)`` array, once they fit their cameras (one camera
    per view, of its size, colour); NeRF's and splatting's training read their views through it."""
    if not isinstance(images, ImageSet) or len(images) == 0:
        raise InvalidValue("images", "expected a non-empty ImageSet of training views")
    if not isinstance(cameras, Cameras):
        raise InvalidValue("cameras", f"expected Cameras, got {type(cameras).__name__}")
    if len(images) != len(cameras):
        raise InvalidValue("images", f"{len(images)} images for {len(cameras)} cameras: one camera per "
                                     "training view")
    for i, image in enumerate(images.images):
        if (image.width, image.height) != (cameras.width, cameras.height):
            raise InvalidValue("images", f"view {i} is {image.width}x{image.height} but the cameras are "
                                         f"{cameras.width}x{cameras.height}: every view must match its "
                                         "camera")
        if image.pixels.ndim != 3:
            raise InvalidValue("images", f"view {i} is grey: a radiance field learns colour images (H, W, 3)")
    return np.stack([image.pixels for image in images.images])


# ----------------------------------------------------------------------------------------------------
# 1. Rays
# ----------------------------------------------------------------------------------------------------
@step_result
class RaysResult:
    """Result of :func:`generate_rays`."""

    rays: RayBundle
    ray_lines: Segments3D
    ray_count: int = metric("training rays (one per pixel of every view)")
    views: int = metric("training views")


def generate_rays(images: ImageSet, cameras: Cameras, bounds: SceneBounds, *,
                  lines: Annotated[int, Range(0, 5000)] = 200) -> RaysResult:
    """A ray through the centre of every training pixel, with the pixel's colour (Mildenhall et al. 2020,
    section 4; ``get_rays`` of their code, without its half-pixel offset).

    Origin ``-R^T t``, direction ``R^T K^-1 (u, v, 1)`` with pixel ``(j, i)``'s centre at ``(u, v) = (j, i)``
    (the lab's convention; ``(j + 0.5, i + 0.5)`` where the top-left corner is the origin). A direction's
    camera-frame z is 1, so the ray parameter is the depth and ``bounds.near`` / ``bounds.far`` are depths.
    ``ray_lines`` draws ``lines`` of them (evenly picked) from near to far in their pixel's colour.

    Args:
        lines: rays drawn in 3D.
    """
    pixels = training_views(images, cameras)
    scene = as_bounds(bounds)
    origins, directions = cameras_rays(cameras)
    count = origins.shape[0] * origins.shape[1]
    views = np.repeat(np.arange(len(cameras)), origins.shape[1])
    rays = RayBundle(origins.reshape(count, 3).numpy(), directions.reshape(count, 3).numpy(),
                     pixels.reshape(count, 3), views, scene)
    pick = np.linspace(0, count - 1, min(lines, count)).astype(np.int64) if lines else np.zeros(0, np.int64)
    o, d = rays.origins[pick].astype(np.float64), rays.directions[pick].astype(np.float64)
    drawn = Segments3D(o + scene.near * d, o + scene.far * d, rays.colors[pick])
    return RaysResult(rays, drawn, count, len(cameras))


# ----------------------------------------------------------------------------------------------------
# 2. Positional encoding
# ----------------------------------------------------------------------------------------------------
@step_result
class EncodingResult:
    """Result of :func:`encode_positions`."""

    encoding: EncodingConfig
    encoding_plot: Curve
    position_features: int = metric("width of gamma(x) for a position")
    direction_features: int = metric("width of gamma(d) for a view direction")


def encode_positions(*, frequencies: Annotated[int, Range(0, 16)] = 6,
                     direction_frequencies: Annotated[int, Range(0, 8)] = 4,
                     include_input: bool = True) -> EncodingResult:
    """The positional encoding ``gamma(p) = (sin(2^k pi p), cos(2^k pi p))``, ``k < L`` (Mildenhall et al.
    2020, section 5.1; they use L = 10 for positions, 4 for directions; 6 is the classic course project's).

    Without it the MLP is biased towards smooth functions and blurs the scene (their Figure 4). The plot
    shows ``p`` and ``sin(2^k pi p)`` for one coordinate over the normalized scene ``[-1, 1]``: each
    frequency doubles.

    Args:
        frequencies: L for positions.
        direction_frequencies: L for view directions.
        include_input: put p itself in front of gamma(p), as the paper's code does.
    """
    encoding = EncodingConfig(frequencies, direction_frequencies, include_input)
    x = np.linspace(-1.0, 1.0, 401)
    gamma = positional_encoding(torch.as_tensor(x[:, None]), frequencies, include_input=False).numpy()
    series = [x] + [gamma[:, 2 * k] for k in range(frequencies)]
    labels = ("p", *(f"sin(2^{k} pi p)" for k in range(frequencies)))
    plot = Curve(x, np.stack(series), title="positional encoding", xlabel="p (normalized)", ylabel="value",
                 labels=labels)
    return EncodingResult(encoding, plot, encoding_size(frequencies, include_input=include_input),
                          encoding_size(direction_frequencies, include_input=include_input))


# ----------------------------------------------------------------------------------------------------
# 3. The 2D warm-up
# ----------------------------------------------------------------------------------------------------
@step_result
class ImageFitResult:
    """Result of :func:`fit_image_2d`."""

    fit_psnr: Curve
    fit_images: ImageSet
    psnr_without_encoding: float = metric("PSNR of the fit without the encoding, after the last step",
                                          unit="dB")
    psnr_with_encoding: float = metric("PSNR of the fit with the largest L, after the last step", unit="dB")


def fit_image_2d(images: ImageSet, *, view: Annotated[int, Range(0, 1000)] = 0,
                 side: Annotated[int, Range(8, 256)] = 64,
                 frequencies: Annotated[tuple[int, int, int], Range(1, 10)] = (2, 4, 6),
                 hidden: Annotated[int, Range(8, 256)] = 64, layers: Annotated[int, Range(1, 8)] = 3,
                 iterations: Annotated[int, Range(1, 10000)] = 300,
                 learning_rate: Annotated[float, Range(1e-5, 1.0)] = 3e-3,
                 rng: np.random.Generator, device: str = "cpu") -> Generator[Progress, None, ImageFitResult]:
    """Why NeRF encodes positions, in 2D: fit training image ``view`` (shrunk to at most ``side`` px) with
    a coordinate MLP ``(x, y) -> RGB`` on the raw coordinates and on ``gamma(x, y)`` with each of
    ``frequencies`` L (Tancik et al. 2020, "Fourier features let networks learn high frequency functions",
    Figure 1; Mildenhall et al. 2020, section 5.1). Every fit has the same network, initial weights and
    Adam steps on all pixels (torch on one CPU thread: a small MLP); ``fit_psnr`` plots their PSNR over
    the steps side by side, ``fit_images`` holds the target and the fitted images.

    Args:
        view: the training image to fit.
        side: its longer side after shrinking (pixels).
        frequencies: the values of L compared with no encoding.
        hidden: width of the MLP.
        layers: hidden layers of the MLP.
        iterations: Adam steps per fit (one step sees every pixel).
        learning_rate: Adam's learning rate.
    """
    if not isinstance(images, ImageSet) or len(images) == 0:
        raise InvalidValue("images", "expected a non-empty ImageSet to fit")
    if not 0 <= view < len(images):
        raise InvalidControl("view", f"must be in [0, {len(images) - 1}], got {view}")
    target = fitting_target(images[view].pixels, side)
    seed = int(rng.integers(0, 2**62))
    fits: list[ImageFit] = []
    levels = (0, *sorted(set(frequencies)))
    with single_threaded(device == "cpu"):  # a small MLP: more threads only spin on shared cores
        for k, level in enumerate(levels):
            fit = yield from fit_image(target, level, hidden=hidden, layers=layers, iterations=iterations,
                                       learning_rate=learning_rate, seed=seed, device=device,
                                       before=k * iterations, total=len(levels) * iterations)
            fits.append(fit)
    names = [("no encoding" if f.frequencies == 0 else f"L = {f.frequencies}") for f in fits]
    curve = Curve(np.arange(1, iterations + 1, dtype=np.float64), np.stack([f.psnrs for f in fits]),
                  title="fitting one image: PSNR over Adam steps", xlabel="step", ylabel="dB",
                  labels=tuple(names))
    pictures = (Image(target, name="target"),
                *(Image(np.clip(f.image, 0, 1), name=f"{n}: {image_psnr(f.image, target):.1f} dB")
                  for f, n in zip(fits, names, strict=True)))
    return ImageFitResult(curve, ImageSet(pictures), float(fits[0].psnrs[-1]), float(fits[-1].psnrs[-1]))


# ----------------------------------------------------------------------------------------------------
# 4. Training
# ----------------------------------------------------------------------------------------------------
@step_result
class TrainResult:
    """Result of :func:`train_nerf`."""

    model: NerfCheckpoint | GridCheckpoint
    loss_curve: Curve
    psnr_curve: Curve
    preview: Image
    warnings: Warnings
    final_loss: float = metric("mean photometric loss over the last 10 % of iterations")
    train_psnr: float = metric("mean batch PSNR over the last 10 % of iterations", unit="dB")
    iterations: int = metric("optimizer steps taken")
    train_seconds: float = metric("training time, previews excluded", unit="s")
    rays_per_second: float = metric("training rays rendered per second")
    samples_per_ray: float = metric("samples per ray evaluated with gradient (last tenth of the run)")


def train_nerf(rays: RayBundle, encoding: EncodingConfig, cameras: Cameras, *,
               method: Literal["mlp", "grid"] = "mlp",
               samples: Annotated[int, Range(2, 512)] = 32, fine_samples: Annotated[int, Range(0, 512)] = 0,
               hidden: Annotated[int, Range(8, 512)] = 64, layers: Annotated[int, Range(1, 12)] = 4,
               grid_resolution: Annotated[int, Range(8, 256)] = 128,
               batch_rays: Annotated[int, Range(1, 65536)] = 1024,
               learning_rate: Annotated[float, Range(1e-6, 1.0)] = 5e-3,
               grid_learning_rate: Annotated[float, Range(1e-6, 10.0)] = 0.6,
               lr_decay: Annotated[float, Range(1e-4, 1.0)] = 0.1,
               grid_tv: Annotated[float, Range(0.0, 1.0)] = 1e-3,
               iterations: Annotated[int, Range(1, 1000000)] = 1000,
               budget_seconds: Annotated[float, Range(0.0, 36000.0)] = 60.0,
               preview_every: Annotated[int, Range(10, 100000)] = 100,
               background: Literal["white", "black"] = "white",
               rng: np.random.Generator, device: str = "cpu") -> Generator[Progress, None, TrainResult]:
    """Train the radiance field: render random batches of training rays and fit their pixels' colours
    (Mildenhall et al. 2020, sections 4 and 5.3).

    ``mlp`` (the NeRF): each ray gets ``samples`` jittered stratified depths in ``[near, far]`` (eq. 2)
    and, with ``fine_samples`` > 0, that many more drawn from the coarse weights by inverse-CDF sampling
    (section 5.2); the MLP gives density and colour at every sample and volume rendering (eq. 3)
    composites them over the ``background``; Adam with ``learning_rate`` decaying exponentially to
    ``lr_decay`` times its start over the budget. The defaults are the classic course project's "vanilla"
    NeRF scaled to a CPU (their batch: 4096 rays). ``grid`` (the accelerated variant,
    :mod:`~lab.modules.nerf.grid`): density and colour on a voxel grid trained coarse to fine up to
    ``grid_resolution``^3 with ``grid_learning_rate`` and a total-variation penalty of weight ``grid_tv``,
    empty space skipped and rays terminated early.
    Stops after ``iterations`` or ``budget_seconds`` of training (0: no time limit), whichever comes
    first. Yields the loss and PSNR every 10 iterations and a preview (at most 64 px) every
    ``preview_every``: of training view 0, or of the camera the viewer makes it follow (the browser's,
    :mod:`~lab.modules.nerf.preview`: each snapshot offers the follower); the result's ``preview`` is
    training view 0.

    Args:
        method: mlp (NeRF's network) or grid (the accelerated voxel grid).
        samples: stratified samples per ray (mlp).
        fine_samples: extra samples per ray from the coarse weights (mlp; 0: no hierarchical sampling).
        hidden: width of the MLP.
        layers: layers of the MLP's trunk (from 4 on, gamma(x) is fed again half way).
        grid_resolution: vertices per side of the finest grid (grid).
        batch_rays: rays per optimizer step.
        learning_rate: Adam's initial learning rate (mlp).
        grid_learning_rate: Adam's initial learning rate on the grid's values (grid).
        lr_decay: the learning rate at the end of the budget, as a fraction of the initial one (mlp).
        grid_tv: weight of the total-variation penalty on the grid's raw density and colours (grid; 0:
            none): neighbouring vertices alike unless the images say otherwise.
        iterations: most optimizer steps.
        budget_seconds: most seconds of training (0: only the iterations count).
        preview_every: iterations between two preview renderings.
        background: the colour behind the scene (white for object datasets).
    """
    bundle = as_rays(rays)
    _check_batch(method, batch_rays, samples + fine_samples, hidden)
    colour = torch.tensor(BACKGROUNDS[background], dtype=torch.float32, device=device)
    small = scaled_cameras(cameras, min(1.0, PREVIEW_SIDE / max(cameras.width, cameras.height)))
    origins, directions = cameras_rays(small, device=device)
    view0 = PreviewRays(origins[0], directions[0], (small.height, small.width))
    preview = FollowedPreview(cameras, bundle.bounds, device=device, still_side=PREVIEW_SIDE)
    back = np.asarray(BACKGROUNDS[background])
    model: NerfCheckpoint | GridCheckpoint
    if method == "grid":
        grid_options = GridOptions(grid_resolution, batch_rays, grid_learning_rate, iterations,
                                   budget_seconds, preview_every, tv_density=grid_tv, tv_color=grid_tv)
        run = yield from offering_preview(train_grid_field(bundle, grid_options, background=colour,
                                                           preview=preview, rng=rng, device=device), preview)
        assert isinstance(run.net, GridField)
        model = grid_checkpoint_from(run.net, bundle.bounds, back)
    else:
        config = FieldConfig(as_encoding(encoding), hidden, layers, samples, fine_samples)
        options = TrainingOptions(batch_rays, learning_rate, lr_decay, iterations, budget_seconds,
                                  preview_every)
        run = yield from offering_preview(train_field(bundle, config, options, background=colour,
                                                      preview=preview, rng=rng, device=device), preview)
        assert isinstance(run.net, NerfMLP)
        model = checkpoint_from(run.net, bundle.bounds, back)
    warnings = _check_run(run, iterations, budget_seconds)
    tail = max(1, run.iterations // 10)
    loss_curve, psnr_curve = training_curves(run)
    final = FieldRenderer(model, device).image(view0.origins, view0.directions, view0.shape)
    return TrainResult(model, loss_curve, psnr_curve, Image(final.color, name="training view 0"), warnings,
                       float(run.losses[-tail:].mean()), float(np.minimum(run.psnrs[-tail:], 99.0).mean()),
                       run.iterations, run.seconds, run.iterations * batch_rays / max(run.seconds, 1e-9),
                       run.samples_per_ray)


def _check_run(run: TrainingRun, iterations: int, budget_seconds: float) -> tuple[str, ...]:
    """Refuse (:class:`InvalidControl` on ``budget_seconds``) a run whose time budget ran out inside its
    first step (one step of a fresh model is noise); a warning for a run stopped before its iterations and
    its budget (cancelled: the model trained so far is the result)."""
    ran_out = 0 < budget_seconds <= run.seconds
    if ran_out and run.iterations <= 1 < iterations:
        raise InvalidControl("budget_seconds", f"{budget_seconds:g} s ran out during the first "
                                               f"training step ({run.seconds:.2g} s): give a budget of many "
                                               "steps, or 0 for no time limit")
    if run.iterations < iterations and not ran_out:
        return (f"stopped after {run.iterations} of {iterations} iterations: the model trained so far is "
                "kept",)
    return ()


def _check_batch(method: str, batch_rays: int, samples: int, hidden: int) -> None:
    """Refuse (:class:`CapacityExceeded`) an MLP batch whose backward pass would hold more than about a GB."""
    if method != "mlp":
        return
    if batch_rays * samples > MAX_BATCH_SAMPLES:
        raise CapacityExceeded("batch_rays", f"{batch_rays} rays x {samples} samples is more than "
                                             f"{MAX_BATCH_SAMPLES} samples a batch: use fewer rays or "
                                             "samples")
    if batch_rays * samples * hidden > MAX_BATCH_ACTIVATIONS:
        raise CapacityExceeded("hidden", f"{batch_rays} rays x {samples} samples x {hidden} wide is more "
                                         f"than {MAX_BATCH_ACTIVATIONS} activations a layer: use a narrower "
                                         "MLP or fewer rays")


# ----------------------------------------------------------------------------------------------------
# 5-6. Rendering
# ----------------------------------------------------------------------------------------------------
class FieldRenderer:
    """A trained model (either kind) made ready to render on ``device``: whole views and single rays."""

    def __init__(self, model: object, device: str) -> None:
        if not isinstance(model, (NerfCheckpoint, GridCheckpoint)):
            raise InvalidValue("model", f"expected a NerfCheckpoint or a GridCheckpoint, got "
                                        f"{type(model).__name__}: run train_nerf")
        self.model = model
        self.device = device
        self.background = torch.as_tensor(model.background, device=device)
        self.net = network_from(model, device) if isinstance(model, NerfCheckpoint) else None
        self.grid = grid_from(model, device) if isinstance(model, GridCheckpoint) else None

    def image(self, origins: torch.Tensor, directions: torch.Tensor, shape: tuple[int, int], *,
              bounds: SceneBounds | None = None, background: torch.Tensor | None = None) -> ImageRendering:
        """One view from its rays ``(H * W, 3)``; sampled between the model's near and far unless ``bounds``
        (with the model's centre and radius) says otherwise, over the model's background unless
        ``background`` ``(3,)``."""
        bounds = self.model.bounds if bounds is None else bounds
        background = self.background if background is None else background
        if self.grid is not None:
            return render_grid_image(self.grid, origins, directions, bounds, shape, background=background)
        assert self.net is not None
        return render_image(self.net, origins, directions, bounds, shape, background=background)

    def ray(self, origin: torch.Tensor, direction: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """Depths and weights of the samples of one ray ``(1, 3)`` (of its last pass; a grid's evaluated
        samples)."""
        with torch.no_grad():
            if self.grid is not None:
                out, t = render_grid(self.grid, origin, direction, self.model.bounds,
                                     step=grid_step(self.grid), background=self.background,
                                     occupied=self.grid.occupancy())
                return t.cpu().numpy(), out.weights.cpu().numpy()
            assert self.net is not None
            ray = render_rays(self.net, origin, direction, self.model.bounds, background=self.background,
                              jitter=False)
            t = ray.t_coarse if ray.t_fine is None else ray.t_fine
            return t[0].cpu().numpy(), ray.final.weights[0].cpu().numpy()

    def views(self, cameras: Cameras) -> list[ImageRendering]:
        """Every view of ``cameras``."""
        origins, directions = cameras_rays(cameras, device=self.device)
        shape = (cameras.height, cameras.width)
        return [self.image(origins[v], directions[v], shape) for v in range(len(cameras))]


@step_result
class HeldOutResult:
    """Result of :func:`render_held_out`."""

    test_renders: ImageSet
    test_depth: np.ndarray
    test_opacity: np.ndarray
    held_out_cameras: Cameras
    render_seconds: float = metric("time to render every held-out view", unit="s")


#: The most rays per pixel along each axis that :func:`render_held_out` takes from a dataset's
#: ``pixel_supersample`` (a Blender scene shrunk 8 times would ask for 64 rays a pixel; 4 x 4 points estimate
#: the same area mean closely at a quarter of the cost).
MAX_HELD_OUT_SUPERSAMPLE = 4


def held_out_supersample(supersample: int, pixel_supersample: int | None) -> int:
    """Rays per pixel along each axis for :func:`render_held_out`: ``supersample`` where it is given (> 0),
    else the dataset's ``pixel_supersample`` (how its images were made), at most
    :data:`MAX_HELD_OUT_SUPERSAMPLE`; 1 (the pixel centre) for a dataset that does not say."""
    if supersample > 0:
        return supersample
    if pixel_supersample is None:
        return 1
    if isinstance(pixel_supersample, bool) or not isinstance(pixel_supersample, (int, np.integer)) \
            or pixel_supersample < 1:
        raise InvalidValue("pixel_supersample", f"expected a positive integer (rays per pixel along each "
                                                f"axis), got {pixel_supersample!r}")
    return min(int(pixel_supersample), MAX_HELD_OUT_SUPERSAMPLE)


def render_held_out(model: NerfCheckpoint | GridCheckpoint, test_cameras: Cameras,
                    pixel_supersample: int | None = None, *,
                    supersample: Annotated[int, Range(0, 8)] = 0, device: str = "cpu") -> HeldOutResult:
    """Render every held-out view (no jitter; fine samples placed deterministically) for evaluation:
    colour ``(H, W, 3)``, expected depth and opacity ``(H, W)`` per view (see :func:`render_view`);
    ``held_out_cameras`` are the held-out cameras carrying the renders (a click on a pixel of one runs
    :func:`render_view` for its ray in the viewer).

    Each pixel is rendered the way the dataset made its images, so that the comparison is like for like:
    a rendered or photographed pixel is the mean of the light over its area, and the synthetic object's
    images are means of 2 x 2 rays inside each pixel (``pixel_supersample`` in the state, the dataset's;
    a NeRF-synthetic folder shrunk ``f`` times: ``f``). So the view is rendered at ``s`` times its
    resolution (:func:`~lab.modules.nerf.rays.scaled_cameras`: rays through an ``s x s`` grid of points
    inside each pixel, those of the renderer's supersampling) and box-filtered back
    (:meth:`~lab.modules.nerf.model.ImageRendering.box_filtered`): colour, depth and opacity are each
    pixel's mean. One ray through each pixel centre would score even the exact scene at only 30.6 dB on
    the synthetic object (its edges and textures are area means). Brute-force supersampling is how
    Mip-NeRF's comparisons render a pixel's area (Barron et al. 2021, section 1).

    Args:
        supersample: rays per pixel along each axis (0: the dataset's ``pixel_supersample``, at most
            4; 1 where the dataset does not say; 1: one ray through each pixel centre).
    """
    renderer = FieldRenderer(model, device)
    factor = held_out_supersample(supersample, pixel_supersample)
    started = time.perf_counter()
    fine = scaled_cameras(test_cameras, factor) if factor > 1 else test_cameras
    views = [view.box_filtered(factor) if factor > 1 else view for view in renderer.views(fine)]
    seconds = time.perf_counter() - started
    return HeldOutResult(ImageSet(tuple(Image(v.color, name=f"held-out {i}") for i, v in enumerate(views))),
                         np.stack([v.depth for v in views]), np.stack([v.opacity for v in views]),
                         Cameras(test_cameras.K, test_cameras.R, test_cameras.t, test_cameras.width,
                                 test_cameras.height, image="test_renders"), seconds)


@step_result
class ViewResult:
    """Result of :func:`render_view`."""

    rendered: Image
    depth_map: Image
    opacity_map: Image
    ray_weights: Curve
    ray_samples: PointCloud
    render_seconds: float = metric("time to render the view", unit="s")


def render_view(model: NerfCheckpoint | GridCheckpoint, test_cameras: Cameras, *,
                view: Annotated[int, Range(0, 1000)] = 0, pixel_u: Annotated[int, Range(-1, 10000)] = -1,
                pixel_v: Annotated[int, Range(-1, 10000)] = -1, device: str = "cpu") -> ViewResult:
    """Render held-out camera ``view``: its colour, its depth map (expected termination depth
    ``sum w_i t_i``, the unabsorbed rest at far; shown from near = black to far = white) and opacity
    ``sum w_i`` (eq. 3), and the weights ``w_i`` along the ray through pixel ``(pixel_u, pixel_v)`` (-1: the
    image centre), over the samples of the last pass: plotted over depth (``ray_weights``) and drawn in 3D
    (``ray_samples``: each sample's point, grey for weight 0 to red for the ray's largest weight).

    Args:
        view: the held-out camera.
        pixel_u: column of the pixel whose ray's weights are plotted (-1: the centre column).
        pixel_v: row of that pixel (-1: the centre row).
    """
    renderer = FieldRenderer(model, device)
    if not 0 <= view < len(test_cameras):
        raise InvalidControl("view", f"must be in [0, {len(test_cameras) - 1}], got {view}")
    u = test_cameras.width // 2 if pixel_u < 0 else pixel_u
    v = test_cameras.height // 2 if pixel_v < 0 else pixel_v
    if u >= test_cameras.width or v >= test_cameras.height:
        raise InvalidControl("pixel_u" if u >= test_cameras.width else "pixel_v",
                             f"pixel ({u}, {v}) is outside the {test_cameras.width}x{test_cameras.height} "
                             "image")
    one = Cameras(test_cameras.K[view], test_cameras.R[view], test_cameras.t[view], test_cameras.width,
                  test_cameras.height)
    started = time.perf_counter()
    image = renderer.views(one)[0]
    seconds = time.perf_counter() - started
    origins, directions = cameras_rays(one, device=device)
    index = v * one.width + u
    t, w = renderer.ray(origins[0, index:index + 1], directions[0, index:index + 1])
    weights = Curve(t, w, title=f"weights along the ray of pixel ({u}, {v})", xlabel="depth t", ylabel="w_i",
                    labels=("w_i = T_i alpha_i",))
    o, d = (a[0, index].double().cpu().numpy() for a in (origins, directions))
    samples = PointCloud(o + t[:, None].astype(np.float64) * d, colors=weight_colors(w))
    near, far = renderer.model.bounds.near, renderer.model.bounds.far
    depth = np.clip((image.depth - near) / (far - near), 0.0, 1.0)
    return ViewResult(Image(image.color, name=f"held-out view {view}"), Image(depth, name="depth"),
                      Image(np.clip(image.opacity, 0.0, 1.0), name="opacity"), weights, samples, seconds)


def weight_colors(weights: np.ndarray) -> np.ndarray:
    """``(S, 3)`` colours of samples by weight: grey (0.6) at 0 to red at the largest weight of the ray."""
    w = np.asarray(weights, dtype=np.float64)
    share = w / w.max() if w.size and w.max() > 0 else np.zeros_like(w)
    return np.stack([0.6 + 0.4 * share, 0.6 * (1.0 - share), 0.6 * (1.0 - share)], axis=1)


# ----------------------------------------------------------------------------------------------------
# 7. Novel views along a path
# ----------------------------------------------------------------------------------------------------
@step_result
class PathResult:
    """Result of :func:`render_path`."""

    path_frames: ImageSet
    path_cameras: Cameras
    render_seconds: float = metric("time to render every frame", unit="s")


def render_path(model: NerfCheckpoint | GridCheckpoint, cameras: Cameras, *,
                frames: Annotated[int, Range(2, 360)] = 24, scale: Annotated[float, Range(0.05, 4.0)] = 1.0,
                device: str = "cpu") -> Generator[Progress, None, PathResult]:
    """Novel views along an orbit about the scene centre at the training cameras' mean height and distance
    (:func:`~lab.modules.nerf.path.orbit_path`: "up" is the mean of the cameras' up vectors, frame 0 at
    training camera 0's azimuth), rendered like a held-out view at ``scale`` times the training
    resolution. ``path_cameras`` carry their frames (drawn as frustums around the scene); the frames are
    exported as an animated GIF (``vision-lab export nerf --format gif``). Yields each frame as it is
    rendered.

    Args:
        frames: views along the full turn.
        scale: their resolution as a fraction of the training cameras'.
    """
    renderer = FieldRenderer(model, device)
    if not isinstance(cameras, Cameras) or len(cameras) == 0:
        raise InvalidValue("cameras", "expected the training Cameras (the orbit follows their height)")
    path = orbit_path(cameras, renderer.model.bounds.center, frames, scale=scale)
    origins, directions = cameras_rays(path, device=device)
    rendered: list[Image] = []
    started = time.perf_counter()
    for i in range(frames):
        view = renderer.image(origins[i], directions[i], (path.height, path.width))
        rendered.append(Image(view.color, name=f"frame {i}"))
        yield Progress(iteration=i + 1, total=frames, message=f"frame {i + 1} of {frames}",
                       values={"frame": rendered[-1]})
    seconds = time.perf_counter() - started
    carrying = Cameras(path.K, path.R, path.t, path.width, path.height, image="path_frames")
    return PathResult(ImageSet(tuple(rendered)), carrying, seconds)


# ----------------------------------------------------------------------------------------------------
# 8. A mesh of the density
# ----------------------------------------------------------------------------------------------------
@step_result
class MeshResult:
    """Result of :func:`extract_mesh`."""

    mesh: Mesh
    vertices: int = metric("mesh vertices")
    faces: int = metric("mesh triangles")
    max_density: float = metric("largest density sigma on the lattice (per scene unit)")


def extract_mesh(model: NerfCheckpoint | GridCheckpoint, *, resolution: Annotated[int, Range(16, 256)] = 96,
                 level: Annotated[float, Range(1e-3, 1e5)] = 5.0, device: str = "cpu") -> MeshResult:
    """The surface where the density crosses ``level``, as a coloured triangle mesh (:mod:`~.mesh`):
    sigma sampled on a ``resolution^3`` lattice over the scene box, ``skimage.measure.marching_cubes``
    at ``level``, each vertex coloured by the volume rendering of a short ray that meets it head on
    (along the density's gradient, from 3 lattice steps outside to 3 inside, its colour divided by its
    opacity). Exported as PLY and GLB (``vision-lab export nerf --format ply``) in the scene's frame.

    Args:
        resolution: lattice points per side of the scene box.
        level: the density sigma (per scene unit) of the surface: higher lies deeper and drops faint parts.
    """
    renderer = FieldRenderer(model, device)
    bounds = renderer.model.bounds
    sigma = density_lattice(renderer.model, resolution, device=device)
    surface = iso_surface(sigma, level, bounds)
    reach = 3.0 * 2.0 * bounds.radius / (resolution - 1)
    origins, directions = head_on_rays(surface, reach)
    segment = SceneBounds(0.0, 2.0 * reach, bounds.center, bounds.radius)
    seen = renderer.image(torch.as_tensor(origins, dtype=torch.float32, device=device),
                          torch.as_tensor(directions, dtype=torch.float32, device=device),
                          (1, len(origins)), bounds=segment,
                          background=torch.zeros(3, dtype=torch.float32, device=device))
    colours = seen.color[0] / np.maximum(seen.opacity[0], 1e-3)[:, None]
    mesh = coloured_mesh(surface, colours)
    return MeshResult(mesh, len(mesh.vertices), len(mesh.faces), float(sigma.max()))


__all__ = ["BACKGROUNDS", "MAX_BATCH_ACTIVATIONS", "MAX_BATCH_SAMPLES", "MAX_HELD_OUT_SUPERSAMPLE",
           "PREVIEW_SIDE", "EncodingResult", "FieldRenderer", "HeldOutResult", "ImageFitResult", "MeshResult",
           "PathResult", "RaysResult", "TrainResult", "ViewResult", "encode_positions", "extract_mesh",
           "fit_image_2d", "generate_rays", "held_out_supersample", "render_held_out", "render_path",
           "render_view", "train_nerf", "training_views"]
