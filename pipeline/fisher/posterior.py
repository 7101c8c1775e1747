"""Laplace posterior, GO-PRE scores and predictive entropy, all diagonal (as FisherRF).

Vectors are per-parameter diagonals, flattened to [..., D], float64. Paper references:
Eq. covariance-update  Sigma_x = (Sigma^-1 + tau^-2 J_x^T J_x)^-1  ->  Sx = 1 / (1/S + F_x / tau^2)
Eq. go-pre-score       log det(I + tau^-2 Sx^1/2 M Sx^1/2)          ->  sum_i log1p(Sx_i M_i / tau^2)
(the paper sets tau = 1; keeping tau^-2 inside the log makes the tau -> 0 ablation well defined).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def posterior_variance(h_train: Tensor, lam: float = 1e-6) -> Tensor:
    """S = 1 / (H_train + lambda), the Laplace posterior variance [..., D]."""
    if lam <= 0:
        raise ValueError(f"lambda must be positive, got {lam}")
    return 1.0 / (h_train.double() + lam)


def updated_variance(s: Tensor, fisher_x: Tensor, tau: float = 1.0) -> Tensor:
    """Sx = 1 / (1/S + F_x / tau^2) after observing candidate x: S [D], F_x [..., D]."""
    return 1.0 / (1.0 / s + fisher_x.double() / tau ** 2)


def gopre_score(sx: Tensor, goal: Tensor, tau: float = 1.0) -> Tensor:
    """sum_i log1p(Sx_i M_i / tau^2) over the last axis; lower is better (argmin)."""
    return torch.log1p(sx * goal.double() / tau ** 2).sum(-1)


def trace_score(sx: Tensor, goal: Tensor, tau: float = 1.0) -> Tensor:
    """Trace approximation sum_i Sx_i M_i / tau^2 (first-order log1p)."""
    return (sx * goal.double()).sum(-1) / tau ** 2


def monte_carlo_score(sx: Tensor, probe_fishers: Tensor, tau: float = 1.0) -> Tensor:
    """Direct Monte-Carlo mean_k sum_i log1p(Sx_i F_pk,i / tau^2): sx [..., D], probes [K, D]."""
    probes = probe_fishers.double() / tau ** 2
    total = torch.zeros(sx.shape[:-1], dtype=torch.float64, device=sx.device)
    for probe in probes:  # one [..., D] temporary at a time, not [..., K, D]
        total += torch.log1p(sx * probe).sum(-1)
    return total / probes.shape[0]


def goal_hessian(probe_fishers: Tensor) -> Tensor:
    """M = mean over K probe poses of F_p: [K, D] -> [D]."""
    if probe_fishers.shape[0] == 0:
        raise ValueError("goal_hessian: no probe poses (K = 0)")
    return probe_fishers.double().mean(0)


def log_det_information(s: Tensor, fisher: Tensor, tau: float = 1.0) -> Tensor:
    """log det(I + tau^-2 S^1/2 F S^1/2) for diagonal S [D] and F diagonal [D] or dense [D, D].

    By the matrix determinant lemma this equals log det(J S J^T + tau^2 I) - log det(tau^2 I)
    when F = J^T J (the output-space form, whose size is the number of pixels x channels).
    """
    s = s.double()
    if fisher.ndim == 1:
        return torch.log1p(s * fisher.double() / tau ** 2).sum()
    root = s.sqrt()
    eye = torch.eye(len(s), dtype=torch.float64, device=s.device)
    m = eye + root[:, None] * fisher.double() * root[None, :] / tau ** 2
    return torch.linalg.slogdet(m)[1]


def predictive_entropy(s: Tensor, fisher_view: Tensor, num_outputs: int, tau: float = 1.0) -> Tensor:
    """Differential entropy of a view's predictive Gaussian, 1/2 log det(2 pi e (J S J^T + tau^2 I)),
    in the parameter-space form with the diagonal Fisher of the view (nats)."""
    const = 0.5 * num_outputs * (math.log(2 * math.pi * math.e) + 2 * math.log(tau))
    return 0.5 * log_det_information(s, fisher_view, tau) + const
