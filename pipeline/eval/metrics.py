"""Image metrics as the 3DGS evaluation computes them, per view, then averaged over views.

- PSNR: 10 log10(1 / MSE) of the render clamped to [0, 1] against the ground truth, per view.
- SSIM: as 3DGS's ``utils/loss_utils.ssim`` computes it (and the papers that evaluate with it):
  an 11x11 Gaussian window with sigma 1.5, K1 = 0.01, K2 = 0.03, local means and (population)
  variances by convolution with zero padding, the SSIM map averaged over every pixel and channel
  (``ssim_value``; the formula is the training loss's, ``pipeline.fit.losses.ssim_map``, here in
  float64 with the window applied as two 1-D passes: the Gaussian window is separable, and
  float64 ``conv2d`` of the 2-D window took ~40 ms per 64 px view on 2 CPU threads, ~0.7 ms this
  way; the two agree to 1e-15, tested). One difference remains: 3DGS scores renders it saved as 8-bit PNGs; we score the
  float render clamped to [0, 1] (as for PSNR).
- SSIM (scikit-image), a second column: ``structural_similarity`` with the same window and
  constants (``SSIM_SETTINGS``), which averages over the valid interior only (it crops
  (win - 1) / 2 = 5 px at each border). At 48-64 px the two differ by a few hundredths.
- LPIPS: the ``lpips`` package with the VGG backbone (as 3DGS and FisherRF report; gsplat's
  default is AlexNet). Its backbone weights come from torchvision's pretrained VGG16; when the
  package, torchvision or the weights are missing, LPIPS is *unavailable*: recorded as ``None``
  with the reason, never as a number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.ndimage import correlate1d
from skimage.metrics import structural_similarity
from torch import Tensor

from pipeline.cameras import Cameras
from pipeline.splat import Gaussians, RenderSettings, compiled, render

SSIM_CONVENTION = ("ssim: 3DGS's (zero-padded windows, mean over all pixels); "
                   "ssim_skimage: scikit-image's structural_similarity (valid interior)")
SSIM_SETTINGS = {"gaussian_weights": True, "sigma": 1.5, "win_size": 11, "K1": 0.01, "K2": 0.03,
                 "use_sample_covariance": False, "data_range": 1.0, "channel_axis": -1}


def _check_pair(pred: Tensor, gt: Tensor) -> None:
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[-1] != 3:
        raise ValueError(f"images must both be [H, W, 3], got {tuple(pred.shape)} and {tuple(gt.shape)}")


def psnr_value(pred: Tensor, gt: Tensor, mask: Tensor | None = None) -> float:
    """PSNR in dB of one view: pred, gt [H, W, 3] in [0, 1] (pred is clamped); with ``mask``
    [H, W] (1 = counted), the mean squared error over the masked-in pixels only."""
    _check_pair(pred, gt)
    err = (pred.clamp(0, 1).double() - gt.to(pred.device).double()).square()
    if mask is None:
        mse = float(err.mean())
    else:
        weight = _mask_weight(mask, pred)
        mse = float((err * weight[..., None]).sum() / (3 * weight.sum()))
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def _mask_weight(mask: Tensor, pred: Tensor) -> Tensor:
    if mask.shape != pred.shape[:2]:
        raise ValueError(f"mask must be [H, W] = {tuple(pred.shape[:2])}, got {tuple(mask.shape)}")
    weight = (mask.to(pred.device).double() >= 0.5).double()
    if float(weight.sum()) == 0:
        raise ValueError("mask: no pixel of this view is masked in (nothing to score)")
    return weight


def _gaussian_window_1d(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2
    g = np.exp(-(x * x) / (2 * sigma * sigma))
    return g / g.sum()


WINDOW_1D = _gaussian_window_1d()  # 3DGS's window: 11 taps, sigma 1.5; its 2-D window is the outer product


def ssim_value(pred: Tensor, gt: Tensor, mask: Tensor | None = None) -> float:
    """3DGS's SSIM of one view (zero-padded windows, the mean over all pixels and channels), in
    float64: pred, gt [H, W, 3] in [0, 1] (pred is clamped); with ``mask`` [H, W], the SSIM map's
    mean over the masked-in pixels only."""
    ssim = ssim_map(pred, gt)
    if mask is None:
        return float(ssim.mean())
    weight = _mask_weight(mask, pred).cpu().numpy()
    return float((ssim * weight[..., None]).sum() / (3 * weight.sum()))


def ssim_map(pred: Tensor, gt: Tensor) -> np.ndarray:
    """3DGS's per-pixel SSIM [H, W, 3] float64 (its mean is ``ssim_value``)."""
    _check_pair(pred, gt)
    x = pred.detach().clamp(0, 1).double().cpu().numpy()
    y = gt.detach().double().cpu().numpy()
    stats = np.stack([x, y, x * x, y * y, x * y])  # [5, H, W, 3]
    # the 2-D window as a pass along rows then columns; "constant" mode pads with zeros as conv2d
    local = correlate1d(correlate1d(stats, WINDOW_1D, axis=1, mode="constant"), WINDOW_1D, axis=2,
                        mode="constant")
    mu_x, mu_y, exx, eyy, exy = local
    sxx, syy, sxy = exx - mu_x ** 2, eyy - mu_y ** 2, exy - mu_x * mu_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2))


