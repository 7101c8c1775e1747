"""The model's doors a strategy goes through: render, per-view Fisher, training Hessian.

``SelectionContext.backend`` hands a strategy one ``ModelDoors`` object, bound to the round's
model, background and render settings, with the backend name resolved once for the model's device
(``compiled`` on CPU when numba loads, else ``tiles``; CUDA tensors take the torch path). A
strategy written against these three doors runs on every backend and device without asking which.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.cameras import Cameras
from pipeline.fisher.exact import FisherSpec, view_fisher
from pipeline.fisher.features import param_layout
from pipeline.splat import Gaussians, RenderSettings
from pipeline.splat.compiled import resolve_backend
from pipeline.splat.render import RenderOutput, render


@dataclass(frozen=True)
class ModelDoors:
    """``render(cameras [C]) -> RenderOutput`` (rgb [C, H, W, 3] ...), ``view_fisher(cameras [C])
    -> [C, N, P]`` float64 (the exact diag(J^T J) of each view, paper Eq. 3), ``training_hessian(
    cameras [C]) -> [N, P]`` float64 (their sum: H_train of the taken views when given them)."""

    gaussians: Gaussians
    background: Tensor               # [3]
    settings: RenderSettings         # with ``backend`` resolved to one name

    @classmethod
    def of(cls, gaussians: Gaussians, background: Tensor, settings: RenderSettings) -> "ModelDoors":
        name = resolve_backend(settings.backend, gaussians.means.device)
        return cls(gaussians, background, RenderSettings(settings.near, settings.tile_size, settings.chunk,
                                                         name, settings.dense_pixel_block))

    @property
    def name(self) -> str:
        """The resolved backend: compiled | tiles | dense | loop."""
        return self.settings.backend

    def render(self, cameras: Cameras) -> RenderOutput:
        with torch.no_grad():
            return render(self.gaussians, cameras, self.background, settings=self.settings)

    def view_fisher(self, cameras: Cameras, spec: FisherSpec = FisherSpec()) -> Tensor:
        return view_fisher(self.gaussians, cameras, self.background, spec, self.settings)

    def training_hessian(self, cameras: Cameras, spec: FisherSpec = FisherSpec()) -> Tensor:
        if len(cameras) == 0:
            return torch.zeros(len(self.gaussians), spec_width(self, spec), dtype=torch.float64)
        return self.view_fisher(cameras, spec).sum(0)


def spec_width(doors: ModelDoors, spec: FisherSpec) -> int:
    """P, the Fisher's parameters per Gaussian under ``spec`` (its stored SH degree)."""
    if spec.sh_degree is not None:
        raise ValueError("training_hessian of no camera with spec.sh_degree set: give at least one camera")
    return sum(width for _, width in param_layout(doors.gaussians, spec.groups))
