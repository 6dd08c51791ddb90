"""The typed value of Gaussian splatting that flows between steps: :class:`SplatModel` (the trained or
initial Gaussians' raw parameters, before activation, as the paper's code and its PLY files keep them).

It is drawn through :meth:`SplatModel.splats` (the lab's :class:`~lab.core.GaussianSplats`: centres,
covariances, base colours and opacities), and moves to and from torch with :meth:`SplatModel.tensors` and
:func:`model_from_tensors`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from lab.core import CapacityExceeded, GaussianSplats, InvalidValue
from lab.modules.splatting.gaussians import covariances
from lab.modules.splatting.sh import MAX_SH_DEGREE, sh_count, sh_to_rgb

#: Most Gaussians a model may hold (about 0.5 GB of parameters and Adam moments in training).
MAX_GAUSSIANS = 1_000_000
#: The parameter names, in the order the rasterizer takes them.
PARAMETERS = ("means", "log_scales", "quats", "opacity_logits", "sh")
_SHAPES: dict[str, tuple[int, ...]] = {"means": (3,), "log_scales": (3,), "quats": (4,), "opacity_logits": (),
                                       "sh": (sh_count(MAX_SH_DEGREE), 3)}


def check_count(count: int, field: str = "gaussians") -> None:
    """:class:`CapacityExceeded` if ``count`` is more than :data:`MAX_GAUSSIANS`."""
    if count > MAX_GAUSSIANS:
        raise CapacityExceeded(field, f"{count} Gaussians is more than the cap of {MAX_GAUSSIANS}")


@dataclass(frozen=True, eq=False)
class SplatModel:
    """``N`` 3D Gaussians (Kerbl et al. 2023, section 4): ``means`` (N, 3), ``log_scales`` (N, 3),
    unnormalized quaternions ``quats`` (N, 4) ``(w, x, y, z)``, ``opacity_logits`` (N,), spherical-harmonic
    coefficients ``sh`` (N, 16, 3) (degree 0 first) of which degrees up to ``sh_degree`` are used, and the
    ``background`` (3,) they were trained over. float32; every value finite."""

    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray
    sh_degree: int = 0
    background: np.ndarray = field(default_factory=lambda: np.ones(3, np.float32))

    def __post_init__(self) -> None:
        n = len(np.asarray(self.means).reshape(-1, 3))
        check_count(n)
        for name in PARAMETERS:
            array = np.asarray(getattr(self, name), dtype=np.float32)
            if name == "sh" and array.ndim == 3 and array.shape[1] < _SHAPES["sh"][0]:
                missing = np.zeros((n, _SHAPES["sh"][0] - array.shape[1], 3), np.float32)
                array = np.concatenate([array, missing], axis=1)
            if array.shape != (n, *_SHAPES[name]):
                raise InvalidValue(f"gaussians.{name}", f"expected shape {(n, *_SHAPES[name])}, got "
                                                        f"{array.shape}")
            if not np.all(np.isfinite(array)):
                bad = int(np.flatnonzero(~np.isfinite(array.reshape(n, -1)).all(axis=1))[0]) if n else 0
                raise InvalidValue(f"gaussians.{name}", f"Gaussian {bad} has a NaN or infinite {name}")
            object.__setattr__(self, name, np.ascontiguousarray(array))
        if n and np.any(np.linalg.norm(self.quats, axis=1) == 0):
            raise InvalidValue("gaussians.quats", "a zero quaternion is no rotation")
        if not 0 <= int(self.sh_degree) <= MAX_SH_DEGREE:
            raise InvalidValue("gaussians.sh_degree", f"must be 0 to {MAX_SH_DEGREE}, got {self.sh_degree}")
        object.__setattr__(self, "sh_degree", int(self.sh_degree))
        background = np.asarray(self.background, dtype=np.float32).reshape(-1)
        if background.shape != (3,) or not np.all(np.isfinite(background)):
            raise InvalidValue("gaussians.background", f"expected an RGB colour, got {self.background!r}")
        object.__setattr__(self, "background", background)

    def __len__(self) -> int:
        return len(self.means)

    def tensors(self, *, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32,
                requires_grad: bool = False) -> dict[str, torch.Tensor]:
        """The parameters as torch tensors by name (:data:`PARAMETERS`), fresh leaves."""
        return {name: torch.tensor(getattr(self, name), dtype=dtype, device=device,
                                   requires_grad=requires_grad) for name in PARAMETERS}

    def splats(self) -> GaussianSplats:
        """The Gaussians to draw: centres, ``Sigma = R S S^T R^T``, the view-independent (degree-0) colour
        clipped to [0, 1] and the activated opacity."""
        with torch.no_grad():
            t = self.tensors(dtype=torch.float64)
            cov = covariances(t["log_scales"], t["quats"]).numpy()
            rgb = np.clip(sh_to_rgb(t["sh"][:, 0]).numpy(), 0.0, 1.0)
            opacity = torch.sigmoid(t["opacity_logits"]).numpy()
        return GaussianSplats(self.means.astype(np.float64), cov, rgb, opacity)


def model_from_tensors(tensors: dict[str, torch.Tensor], *, sh_degree: int,
                       background: np.ndarray) -> SplatModel:
    """A :class:`SplatModel` of torch parameters by name (detached, copied to the CPU)."""
    arrays = [tensors[name].detach().cpu().numpy() for name in PARAMETERS]
    return SplatModel(arrays[0], arrays[1], arrays[2], arrays[3], arrays[4], sh_degree=sh_degree,
                      background=background)


def as_model(value: Any, field: str = "gaussians") -> SplatModel:
    """``value`` if it is a :class:`SplatModel`, else a clear :class:`InvalidValue`."""
    if not isinstance(value, SplatModel):
        raise InvalidValue(field, f"expected a SplatModel, got {type(value).__name__}")
    return value


__all__ = ["MAX_GAUSSIANS", "PARAMETERS", "SplatModel", "as_model", "check_count", "model_from_tensors"]
