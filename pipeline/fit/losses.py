"""Training losses: L1, differentiable SSIM (3DGS's 11x11 Gaussian window), and PSNR."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor


def _window(size: int, sigma: float, channels: int, like: Tensor) -> Tensor:
    """The [channels, 1, size, size] Gaussian window in ``like``'s dtype and device (cached: a
    training step asks for the same one every time)."""
    return _window_cached(size, float(sigma), channels, like.dtype, like.device)


@functools.lru_cache(maxsize=16)
def _window_cached(size: int, sigma: float, channels: int, dtype: torch.dtype,
                   device: torch.device) -> Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(channels, 1, size, size).contiguous()


def ssim(img: Tensor, ref: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM of [..., H, W, C] images in [0, 1] (zero-padded 'same' windows, as 3DGS trains)."""
    return ssim_map(img, ref, window, sigma).mean()


def ssim_map(img: Tensor, ref: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Per-pixel SSIM [B, C, H, W] of [..., H, W, C] images (Gaussian window, zero padding)."""
    x = img.reshape(-1, *img.shape[-3:]).permute(0, 3, 1, 2)
    y = ref.reshape(-1, *ref.shape[-3:]).permute(0, 3, 1, 2)
    c = x.shape[1]
    # the five local means in one grouped convolution (one op instead of five)
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # [B, 5C, H, W]
    means = F.conv2d(stack, _window(window, sigma, 5 * c, x), padding=window // 2, groups=5 * c)
    mu_x, mu_y, exx, eyy, exy = means.split(c, dim=1)
    sxx, syy, sxy = exx - mu_x ** 2, eyy - mu_y ** 2, exy - mu_x * mu_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2))


def photometric_loss(img: Tensor, ref: Tensor, ssim_weight: float = 0.2) -> Tensor:
    """(1 - w) L1 + w (1 - SSIM), the 3DGS training loss."""
    return (1 - ssim_weight) * (img - ref).abs().mean() + ssim_weight * (1 - ssim(img, ref))


def masked_pair(img: Tensor, ref: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """The training loss's inputs under a mask [H, W] (1 = kept, 0 = ignored, e.g. a visitor walking
    through a capture): both images multiplied by it, so a masked-out pixel adds nothing to the
    loss and gives no gradient (nerfstudio's splatfacto does the same). None: unchanged."""
    if mask is None:
        return img, ref
    keep = mask.to(img)[..., None]
    return img * keep, ref * keep


def psnr(img: Tensor, ref: Tensor) -> Tensor:
    """PSNR in dB of images in [0, 1] (mean squared error over all pixels and channels)."""
    mse = (img.clamp(0, 1) - ref).square().mean()
    return -10 * torch.log10(mse.clamp_min(1e-20))


class _CompiledPhotometricLoss(torch.autograd.Function):
    """``photometric_loss`` of one [H, W, 3] CPU image as one autograd node: value and gradient
    from one compiled pass (``loss_kernels``), in float64, cast to the image's dtype."""

    @staticmethod
    def forward(ctx, img, ref, ssim_weight):
        from pipeline.fit import loss_kernels
        from pipeline.splat import compiled
        value, grad = loss_kernels.photometric_value_and_grad(
            img.detach().contiguous().numpy(), ref.detach().contiguous().numpy(),
            float(ssim_weight), window_taps(11, 1.5), compiled.use_threads())
        ctx.grad = torch.from_numpy(grad).to(img.dtype)
        return img.new_tensor(value)

    @staticmethod
    def backward(ctx, grad_out):
        return grad_out * ctx.grad, None, None


@functools.lru_cache(maxsize=4)
def window_taps(size: int, sigma: float):
    """The 1-D SSIM window [size] float64 the compiled loss takes (cached; read only)."""
    from pipeline.fit import loss_kernels
    return loss_kernels.gaussian_taps(size, sigma)


def photometric_loss_compiled(img: Tensor, ref: Tensor, ssim_weight: float = 0.2) -> Tensor:
    """``photometric_loss`` of an [H, W, 3] image on the CPU by the compiled kernel (value and
    gradient in one pass; ~4x faster than the ~40 torch ops at 64 px). The same loss to float
    rounding: float64 inside, so in float32 it differs from the torch ops' float32 rounding (tests
    compare both, and the float64 value to 1e-12). The reference needs no gradient."""
    if img.dim() != 3 or img.shape[-1] != 3 or img.shape != ref.shape:
        raise ValueError(f"photometric_loss_compiled: img and ref must be one [H, W, 3] image, "
                         f"got {tuple(img.shape)} and {tuple(ref.shape)}")
    if img.device.type != "cpu":
        raise ValueError(f"photometric_loss_compiled runs on CPU tensors, got {img.device}")
    return _CompiledPhotometricLoss.apply(img, ref, ssim_weight)
