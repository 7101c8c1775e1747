"""The final model's pixel-level uncertainty against its error on test views, one record per job.

The map is the model's Laplace predictive variance (``pipeline.fisher``: S = 1 / (H_train + lambda)
of the views the episode took, pushed through each pixel's Jacobian), per colour channel: a variance,
so the calibration metrics mean something. It is the same posterior for every strategy (the model
trained on the strategy's picks), so these numbers say how well the uncertainty of the model each
strategy built is calibrated, not how a strategy's own score ranks pixels. On the views given
(the job's ``renders`` first test views):

- AUSE of MAE (absolute error summed over channels), RMSE (squared error summed, the curve's root)
  and DSSIM (1 - SSIM map, channel mean), each in both normalisations (``pixel_uncertainty``:
  ``_max`` FisherRF / WarpRF / AaltoML, ``_start`` 3DGS-Uncertainty), ranked by the variance summed
  over channels;
- NLL of the ground truth under N(render, max(sigma, 0.03)^2) per channel, AUCE, and Pearson's and
  Spearman's correlation of the summed variance with the MAE.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from torch import Tensor

from pipeline.eval import pixel_uncertainty as pu
from pipeline.eval.metrics import ssim_map

CURVE_FRACTIONS = tuple(round(k / 20, 2) for k in range(20))  # removed: 0, 0.05, ..., 0.95
MAP = "Laplace predictive variance of the final model (per channel; ranked by the sum)"


@dataclass(frozen=True)
class PixelUncertainty:
    views: int
    ause_mae_max: float
    ause_mae_start: float
    ause_rmse_max: float
    ause_rmse_start: float
    ause_dssim_max: float
    ause_dssim_start: float
    nll: float
    auce: float
    pearson: float
    spearman: float

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class _Pixels:
    """Every shown pixel once, as the metrics read them: truth, render (clamped) and variance
    [T, H, W, 3] float64, the ranking score (the variance summed over channels) [T*H*W] and, per
    error, its per-pixel values and whether its curve is the root of the kept mean (RMSE)."""

    truth: np.ndarray
    render: np.ndarray
    variance: np.ndarray
    score: np.ndarray
    errors: dict[str, tuple[np.ndarray, bool]]


def _pixels(truth: Tensor, render: Tensor, variance: Tensor) -> _Pixels:
    if not (truth.shape == render.shape == variance.shape) or truth.ndim != 4 or truth.shape[-1] != 3:
        raise ValueError(f"truth, render and variance must be [T, H, W, 3] alike, got {tuple(truth.shape)}, "
                         f"{tuple(render.shape)}, {tuple(variance.shape)}")
    t = truth.detach().double().cpu().numpy()
    r = render.detach().clamp(0, 1).double().cpu().numpy()
    v = np.clip(variance.detach().double().cpu().numpy(), 0.0, None)
    dssim = np.concatenate([(1.0 - ssim_map(render[k], truth[k]).mean(-1)).ravel() for k in range(len(truth))])
    return _Pixels(t, r, v, v.sum(-1).ravel(), {"mae": (np.abs(r - t).sum(-1).ravel(), False),
                                                "rmse": (((r - t) ** 2).sum(-1).ravel(), True),
                                                "dssim": (dssim, False)})


def _curves(px: _Pixels, fractions: tuple[float, ...]) -> dict:
    out: dict = {"fractions": list(fractions)}
    for name, (error, root) in px.errors.items():
        s = pu.sparsification(error, px.score, np.asarray(fractions), root)
        out[name] = {"by_uncertainty": s.by_uncertainty.tolist(), "oracle": s.oracle.tolist(),
                     "random": s.random.tolist()}
    return out


def _record(px: _Pixels) -> PixelUncertainty:
    values = {}
    for name, (error, root) in px.errors.items():
        values[f"ause_{name}_max"] = pu.ause_max(error, px.score, root)[0]
        values[f"ause_{name}_start"] = pu.ause_start(error, px.score, root)[0]
    sigma = np.sqrt(px.variance).reshape(-1, 3)
    values["nll"] = pu.gaussian_nll(px.render.reshape(-1, 3), px.truth.reshape(-1, 3), sigma)
    values["auce"] = pu.auce(px.render.reshape(-1, 3), px.truth.reshape(-1, 3), sigma)[0]
    values["pearson"], values["spearman"] = pu.correlations(px.score, px.errors["mae"][0])
    return PixelUncertainty(len(px.truth), **{k: float(x) for k, x in values.items()})


def sparsification_curves(truth: Tensor, render: Tensor, variance: Tensor,
                          fractions: tuple[float, ...] = CURVE_FRACTIONS) -> dict:
    """truth, render, variance [T, H, W, 3] -> the curves of the kept pixels' error at each removal
    fraction, unnormalised, per error (mae, rmse, dssim): ranked by the summed variance, by the true
    error (oracle) and at random (the error of all pixels); what Fig. 7's pixel-level panels draw."""
    return _curves(_pixels(truth, render, variance), fractions)


def pixel_uncertainty(truth: Tensor, render: Tensor, variance: Tensor) -> PixelUncertainty:
    """truth, render [T, H, W, 3] in [0, 1], variance [T, H, W, 3] (per channel) -> the record."""
    return _record(_pixels(truth, render, variance))


def final_model_uncertainty(truth: Tensor, render: Tensor, variance: Tensor) -> tuple[PixelUncertainty, dict]:
    """The record and the curves (``CURVE_FRACTIONS``) of one set of views, their pixels read once."""
    px = _pixels(truth, render, variance)
    return _record(px), _curves(px, CURVE_FRACTIONS)