def ssim_skimage_value(pred: Tensor, gt: Tensor) -> float:
    """scikit-image's SSIM of one view (settings in ``SSIM_SETTINGS``; the valid interior's
    mean): pred, gt [H, W, 3] in [0, 1]."""
    _check_pair(pred, gt)
    a = pred.detach().clamp(0, 1).double().cpu().numpy()
    b = gt.detach().double().cpu().numpy()
    return float(structural_similarity(b, a, **SSIM_SETTINGS))


class LpipsMetric:
    """LPIPS (VGG) when it can run here; ``available`` and ``reason`` say whether and why not."""

    def __init__(self, net: str = "vgg"):
        self.net, self.model, self.reason = net, None, ""
        try:
            import lpips  # optional extra: pip install 'gopre[lpips]'
            self.model = lpips.LPIPS(net=net, verbose=False).eval()
        except Exception as err:  # ImportError, or the pretrained weights cannot be fetched
            self.reason = f"LPIPS ({net}) unavailable: {type(err).__name__}: {str(err).splitlines()[0][:160]}"

    @property
    def available(self) -> bool:
        return self.model is not None

    @torch.no_grad()
    def __call__(self, pred: Tensor, gt: Tensor) -> float | None:
        if self.model is None:
            return None
        _check_pair(pred, gt)
        to_nchw = lambda x: x.clamp(0, 1).permute(2, 0, 1)[None].float().cpu()  # noqa: E731
        return float(self.model(to_nchw(pred), to_nchw(gt), normalize=True))


@dataclass
class ViewMetrics:
    """Per-view metrics of a set of test views; ``lpips`` is None when unavailable."""

    psnr: list[float]
    ssim: list[float]                 # 3DGS's convention
    ssim_skimage: list[float]
    lpips: list[float] | None = None
    lpips_status: str = "not computed"
    extra: dict = field(default_factory=dict)

    def mean(self) -> dict:
        out = {"psnr": float(np.mean(self.psnr)), "ssim": float(np.mean(self.ssim)),
               "ssim_skimage": float(np.mean(self.ssim_skimage)),
               "lpips": float(np.mean(self.lpips)) if self.lpips is not None else None}
        return out


@torch.no_grad()
def evaluate_views(gaussians: Gaussians, cameras: Cameras, images: Tensor, background: Tensor,
                   lpips: LpipsMetric | None = None, settings: RenderSettings = RenderSettings(),
                   ssim: bool = True, masks: Tensor | None = None) -> ViewMetrics:
    """Render each camera [C] and compare with ``images`` [C, H, W, 3]. On the compiled backend
    the views are rendered and scored side by side, one per thread (the same numbers).
    ``masks`` [C, H, W] (1 = the object): PSNR and SSIM over the masked-in pixels only;
    scikit-image's SSIM and LPIPS see the render with its masked-out pixels set to the truth's."""
    if images.shape[0] != len(cameras):
        raise ValueError(f"{images.shape[0]} images for {len(cameras)} cameras")
    if masks is not None and masks.shape != images.shape[:3]:
        raise ValueError(f"masks must be [C, H, W] = {tuple(images.shape[:3])}, got {tuple(masks.shape)}")

    def one_view(i: int) -> tuple[Tensor, float, float, float]:
        with torch.no_grad():  # grad mode is per thread
            pred = render(gaussians, cameras[i], background, settings=settings).rgb[0].clamp(0, 1)
            mask = None if masks is None else masks[i]
            whole = pred if mask is None else torch.where(mask[..., None] >= 0.5, pred, images[i].to(pred))
            return (whole, psnr_value(pred, images[i], mask),
                    ssim_value(pred, images[i], mask) if ssim else float("nan"),
                    ssim_skimage_value(whole, images[i]) if ssim else float("nan"))

    compiled_views = compiled.resolve_backend(settings.backend, gaussians.means.device) == "compiled"
    threads = compiled.use_threads() if compiled_views else 1
    psnrs, ssims, skimage, lp = [], [], [], []
    views = compiled.map_in_threads(one_view, len(cameras), threads)
    for i, (pred, psnr_i, ssim_i, skimage_i) in enumerate(views):
        psnrs.append(psnr_i)
        ssims.append(ssim_i)
        skimage.append(skimage_i)
        if lpips is not None and lpips.available:  # the network runs here, one view at a time
            lp.append(lpips(pred, images[i]))
    if lpips is None:
        return ViewMetrics(psnrs, ssims, skimage)
    status = "vgg" if lpips.available else lpips.reason
    return ViewMetrics(psnrs, ssims, skimage, lp if lpips.available else None, status)
