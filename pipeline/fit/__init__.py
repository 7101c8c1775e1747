"""Training a splat on a view set with the 3DGS recipe."""

from pipeline.fit.config import FitConfig, paper_preset
from pipeline.fit.trainer import Trainer, evaluate_psnr, fit

__all__ = ["FitConfig", "Trainer", "evaluate_psnr", "fit", "paper_preset"]
