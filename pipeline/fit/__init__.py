"""Training a splat on a view set with the 3DGS recipe."""

from pipeline.fit.config import FitConfig, cpu_preset, paper_preset, preset, tiny_preset
from pipeline.fit.trainer import Trainer, evaluate_psnr, fit

__all__ = ["FitConfig", "Trainer", "cpu_preset", "evaluate_psnr", "fit", "paper_preset", "preset",
           "tiny_preset"]
