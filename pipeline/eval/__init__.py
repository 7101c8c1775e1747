"""Evaluation: image metrics (PSNR, SSIM, optional LPIPS) and sparsification / AUSE."""

from pipeline.eval.metrics import (LpipsMetric, ViewMetrics, evaluate_views, psnr_value, ssim_skimage_value,
                                   ssim_value)
from pipeline.eval.sparsification import ause, oracle_curve, random_curve, sparsification_curve

__all__ = ["LpipsMetric", "ViewMetrics", "ause", "evaluate_views", "oracle_curve", "psnr_value",
           "random_curve", "sparsification_curve", "ssim_skimage_value", "ssim_value"]
