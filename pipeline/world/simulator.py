"""Capture simulators: the ground-truth image of any camera pose.

- ``GeneratedWorld``: the generated scene's analytic ray caster (``data.synthetic.render_view``),
  its render processed exactly as the Blender reader processes the stored views (8-bit RGBA at the
  scene's stored size, Lanczos to the training width, composited over the background), so a
  dataset pose gives back the dataset's image.
- ``TwinWorld``: any other scene through a reference splat (a "digital twin") trained on all of
  the scene's training views, rendered by our renderer. Views taken off the dataset's poses are
  then the twin's renders, not photographs: every report of such a run must say so, and evaluate
  on the dataset's real held-out views as well.
Both answer ``capture(cameras) -> [C, H, W, 3]`` float32 in [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import torch
from PIL import Image
from torch import Tensor

from pipeline.cameras import Cameras
from pipeline.data import synthetic
from pipeline.data.images import image_tensor
from pipeline.fit.config import FitConfig
from pipeline.fit.trainer import fit
from pipeline.splat import Gaussians, RenderSettings, render


class World(Protocol):
    name: str

    def capture(self, cameras: Cameras) -> Tensor: ...


def opencv_to_opengl_c2w(viewmat: Tensor) -> Tensor:
    """World->camera (OpenCV) [4, 4] -> camera->world (OpenGL: y up, looking down -z) [4, 4]."""
    c2w = torch.linalg.inv(viewmat.double())
    c2w[:3, 1:3] *= -1
    return c2w


@dataclass
class GeneratedWorld:
    """The generated scene as a simulator. ``stored_size``: the side of its stored square images
    (``scene.json``'s ``size``); ``background`` [3]: the reader's."""

    stored_size: int
    background: Tensor
    name: str = "generated"
    _textures: list = field(default_factory=list, repr=False)

    def capture(self, cameras: Cameras) -> Tensor:
        self._check_intrinsics(cameras)
        if not self._textures:
            self._textures.extend(synthetic._textures())
        out = []
        for i in range(len(cameras)):
            rgba = synthetic.render_view(opencv_to_opengl_c2w(cameras.viewmats[i]), self.stored_size,
                                         self._textures)
            out.append(image_tensor(Image.fromarray(rgba, "RGBA"), (cameras.width, cameras.height),
                                    self.background))
        return torch.stack(out)

    @staticmethod
    def _check_intrinsics(cameras: Cameras) -> None:
        """The ray caster has the scene's one field of view, square images, centred principal point."""
        if cameras.width != cameras.height:
            raise ValueError(f"the generated world renders square images, got {cameras.width} x {cameras.height}")
        focal = 0.5 * cameras.width / math.tan(0.5 * synthetic.CAMERA_ANGLE_X)
        expected = torch.tensor([[focal, 0, cameras.width / 2], [0, focal, cameras.height / 2], [0, 0, 1]],
                                dtype=torch.float64)
        if not torch.allclose(cameras.Ks.double(), expected.expand_as(cameras.Ks), rtol=1e-4, atol=1e-3):
            raise ValueError("the generated world renders the scene's own intrinsics (field of view "
                             f"{synthetic.CAMERA_ANGLE_X:.4f} rad, centred): the cameras' Ks differ")


@dataclass
class TwinWorld:
    """A reference splat as a simulator (its renders clamped to [0, 1])."""

    gaussians: Gaussians
    background: Tensor
    settings: RenderSettings = field(default_factory=RenderSettings)
    name: str = "twin"

    @torch.no_grad()
    def capture(self, cameras: Cameras) -> Tensor:
        return render(self.gaussians, cameras, self.background.to(self.gaussians.means),
                      settings=self.settings).rgb.clamp(0, 1)


def train_twin(init: Gaussians, cameras: Cameras, images: Tensor, config: FitConfig,
               background: Tensor, progress: bool = False) -> Gaussians:
    """The digital twin: ``init`` fitted to every training view (``images`` [C, H, W, 3])."""
    return fit(init, cameras, images, config, background, progress=progress)
