"""Laplace posterior, GO-PRE scores and predictive entropy, all diagonal (as FisherRF).

Vectors are per-parameter diagonals, flattened to [..., D], float64.

Where tau enters (paper Eqs. 1, 5, 8, 11-12)
--------------------------------------------
Eq. 1 models a pixel as z = f(p, theta) + eta, eta ~ N(0, tau^2 I). Read literally, the noise
scales every likelihood term, so the Laplace posterior would be
    Sigma^-1 = tau^-2 H_train + lambda,  Sigma_x^-1 = Sigma^-1 + tau^-2 F_x        (Eq. 5)
and the score terms become log(1 + M_i / (H_i + F_i + lambda tau^2)): as tau -> 0 the goal M
still weighs every parameter, so under that reading the paper's ablation claim ("taking the limit
tau -> 0, under which the Goal Hessian loses its effect on the candidate ranking", Sec. 4,
Analysis) is false.
The paper instead fixes the posterior at tau = 1 ("we set tau = 1", as FisherRF: Sigma = (H + lambda)^-1,
Sigma_x = (Sigma^-1 + F_x)^-1) and lets tau^2 enter "the acquisition score as a precision-scale
parameter" (the same paragraph, ablation "w/o observation noise"):
    score_tau(x) = log det(I + tau^-2 Sigma_x^1/2 M Sigma_x^1/2) = sum_i log1p(Sx_i M_i / tau^2)  (Eq. 8)
That is what this module implements: ``updated_variance`` and the greedy update H <- H + F_pick
(``acquisition.base.greedy_pick``) use the unit-noise posterior, and tau appears only in the score.
At tau = 1 (the paper's GO-PRE) all readings agree. As tau -> 0, for M_i > 0,
    log1p(Sx_i M_i / tau^2) = log Sx_i + log M_i - 2 log tau + O(tau^2 / (Sx_i M_i)),
and the last three terms do not depend on the candidate x, so the ranking tends to that of
    score_0(x) = sum_{i : M_i > 0} log Sx_i   (= log det Sigma_x restricted to what the goal sees).
M's values drop out; only its support (the parameters some probe pose sees at all) is left.
``gopre_limit_score`` is that limit, computed exactly rather than at a small tau, where
Sx_i M_i / tau^2 would not yet be large for the many tiny M_i and the goal would still rank.
Eqs. 11-12 (the predictive covariance J Sigma J^T + tau^2 I of an arbitrary view) use tau in
``predictive_entropy`` with the same unit-noise Sigma.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


POSTERIOR_LAMBDA = 1e-6  # lambda of S = 1 / (H_train + lambda): every strategy's and map's default


def posterior_variance(h_train: Tensor, lam: float = POSTERIOR_LAMBDA) -> Tensor:
    """S = 1 / (H_train + lambda), the Laplace posterior variance [..., D]."""
    if lam <= 0:
        raise ValueError(f"lambda must be positive, got {lam}")
    return 1.0 / (h_train.double() + lam)


def updated_variance(s: Tensor, fisher_x: Tensor) -> Tensor:
    """Sx = 1 / (1/S + F_x) after observing candidate x (unit-noise posterior, see the module
    docstring): S [D], F_x [..., D]."""
    return 1.0 / (1.0 / s + fisher_x.double())


def gopre_score(sx: Tensor, goal: Tensor, tau: float = 1.0) -> Tensor:
    """sum_i log1p(Sx_i M_i / tau^2) over the last axis; lower is better (argmin)."""
    return torch.log1p(sx * goal.double() / tau ** 2).sum(-1)


def gopre_score_of_fishers(s: Tensor, fisher_x: Tensor, goal: Tensor, tau: float = 1.0) -> Tensor:
    """``gopre_score(updated_variance(s, fisher_x), goal, tau)`` with one [..., D] temporary
    instead of five (the same operations in the same order, in place): S [D], F_x [..., D]."""
    t = fisher_x.double() + 1.0 / s
    t.reciprocal_().mul_(goal.double())
    if tau != 1.0:
        t.div_(tau ** 2)
    return t.log1p_().sum(-1)


def gopre_scores_sparse(s: Tensor, goal: Tensor, views, tau: float = 1.0) -> Tensor:
    """``gopre_score(updated_variance(s, F_x), goal, tau)`` for each view x given as a
    ``fisher.exact.SparseFisher`` (ids [M], rows [M, P]): s, goal [N, P]. A view changes the
    posterior only on its own rows, so each score is the no-view total plus its rows' change,
    computed with the same operations as the dense score (1 / (1 / S) for the untouched entries,
    as the dense formula evaluates them). [len(views)] float64."""
    inv_s = 1.0 / s
    untouched = torch.log1p(inv_s.reciprocal() * goal / tau ** 2)
    total = untouched.sum()
    scores = torch.empty(len(views), dtype=torch.float64)
    for i, view in enumerate(views):
        t = view.rows + inv_s[view.ids]
        t.reciprocal_().mul_(goal[view.ids])
        if tau != 1.0:
            t.div_(tau ** 2)
        scores[i] = total + (t.log1p_().sum() - untouched[view.ids].sum())
    return scores


def gopre_limit_score(sx: Tensor, goal: Tensor) -> Tensor:
    """The tau -> 0 limit of ``gopre_score`` up to candidate-independent terms:
    sum over {i : M_i > 0} of log Sx_i, [..., D] -> [...]; lower is better. M's values do not
    enter, only its support."""
    seen = goal.double() > 0
    return torch.where(seen, torch.log(sx), torch.zeros_like(sx)).sum(-1)


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
