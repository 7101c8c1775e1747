"""3DGS adaptive density control: gradient statistics, clone/split, prune, opacity reset.

Parameters live in a dict of leaf tensors, each alone in one Adam param group; every change of
the Gaussian set also remaps the Adam moments (kept rows keep theirs, new rows start at zero).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.fit.adam import FusedAdam
from pipeline.fit.config import DensifyConfig
from pipeline.splat.gaussians import quat_to_rotmat


@dataclass
class DensifyStats:
    """Running per-Gaussian statistics between densification steps ([N] each)."""

    grad_sum: Tensor
    count: Tensor
    max_radii: Tensor

    @staticmethod
    def zeros(n: int, like: Tensor) -> "DensifyStats":
        return DensifyStats(like.new_zeros(n), like.new_zeros(n), like.new_zeros(n))

    def update(self, means2d_grad: Tensor, radii: Tensor, width: int, height: int) -> None:
        """Accumulate the NDC-space gradient norm of means2d [N, 2] for Gaussians seen (radii > 0)."""
        seen = radii > 0
        ndc = means2d_grad * means2d_grad.new_tensor([width / 2, height / 2])
        self.grad_sum += torch.where(seen, ndc.norm(dim=-1), torch.zeros_like(self.grad_sum))
        self.count += seen.to(self.count.dtype)
        self.max_radii = torch.maximum(self.max_radii, radii.to(self.max_radii.dtype))

    def mean_grads(self) -> Tensor:
        return self.grad_sum / self.count.clamp_min(1)


def remap(params: dict[str, Tensor], optimizer: FusedAdam, keep: Tensor,
          new: dict[str, Tensor] | None = None) -> dict[str, Tensor]:
    """Keep rows ``keep`` ([N] bool) of every parameter, append ``new`` rows, remap Adam state."""
    out = {}
    for group in optimizer.param_groups:
        name = group["name"]
        old = params[name]
        extra = new[name] if new is not None else old.new_zeros(0, *old.shape[1:])
        param = torch.cat([old.detach()[keep], extra]).requires_grad_(True)
        state = optimizer.state.pop(old, None)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                state[key] = torch.cat([state[key][keep], torch.zeros_like(extra)])
            optimizer.state[param] = state
        group["params"] = [param]
        out[name] = param
    return out


def _select_under_cap(grads: Tensor, candidates: Tensor, cost: Tensor, room: int | None) -> Tensor:
    """Candidates to densify, highest gradient first, whose added count fits in ``room``."""
    if room is None:
        return candidates
    chosen = torch.zeros_like(candidates)
    idx = torch.nonzero(candidates)[:, 0]
    idx = idx[torch.argsort(grads[idx], descending=True)]
    fits = torch.cumsum(cost[idx], 0) <= max(room, 0)
    chosen[idx[fits]] = True
    return chosen


def densify_and_prune(params: dict[str, Tensor], optimizer: FusedAdam,
                      stats: DensifyStats, cfg: DensifyConfig, extent: float, prune_large: bool,
                      generator: torch.Generator | None = None) -> dict[str, Tensor]:
    """One 3DGS densification step; returns the new parameter dict (optimizer updated)."""
    n = params["means"].shape[0]
    grads = stats.mean_grads()
    scales = torch.exp(params["log_scales"].detach())
    max_scale = scales.max(dim=1).values
    big = max_scale > cfg.percent_dense * extent
    candidates = grads >= cfg.grad_threshold
    cost = torch.where(big, cfg.split_count - 1, 1)
    room = None if cfg.max_gaussians is None else cfg.max_gaussians - n
    chosen = _select_under_cap(grads, candidates, cost, room)
    clone, split = chosen & ~big, chosen & big

    new = {k: v.detach()[clone] for k, v in params.items()}
    if bool(split.any()):
        k = cfg.split_count
        src = {name: v.detach()[split].repeat_interleave(k, dim=0) for name, v in params.items()}
        std = scales[split].repeat_interleave(k, dim=0)
        noise = torch.randn(std.shape, generator=generator, dtype=std.dtype).to(std.device) * std
        rot = quat_to_rotmat(src["quats"])
        src["means"] = src["means"] + (rot @ noise[..., None])[..., 0]
        src["log_scales"] = src["log_scales"] - torch.log(src["log_scales"].new_tensor(cfg.split_scale_div))
        new = {name: torch.cat([new[name], src[name]]) for name in params}
    params = remap(params, optimizer, torch.ones(n, dtype=torch.bool, device=split.device), new)

    total = params["means"].shape[0]
    drop = torch.zeros(total, dtype=torch.bool, device=split.device)
    drop[:n] = split  # split originals are replaced by their samples
    drop |= torch.sigmoid(params["logit_opacities"].detach()) < cfg.min_opacity
    if prune_large:
        radii = torch.cat([stats.max_radii, stats.max_radii.new_zeros(total - n)])
        drop |= radii > cfg.max_screen_radius
        if cfg.max_world_scale is not None:
            world = torch.exp(params["log_scales"].detach()).max(dim=1).values
            drop |= world > cfg.max_world_scale * extent
    if bool(drop.all()):  # never prune the scene away entirely
        drop[torch.argmax(params["logit_opacities"].detach())] = False
    return remap(params, optimizer, ~drop)


def reset_opacity(params: dict[str, Tensor], optimizer: FusedAdam,
                  value: float) -> dict[str, Tensor]:
    """Clamp every opacity to at most ``value`` and zero its Adam moments (3DGS opacity reset)."""
    old = params["logit_opacities"]
    ceiling = torch.logit(old.new_tensor(value))
    for group in optimizer.param_groups:
        if group["name"] == "logit_opacities":
            fresh = torch.minimum(old.detach(), ceiling).requires_grad_(True)
            state = optimizer.state.pop(old, None)
            if state:
                state["exp_avg"] = torch.zeros_like(fresh)
                state["exp_avg_sq"] = torch.zeros_like(fresh)
                optimizer.state[fresh] = state
            group["params"] = [fresh]
    return {**params, "logit_opacities": fresh}
