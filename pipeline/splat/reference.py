"""Slow, obviously correct compositors: the test oracles for the tiled rasterizer.

Both evaluate every pixel against every Gaussian in one global front-to-back order (stable sort
by depth). A Gaussian may touch a pixel only inside the tiles its 3-sigma square overlaps: that
is the support rule of 3DGS, and it is what makes tiles an exact speed-up rather than an
approximation. The alpha formula and the termination rule are written out here independently of
``rasterize.py``.

- ``rasterize_loop``: the 3DGS CUDA loop transcribed literally, one Gaussian at a time.
- ``rasterize_dense``: the same rule with all pixels x all Gaussians as [H*W, N] tensors.
"""

from __future__ import annotations

import torch
import torch.utils.checkpoint
from torch import Tensor

from pipeline.cameras import pixel_centers


def _support(means2d: Tensor, radii: Tensor, u: Tensor, v: Tensor, tile_size: int) -> Tensor:
    """[H*W, N] True where the pixel's tile lies in the Gaussian's tile rectangle."""
    pu = torch.floor(u / tile_size)[:, None]
    pv = torch.floor(v / tile_size)[:, None]
    mu, mv = means2d.detach()[:, 0], means2d.detach()[:, 1]
    r = radii.to(mu.dtype)
    inside = (pu >= torch.floor((mu - r) / tile_size)) & (pu <= torch.floor((mu + r) / tile_size)) & \
             (pv >= torch.floor((mv - r) / tile_size)) & (pv <= torch.floor((mv + r) / tile_size))
    return inside & (radii > 0)[None, :]


def _power(means2d: Tensor, conics: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """-1/2 d^T Q d for every pixel and Gaussian, [H*W, N], with Q = [[a, b], [b, c]]."""
    d = torch.stack([u[:, None] - means2d[None, :, 0], v[:, None] - means2d[None, :, 1]], -1)
    q = torch.stack([conics[:, 0], conics[:, 1], conics[:, 1], conics[:, 2]], -1).reshape(-1, 2, 2)
    return -0.5 * torch.einsum("pni,nij,pnj->pn", d, q, d)


def rasterize_dense(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor,
                    radii: Tensor, depths: Tensor, width: int, height: int, tile_size: int = 8,
                    pixel_block: int | None = None) -> tuple[Tensor, Tensor]:
    """Same contract as ``rasterize.rasterize``: ([H, W, D], [H, W]).

    ``pixel_block``: if set, pixels are processed in blocks of that many under activation
    checkpointing (memory of one block, at the price of a second forward in backward).
    """
    order = torch.argsort(depths.detach(), stable=True)
    means2d, conics, opacities, features, radii = (x[order] for x in
                                                   (means2d, conics, opacities, features, radii))
    u, v = pixel_centers(width, height, means2d.dtype, means2d.device)

    def block(u_b: Tensor, v_b: Tensor, means2d, conics, opacities, features):
        power = _power(means2d, conics, u_b, v_b)
        alpha = torch.minimum(opacities[None, :] * torch.exp(power), power.new_tensor(0.99))
        used = _support(means2d, radii, u_b, v_b, tile_size) & (power <= 0) & (alpha >= 1 / 255)
        alpha = torch.where(used, alpha, torch.zeros_like(alpha))
        # a pixel stops before the first Gaussian that would take T below 1e-4
        with torch.no_grad():
            ended = torch.cumprod(1 - alpha, dim=1) < 1e-4
        alpha = torch.where(ended, torch.zeros_like(alpha), alpha)
        transmittance = torch.cumprod(1 - alpha, dim=1)
        before = torch.cat([torch.ones_like(transmittance[:, :1]), transmittance[:, :-1]], dim=1)
        return (alpha * before) @ features, 1 - transmittance[:, -1]

    params = (means2d, conics, opacities, features)
    if pixel_block is None:
        image, acc = block(u, v, *params)
    else:
        parts = [torch.utils.checkpoint.checkpoint(block, u[i:i + pixel_block], v[i:i + pixel_block],
                                                   *params, use_reentrant=False)
                 for i in range(0, u.shape[0], pixel_block)]
        image, acc = torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
    return image.reshape(height, width, -1), acc.reshape(height, width)


def rasterize_loop(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor,
                   radii: Tensor, depths: Tensor, width: int, height: int,
                   tile_size: int = 8) -> tuple[Tensor, Tensor]:
    """The 3DGS per-pixel loop, vectorised over pixels only. Tiny scenes only."""
    u, v = pixel_centers(width, height, means2d.dtype, means2d.device)
    support = _support(means2d, radii, u, v, tile_size)
    power = _power(means2d, conics, u, v)
    trans = torch.ones_like(u)
    done = torch.zeros_like(u, dtype=torch.bool)
    image = features.new_zeros(u.shape[0], features.shape[1])
    for g in torch.argsort(depths.detach(), stable=True).tolist():
        alpha = torch.clamp(opacities[g] * torch.exp(power[:, g]), max=0.99)
        skip = ~support[:, g] | (power[:, g] > 0) | (alpha < 1 / 255) | done
        test_t = trans * (1 - alpha)
        newly_done = ~skip & (test_t < 1e-4)
        use = ~skip & ~newly_done
        image = image + torch.where(use, alpha * trans, torch.zeros_like(alpha))[:, None] * features[g]
        trans = torch.where(use, test_t, trans)
        done = done | newly_done
    return image.reshape(height, width, -1), (1 - trans).reshape(height, width)
