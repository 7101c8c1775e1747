"""Pure-PyTorch differentiable 3D Gaussian splatting (no Hydra, Ray or MLflow here)."""

from pipeline.splat.gaussians import Gaussians
from pipeline.splat.render import RenderOutput, RenderSettings, render

__all__ = ["Gaussians", "RenderOutput", "RenderSettings", "render"]
