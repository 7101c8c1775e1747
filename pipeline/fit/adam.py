"""Adam for the trainer: torch's fused Adam update (``torch._fused_adam_``, the kernel that
``torch.optim.Adam(fused=True)`` runs), called directly, one parameter per group.

Why not ``torch.optim.Adam`` itself: its constructor, ``step`` and ``state_dict`` are wrapped to
keep TorchDynamo out, and the wrapper imports ``torch._dynamo`` on first use: about 2 s (3.5 s beside
a sweep) and 70 MB in every process that trains (each sweep worker, each test that starts one), for a compiler the CPU
path never uses. The update is the same kernel with the same arguments in the same order, so the
parameters and moments are bit-identical to ``torch.optim.Adam(..., fused=True)``'s (tested against
it step by step, through the density control's remaps); ``state_dict`` has torch's layout, so a
checkpoint written by either loads into the other.

The interface is the part of ``torch.optim.Optimizer`` the trainer and the density control use:
``param_groups`` (dicts with ``params`` [one tensor], ``lr``, ``name``), ``state`` (keyed by the
parameter tensor: ``step``, ``exp_avg``, ``exp_avg_sq``), ``step()``, ``state_dict()`` and
``load_state_dict()``.
"""

from __future__ import annotations

import torch
from torch import Tensor

BETAS = (0.9, 0.999)
# torch.optim.Adam's group keys beside lr, params and name, as its state_dict writes them
TORCH_GROUP_DEFAULTS = {"betas": BETAS, "weight_decay": 0, "amsgrad": False, "maximize": False, "foreach": None,
                        "capturable": False, "differentiable": False, "fused": True,
                        "decoupled_weight_decay": False}


class FusedAdam:
    """Adam (no weight decay, no amsgrad) over groups of one parameter each."""

    def __init__(self, groups: list[dict], eps: float):
        """``groups``: ``{"params": [tensor], "lr": float, "name": str}`` each, in a fixed order."""
        for group in groups:
            if len(group["params"]) != 1:
                raise ValueError(f"group {group.get('name')!r}: one parameter per group, got {len(group['params'])}")
        self.eps = eps
        self.param_groups = [{"params": list(g["params"]), "lr": float(g["lr"]), "name": g["name"]} for g in groups]
        self.state: dict[Tensor, dict[str, Tensor]] = {}

    def step(self) -> None:
        """One update of every parameter that has a gradient (torch's rule: a group without one is
        left as it is, its moments uncreated)."""
        for group in self.param_groups:
            (param,) = group["params"]
            if param.grad is None:
                continue
            state = self.state.get(param)
            if state is None:
                state = self.state[param] = self._fresh(param)
            with torch.no_grad():
                torch._foreach_add_([state["step"]], 1)
                torch._fused_adam_([param], [param.grad], [state["exp_avg"]], [state["exp_avg_sq"]], [],
                                   [state["step"]], amsgrad=False, lr=group["lr"], beta1=BETAS[0], beta2=BETAS[1],
                                   weight_decay=0.0, eps=self.eps, maximize=False, grad_scale=None, found_inf=None)

    @staticmethod
    def _fresh(param: Tensor) -> dict[str, Tensor]:
        return {"step": torch.zeros((), dtype=torch.float32, device=param.device),
                "exp_avg": torch.zeros_like(param, memory_format=torch.preserve_format),
                "exp_avg_sq": torch.zeros_like(param, memory_format=torch.preserve_format)}

    def state_dict(self) -> dict:
        """torch.optim.Adam's layout: groups with their parameters' indices, state by index."""
        groups, state = [], {}
        for index, group in enumerate(self.param_groups):
            groups.append({"lr": group["lr"], **TORCH_GROUP_DEFAULTS, "eps": self.eps, "name": group["name"],
                           "params": [index]})
            (param,) = group["params"]
            if param in self.state:
                state[index] = dict(self.state[param])
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, saved: dict) -> None:
        """A ``state_dict`` of this class or of ``torch.optim.Adam`` over the same groups, in order:
        learning rates and moments are taken, cast to each parameter's dtype and device (``step``
        stays float32, as torch keeps it for the fused update)."""
        groups = saved["param_groups"]
        if len(groups) != len(self.param_groups):
            raise ValueError(f"optimizer state has {len(groups)} groups, this optimizer {len(self.param_groups)}")
        self.state = {}
        for group, old in zip(self.param_groups, groups):
            if "name" in old and old["name"] != group["name"]:
                raise ValueError(f"optimizer state group {old['name']!r} where {group['name']!r} was expected")
            (param,) = group["params"]
            group["lr"] = float(old["lr"])
            (index,) = old["params"]
            if index in saved["state"]:
                moments = saved["state"][index]
                self.state[param] = {
                    "step": moments["step"].to(device=param.device, dtype=torch.float32).clone(),
                    "exp_avg": moments["exp_avg"].to(device=param.device, dtype=param.dtype).clone(),
                    "exp_avg_sq": moments["exp_avg_sq"].to(device=param.device, dtype=param.dtype).clone()}
