"""Exact diagonal Fisher against brute-force Jacobians, and the posterior/score identities."""

import math
from dataclasses import replace

import pytest
import torch

from pipeline.fisher.exact import FisherSpec, view_fisher
from pipeline.fisher.posterior import (gopre_score, log_det_information, monte_carlo_score,
                                       posterior_variance, updated_variance)
from pipeline.splat import Gaussians, RenderSettings, render
from pipeline.splat.scenes import orbit_cameras, random_scene

F64 = torch.float64
BG = torch.tensor([0.3, 0.6, 0.9], dtype=F64)
SETTINGS = RenderSettings(tile_size=4, chunk=5)


def jacobians(g, cams, groups, settings=SETTINGS):
    """Per group, the dense Jacobian [pixels*channels, N, p] of all cameras' RGB (stacked)."""
    names = list(g.params())

    def fn(*sel):
        params = dict(g.params())
        params.update(dict(zip(groups, sel)))
        return render(Gaussians(**params), cams, BG, settings=settings).rgb.reshape(-1)
    jac = torch.autograd.functional.jacobian(fn, tuple(g.params()[k] for k in groups))
    n = len(g)
    assert set(groups) <= set(names)
    return [j.reshape(j.shape[0], n, -1) for j in jac]


def brute_fisher(g, cams, groups, settings=SETTINGS):
    return torch.cat([j.square().sum(0) for j in jacobians(g, cams, groups, settings)], dim=1)


@pytest.mark.parametrize("seed,opacity", [(0, (0.3, 0.9)), (1, (0.6, 0.999)), (2, (0.05, 0.3)),
                                          (3, (0.995, 0.9999))])  # the last one hits alpha = 0.99
def test_exact_fisher_matches_autograd_jacobian_every_group(seed, opacity):
    g = random_scene(25, seed=seed, dtype=F64, sh_degree=2, opacity_range=opacity)
    cams = orbit_cameras(1, 13, 11, dtype=F64, radius=2.4, phase=seed)
    groups = ("means", "log_scales", "quats", "logit_opacities", "sh0", "shN")
    ours = view_fisher(g, cams, BG, FisherSpec(groups), SETTINGS)[0]
    ref = brute_fisher(g, cams, groups)
    assert ref.abs().sum() > 0
    assert ((ours - ref).norm() / ref.norm()).item() < 1e-10


def test_fisher_parameter_subset_and_lower_sh_degree():
    g = random_scene(20, seed=3, dtype=F64, sh_degree=2)
    cams = orbit_cameras(1, 12, 12, dtype=F64, radius=2.4)
    groups = ("means", "logit_opacities", "shN")
    ours = view_fisher(g, cams, BG, FisherSpec(groups), SETTINGS)[0]
    ref = brute_fisher(g, cams, groups)
    assert ours.shape == (20, 3 + 1 + 24)
    assert torch.allclose(ours, ref, rtol=1e-9, atol=1e-12)


def test_fisher_is_additive_over_views_and_non_negative():
    g = random_scene(20, seed=4, dtype=F64)
    cams = orbit_cameras(2, 10, 10, dtype=F64, radius=2.4)
    groups = ("means", "log_scales", "quats")
    per_view = view_fisher(g, cams, BG, FisherSpec(groups), SETTINGS)
    joint = brute_fisher(g, cams, groups)  # Jacobian of both images stacked
    assert (per_view >= 0).all()
    assert torch.allclose(per_view.sum(0), joint, rtol=1e-9, atol=1e-12)


def test_fisher_is_zero_for_gaussians_no_pixel_sees():
    g = random_scene(20, seed=5, dtype=F64)
    far = g.means.detach().clone()
    far[:3] = torch.tensor([[40.0, 40.0, 40.0]], dtype=F64)  # far outside the frustum
    g = g.replace(means=far)
    cams = orbit_cameras(1, 12, 12, dtype=F64, radius=2.4)
    f = view_fisher(g, cams, BG, settings=SETTINGS)[0]
    assert (f[:3] == 0).all() and (f[3:].sum(1) > 0).any()


def test_fisher_over_more_tiles_than_one_walk_block():
    """A 26x22 view at tile size 2 has 143 tiles: the walk's blocks of 64 tiles each count once."""
    g = random_scene(12, seed=12, dtype=F64, sh_degree=1, scale_range=(0.15, 0.4))
    cams = orbit_cameras(1, 26, 22, dtype=F64, radius=2.4)
    groups = ("means", "logit_opacities", "sh0")
    fine = RenderSettings(tile_size=2, chunk=4, backend="tiles")  # the torch walk has the blocks
    ours = view_fisher(g, cams, BG, FisherSpec(groups), fine)[0]
    ref = brute_fisher(g, cams, groups)
    assert ((ours - ref).norm() / ref.norm()).item() < 1e-10


def test_fisher_uses_the_settings_near_plane():
    """A Gaussian between the default near plane (0.01) and the settings' (1.0) is culled: zero
    Fisher, as the brute-force Jacobian of the render at that near plane says."""
    g = random_scene(10, seed=13, dtype=F64, sh_degree=0)
    cams = orbit_cameras(1, 12, 10, dtype=F64, radius=2.4)
    eye = torch.linalg.inv(cams.viewmats[0])[:3, 3]
    means = g.means.detach().clone()
    means[0] = eye * 0.75  # 0.6 in front of the camera, on its axis towards the origin
    g = g.replace(means=means)
    groups = ("means", "logit_opacities", "sh0")
    near = replace(SETTINGS, near=1.0)
    ours = view_fisher(g, cams, BG, FisherSpec(groups), near)[0]
    assert (ours[0] == 0).all() and (view_fisher(g, cams, BG, FisherSpec(groups), SETTINGS)[0][0] > 0).any()
    ref = brute_fisher(g, cams, groups, near)
    assert ((ours - ref).norm() / ref.norm()).item() < 1e-10
    # and a near plane below the default: a tiny Gaussian 0.005 in front of the eye is seen
    forward = -eye / eye.norm()
    means[0] = eye + 0.005 * forward + torch.tensor([2e-4, 1e-4, 0.0], dtype=F64)
    log_scales = g.log_scales.detach().clone()
    log_scales[0] = math.log(2e-4)
    g = g.replace(means=means, log_scales=log_scales)
    close = replace(SETTINGS, near=0.001, backend="tiles")
    ours = view_fisher(g, cams, BG, FisherSpec(groups), close)[0]
    ref = brute_fisher(g, cams, groups, close)
    assert (ours[0] > 0).all() and ((ours - ref).norm() / ref.norm()).item() < 1e-10


def test_fisher_of_one_gaussian_and_of_none():
    g = random_scene(1, seed=14, dtype=F64, sh_degree=1, scale_range=(0.5, 0.8))
    cams = orbit_cameras(1, 9, 8, dtype=F64, radius=2.4)
    ours = view_fisher(g, cams, BG, FisherSpec(), SETTINGS)[0]
    ref = brute_fisher(g, cams, FisherSpec().groups)
    assert ref.abs().sum() > 0 and ((ours - ref).norm() / ref.norm()).item() < 1e-10
    with pytest.raises(ValueError, match=r"^gaussians: cannot compute the Fisher of an empty scene$"):
        view_fisher(g.index(torch.zeros(1, dtype=torch.bool)), cams, BG, FisherSpec(), SETTINGS)


def test_determinant_lemma_output_space_equals_parameter_space():
    g = random_scene(6, seed=6, dtype=F64, sh_degree=0)
    cams = orbit_cameras(1, 6, 5, dtype=F64, radius=2.4)
    J = torch.cat(jacobians(g, cams, ("means", "log_scales")), dim=2).reshape(90, -1)  # [90, 36]
    s = torch.rand(J.shape[1], generator=torch.Generator().manual_seed(0), dtype=F64) + 0.1
    for tau in (1.0, 0.3):
        out_space = 0.5 * torch.linalg.slogdet(J @ torch.diag(s) @ J.T + tau ** 2 * torch.eye(90, dtype=F64))[1] \
            - 0.5 * 90 * math.log(tau ** 2)
        param_space = 0.5 * log_det_information(s, J.T @ J, tau)
        assert out_space.item() == pytest.approx(param_space.item(), rel=1e-10)


def _fisher_vectors(seed=7, views=6):
    g = random_scene(60, seed=seed, dtype=F64)
    cams = orbit_cameras(views, 12, 12, dtype=F64, radius=2.6)
    return view_fisher(g, cams, BG, settings=SETTINGS).flatten(1)


def test_jensen_gopre_score_bounds_direct_monte_carlo():
    f = _fisher_vectors()
    h, cands, probes = f[:2].sum(0), f[2:4], f[4:]
    sx = updated_variance(posterior_variance(h), cands)
    upper = gopre_score(sx, probes.mean(0))
    mc = monte_carlo_score(sx, probes)
    assert (upper >= mc - 1e-9).all() and (upper > mc).any()


def test_gopre_with_a_large_identity_goal_ranks_as_dopt():
    f = _fisher_vectors(seed=8, views=8)
    h, cands = f[:2].sum(0), f[2:]
    sx = updated_variance(posterior_variance(h), cands)
    gopre = gopre_score(sx, torch.full_like(h, 1e12))
    dopt = torch.log1p(cands / (h + 1e-6)).sum(-1)
    assert torch.argsort(gopre).tolist() == torch.argsort(dopt, descending=True).tolist()


def test_posterior_rejects_bad_lambda():
    with pytest.raises(ValueError, match="lambda"):
        posterior_variance(torch.ones(3), 0.0)


@pytest.mark.parametrize("groups", [None, ("means", "sh0"), ("quats", "logit_opacities")])
def test_predictive_variance_map_matches_dense_jacobian(groups):
    """sum_p J_p^2 S_p per pixel and channel, for all groups and for subsets whose width P is
    below N (the covariance is per Gaussian, the spec's groups are the ones S covers)."""
    from pipeline.fisher.exact import predictive_variance_maps
    g = random_scene(20, seed=9, dtype=F64, sh_degree=1, opacity_range=(0.3, 0.999))
    cams = orbit_cameras(1, 10, 9, dtype=F64, radius=2.4)
    spec = FisherSpec() if groups is None else FisherSpec(groups=groups)
    J = torch.cat(jacobians(g, cams, spec.groups), dim=2)  # [270, N, P]
    s = torch.rand(20, J.shape[2], generator=torch.Generator().manual_seed(1), dtype=F64) + 0.1
    brute = (J.square() * s).sum((1, 2)).reshape(9, 10, 3)
    ours = predictive_variance_maps(g, cams, s, BG, spec, SETTINGS)[0]
    assert ((ours - brute).norm() / brute.norm()).item() < 1e-10
    # the map is the torch walk's whatever backend the caller renders with (compiled or not)
    auto = predictive_variance_maps(g, cams, s, BG, spec, RenderSettings(tile_size=16))[0]
    assert ((auto - brute).norm() / brute.norm()).item() < 1e-10


def test_render_settings_name_an_unknown_backend():
    """Checked where the settings are made (a config, or the variance maps' own tile walk), so the
    renderer, the Fisher walk and the maps cannot run an unknown backend as the torch walk."""
    for name in ("XXtilesXX", "TILES", None, "dens"):
        with pytest.raises(ValueError, match=r"^backend must be one of \['auto', 'compiled', 'tiles', 'dense', 'loop'\], got "):
            RenderSettings(backend=name)
    assert RenderSettings(backend="loop").backend == "loop"


def test_predictive_entropy_parameter_form_equals_output_form_for_diagonal_fisher():
    from pipeline.fisher.posterior import predictive_entropy
    gen = torch.Generator().manual_seed(2)
    s, f = torch.rand(7, generator=gen, dtype=F64), torch.rand(7, generator=gen, dtype=F64)
    J = torch.diag(f.sqrt())  # a view whose J^T J is exactly diag(f), 7 outputs
    dense = 0.5 * torch.linalg.slogdet(2 * math.pi * math.e * (J @ torch.diag(s) @ J.T
                                                                 + 0.25 * torch.eye(7, dtype=F64)))[1]
    assert predictive_entropy(s, f, 7, tau=0.5).item() == pytest.approx(dense.item(), rel=1e-12)


def test_centre_moments_equal_moments_taken_about_the_new_origin():
    from pipeline.fisher.exact import MOMENT_EXPONENTS, PHI_EXPONENTS, centre_moments
    gen = torch.Generator().manual_seed(11)
    xy = torch.rand(3, 40, 2, generator=gen, dtype=F64) * 8 - 4  # 3 rows of 40 pixels
    w = torch.rand(3, 40, 2, generator=gen, dtype=F64)  # two weight channels
    offsets = torch.randn(3, 2, generator=gen, dtype=F64) * 5

    def moments(points, exps):
        x, y = points[..., 0], points[..., 1]
        return torch.stack([((x ** a * y ** b)[..., None] * w).sum(1) for a, b in exps])  # [E, 3, 2]
    for exps in (MOMENT_EXPONENTS, PHI_EXPONENTS):
        shifted = centre_moments(moments(xy, exps), offsets, exps)
        direct = moments(xy - offsets[:, None, :], exps)
        assert torch.allclose(shifted, direct, rtol=1e-10, atol=1e-9)


def test_fisher_at_a_lower_active_sh_degree_matches_autograd():
    g = random_scene(20, seed=12, dtype=F64, sh_degree=2)
    cams = orbit_cameras(1, 12, 11, dtype=F64, radius=2.4)
    groups = ("means", "sh0", "shN")

    def fn(means, sh0, shn):
        h = Gaussians(**{**g.params(), "means": means, "sh0": sh0, "shN": shn})
        return render(h, cams, BG, sh_degree=1, settings=SETTINGS).rgb.reshape(-1)
    jac = torch.autograd.functional.jacobian(fn, tuple(g.params()[k] for k in groups))
    ref = torch.cat([j.reshape(j.shape[0], 20, -1).square().sum(0) for j in jac], dim=1)
    ours = view_fisher(g, cams, BG, FisherSpec(groups, sh_degree=1), SETTINGS)[0]
    assert ref[:, 3 + 3 + 9:].abs().max() == 0  # degree-2 coefficients are inactive
    assert ((ours - ref).norm() / ref.norm()).item() < 1e-10


def test_fisher_skips_occluded_gaussians_exactly():
    """An opaque wall in front: Gaussians behind it are never walked, and get exactly zero."""
    from pipeline.fisher.exact import view_factors
    g = random_scene(80, seed=13, dtype=F64, opacity_range=(0.3, 0.9))
    cams = orbit_cameras(1, 12, 12, dtype=F64, radius=2.4)
    eye = cams.centers[0]
    wall = Gaussians(means=(0.5 * eye)[None].repeat(3, 1), log_scales=torch.full((3, 3), 1.0, dtype=F64),
                     quats=torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=F64),
                     logit_opacities=torch.full((3,), 12.0, dtype=F64),
                     sh0=torch.zeros(3, 1, 3, dtype=F64), shN=torch.zeros(3, 3, 3, dtype=F64))
    scene = Gaussians.cat([wall, g])
    factors = next(view_factors(scene, cams, BG, FisherSpec(), SETTINGS))
    assert factors.seen.numel() < len(scene)  # some Gaussians are hidden behind the wall
    ours = view_fisher(scene, cams, BG, settings=SETTINGS)[0]
    ref = brute_fisher(scene, cams, ("means", "log_scales", "quats", "logit_opacities", "sh0", "shN"))
    hidden = torch.ones(len(scene), dtype=torch.bool)
    hidden[factors.seen] = False
    assert (ours[hidden] == 0).all() and ((ours - ref).norm() / ref.norm()).item() < 1e-10


def test_float32_at_production_settings_matches_float64():
    """Production runs float32 with the default tiles (8 px) and chunks: the Fisher and the
    render with its gradients agree with float64 to 1e-4 relative on a realistic scene."""
    g64 = random_scene(3000, seed=12, dtype=F64, sh_degree=3, opacity_range=(0.2, 0.95))
    cams64 = orbit_cameras(2, 48, 40, dtype=F64, radius=2.8)
    g32, cams32 = g64.to(dtype=torch.float32), cams64.to(dtype=torch.float32)
    f64 = view_fisher(g64, cams64, BG)
    f32 = view_fisher(g32, cams32, BG.float())
    assert ((f32.double() - f64).norm() / f64.norm()).item() < 1e-4, "Fisher float32 vs float64"
    grads = {}
    for dtype, g, cams in ((F64, g64, cams64), (torch.float32, g32, cams32)):
        leaves = g.clone().requires_grad_()
        out = render(leaves, cams, BG.to(dtype))
        (out.rgb.square().sum() + out.alpha.sum()).backward()
        grads[dtype] = (out.rgb.detach().double(), {k: v.grad.double() for k, v in leaves.params().items()})
    rgb64, grad64 = grads[F64]
    rgb32, grad32 = grads[torch.float32]
    assert ((rgb32 - rgb64).norm() / rgb64.norm()).item() < 1e-5, "image float32 vs float64"
    for name, grad in grad64.items():
        assert ((grad32[name] - grad).norm() / grad.norm()).item() < 1e-4, f"gradient of {name}"


def released_fisherrf_brute_force(g, cams):
    """FisherRF's released Hessian by autograd, from its description (design notes): geometry and
    opacity entries are sum_p (sum_c dI_pc / d theta_act)^2 w.r.t. the activated parameter
    (means as is, scale = exp(log-scale), opacity = sigmoid(logit)), multiplied once by the
    activation's derivative; SH entries are per-channel sums of squares. [N, 3 + 3 + 1 + 3 + 3K]."""
    n = len(g)
    scales, opac = g.log_scales.exp(), torch.sigmoid(g.logit_opacities)

    def channel_summed(means, s, o):
        h = Gaussians(**{**g.params(), "means": means, "log_scales": s.log(), "logit_opacities": torch.logit(o)})
        return render(h, cams, BG, settings=SETTINGS).rgb.sum(-1).reshape(-1)
    jm, js, jo = torch.autograd.functional.jacobian(channel_summed, (g.means, scales, opac))
    means = jm.reshape(-1, n, 3).square().sum(0)
    log_scales = js.reshape(-1, n, 3).square().sum(0) * scales          # exp' = exp, once
    opacity = jo.reshape(-1, n).square().sum(0) * opac * (1 - opac)      # sigmoid', once
    sh = torch.cat([j.square().sum(0) for j in jacobians(g, cams, ("sh0", "shN"))], dim=1)
    return torch.cat([means, log_scales, opacity[:, None], sh], dim=1)


@pytest.mark.parametrize("backend", ["tiles", "compiled"])
def test_released_fisherrf_hessian_matches_its_description_by_autograd(backend):
    from dataclasses import replace
    from pipeline.acquisition.fisherrf import FISHERRF_GROUPS
    from pipeline.splat import compiled
    if backend == "compiled" and compiled.load() is None:
        pytest.skip(f"compiled backend unavailable: {compiled.load_error()}")
    g = random_scene(25, seed=21, dtype=F64, sh_degree=1, opacity_range=(0.2, 0.95))
    means = g.means.detach().clone()
    means[[3, 17]] = torch.tensor([[40.0, 40.0, 40.0]], dtype=F64)  # unseen: zero rows, not shifted
    g = g.replace(means=means)
    cams = orbit_cameras(1, 13, 11, dtype=F64, radius=2.4, phase=1)
    spec = FisherSpec(FISHERRF_GROUPS, hessian="fisherrf_released")
    ours = view_fisher(g, cams, BG, spec, replace(SETTINGS, backend=backend))[0]
    ref = released_fisherrf_brute_force(g, cams)
    exact = view_fisher(g, cams, BG, FisherSpec(FISHERRF_GROUPS), SETTINGS)[0]
    assert ours.shape == ref.shape == (25, 3 + 3 + 1 + 3 + 9)
    assert ((ours - ref).norm() / ref.norm()).item() < 1e-10
    assert torch.allclose(ours[:, 7:], exact[:, 7:], rtol=1e-10, atol=0)  # SH entries are exact
    assert ((ours[:, :7] - exact[:, :7]).norm() / exact[:, :7].norm()).item() > 1e-2
    assert (ours[[3, 17]] == 0).all() and (ours.sum(1) > 0).sum() > 20


def test_the_fisher_background_defaults_to_black():
    g = random_scene(12, seed=22, dtype=F64, sh_degree=1)
    cams = orbit_cameras(1, 10, 9, dtype=F64, radius=2.4)
    spec = FisherSpec(("means", "logit_opacities", "sh0"))
    black = view_fisher(g, cams, torch.zeros(3, dtype=F64), spec, SETTINGS)
    assert torch.equal(view_fisher(g, cams, None, spec, SETTINGS), black)
    assert not torch.allclose(view_fisher(g, cams, BG, spec, SETTINGS), black)  # it matters


def test_the_fisher_runs_the_walk_its_backend_names(monkeypatch):
    """``compiled`` projects and walks in the kernels (no torch walk kept), ``tiles`` projects with
    ``project`` and keeps its ViewWalk: a request for the compiled path is not served by the torch
    one (equal values, 4-8x the time)."""
    import importlib

    from pipeline.fisher.exact import ViewWalk, view_factors
    from pipeline.splat import compiled
    exact = importlib.import_module("pipeline.fisher.exact")
    calls = []
    for name in ("project", "feature_jacobian", "feature_jacobian_compiled"):
        monkeypatch.setattr(exact, name, lambda *a, _f=getattr(exact, name), _n=name: calls.append(_n) or _f(*a))
    g = random_scene(6, seed=23, dtype=F64)
    cams = orbit_cameras(1, 8, 8, dtype=F64)
    for spec in (FisherSpec(), FisherSpec(hessian="fisherrf_released")):
        calls.clear()
        tiles = next(view_factors(g, cams, BG, spec, replace(SETTINGS, backend="tiles")))
        assert isinstance(tiles.walk, ViewWalk) and calls == ["project", "feature_jacobian"], spec
    if compiled.load() is None:
        pytest.skip(f"compiled backend unavailable: {compiled.load_error()}")
    monkeypatch.setattr(compiled, "project_compiled",
                        lambda *a, _f=compiled.project_compiled: calls.append("compiled") or _f(*a))
    for spec in (FisherSpec(), FisherSpec(hessian="fisherrf_released")):
        calls.clear()
        factors = next(view_factors(g, cams, BG, spec, replace(SETTINGS, backend="compiled")))
        assert factors.walk is None and calls == ["compiled", "feature_jacobian_compiled"], spec


def test_fisher_spec_rejects_an_unknown_hessian():
    with pytest.raises(ValueError, match="hessian must be one of .*'exact', 'fisherrf_released'.* got 'exakt'"):
        FisherSpec(hessian="exakt")


def test_scores_reduce_the_last_axis_of_any_batch_shape_in_float64():
    """Scores take sx [..., D]: a [2, 3, D] batch gives [2, 3], each entry the 1-D score, in float64
    even from float32 inputs (a wrong axis or a float32 accumulator shows here)."""
    from pipeline.fisher.posterior import trace_score
    gen = torch.Generator().manual_seed(5)
    sx = torch.rand(2, 3, 7, generator=gen, dtype=F64) + 0.1
    goal, probes = torch.rand(7, generator=gen), torch.rand(4, 7, generator=gen)
    for name, fn, arg in (("gopre", gopre_score, goal), ("trace", trace_score, goal),
                          ("mc", monte_carlo_score, probes)):
        out = fn(sx.float(), arg, 0.7)
        assert out.shape == (2, 3) and out.dtype == F64, name
        for i in range(2):
            for j in range(3):
                assert out[i, j].item() == pytest.approx(fn(sx[i, j].float(), arg, 0.7).item(), rel=1e-12), name
    assert monte_carlo_score(sx, probes, 0.7)[1, 2].item() == pytest.approx(
        sum(torch.log1p(sx[1, 2] * p.double() / 0.49).sum().item() for p in probes) / 4, rel=1e-12)


def test_paper_defaults_tau_is_one():
    """The paper sets tau = 1: every function's default equals an explicit tau = 1."""
    s = torch.tensor([0.5, 2.0, 3.0], dtype=F64)
    f = torch.tensor([1.0, 0.25, 4.0], dtype=F64)
    dense = torch.outer(f, f) + torch.diag(f)
    assert torch.equal(updated_variance(s, f), 1 / (1 / s + f))
    assert log_det_information(s, f).item() == pytest.approx(torch.log1p(s * f).sum().item(), rel=1e-14)
    expected = torch.linalg.slogdet(torch.eye(3, dtype=F64) + s.sqrt()[:, None] * dense * s.sqrt()[None])[1]
    assert log_det_information(s, dense).item() == pytest.approx(expected.item(), rel=1e-14)
    from pipeline.fisher.posterior import predictive_entropy, trace_score
    sx, probes = torch.tensor([[0.3, 0.2, 0.9]], dtype=F64), torch.tensor([[1.0, 2.0, 0.5], [0.1, 0.0, 3.0]], dtype=F64)
    assert trace_score(sx, f).item() == pytest.approx((sx * f).sum().item(), rel=1e-14)
    assert gopre_score(sx, f).item() == pytest.approx(torch.log1p(sx * f).sum().item(), rel=1e-14)
    assert monte_carlo_score(sx, probes).item() == pytest.approx(
        torch.log1p(sx * probes).sum(-1).mean().item(), rel=1e-14)
    assert predictive_entropy(s, f, 12).item() == pytest.approx(
        0.5 * torch.log1p(s * f).sum().item() + 6 * math.log(2 * math.pi * math.e), rel=1e-14)



def test_the_parameter_layout_names_an_unknown_group():
    from pipeline.fisher.features import PARAM_GROUPS, param_layout
    from pipeline.splat.scenes import random_scene
    g = random_scene(3, seed=0, sh_degree=1)
    assert param_layout(g, ("sh0", "means")) == [("means", 3), ("sh0", 3)]  # the flattened order
    with pytest.raises(ValueError, match=r"^unknown parameter groups \['rotation'\]; choose from "):
        param_layout(g, ("means", "rotation"))
    assert len(PARAM_GROUPS) == 6


def test_the_feature_jacobian_checks_its_block_shapes():
    """The geometry block is [N, 8, Q] with Q the selected geometric width (0 for colour only):
    both backends build it so, and a block of another shape is refused by name."""
    from pipeline.fisher.features import FeatureJacobian, feature_jacobian, feature_jacobian_compiled
    from pipeline.splat import compiled
    g = random_scene(4, seed=1, sh_degree=1)
    cams = orbit_cameras(1, 64, 48)
    backends = [feature_jacobian] + ([feature_jacobian_compiled] if compiled.load() is not None else [])
    for jacobian in backends:
        for groups, q in ((("sh0", "shN"), 0), (("means", "logit_opacities"), 3), (("quats", "log_scales"), 7)):
            a = jacobian(g, cams.viewmats[0], cams.Ks[0], 64, 48, groups, None, 0.01)
            assert tuple(a.geometry.shape) == (4, 8, q), (jacobian.__name__, groups)
            assert tuple(a.dense().shape) == (4, 9, sum(w for _, w in a.layout)), (jacobian.__name__, groups)
    with pytest.raises(ValueError, match=r"geometry block has shape \(4, 9, 0\), expected \[N, 8, Q\] = \(4, 8, 0\)"):
        FeatureJacobian([("sh0", 3)], torch.zeros(4, 9, 0), a.opacity_slope, a.sh_slope)
    with pytest.raises(ValueError, match=r"geometry block has shape \(4, 8, 3\), expected .* = \(4, 8, 4\)"):
        FeatureJacobian([("quats", 4)], torch.zeros(4, 8, 3), a.opacity_slope, a.sh_slope)
    with pytest.raises(ValueError, match=r"SH slope has shape \(3, 4, 3\), expected \[N=4, K, 3\]"):
        FeatureJacobian([("sh0", 3)], torch.zeros(4, 8, 0), a.opacity_slope, a.sh_slope[:3])


@pytest.mark.parametrize("backend", ["tiles", "auto"])
def test_the_fisher_takes_cameras_to_the_gaussians_dtype(backend):
    g = random_scene(8, seed=24, dtype=F64)
    cams = orbit_cameras(1, 8, 8)  # float32, as the loaders give them
    spec, settings = FisherSpec(("means", "sh0")), replace(SETTINGS, backend=backend)
    assert torch.equal(view_fisher(g, cams, BG, spec, settings),
                       view_fisher(g, cams.to(dtype=F64), BG, spec, settings))


def test_tau_to_zero_removes_the_goal_from_the_ranking_and_tau_one_does_not():
    """The paper: "taking the limit tau -> 0, under which the Goal Hessian loses its effect on the
    candidate ranking". Two goals on a 2-parameter toy pick different views at tau = 1; their
    finite-tau rankings converge to the limit ranking, which is the same for both."""
    from pipeline.acquisition.base import greedy_pick
    from pipeline.fisher.posterior import gopre_limit_score
    h = torch.tensor([1.0, 1.0], dtype=F64)
    cands = torch.tensor([[9.0, 0.0], [0.0, 4.0], [2.0, 2.5]], dtype=F64)  # view 0 sees parameter 0, ...
    goals = {"a": torch.tensor([10.0, 0.1], dtype=F64), "b": torch.tensor([0.1, 10.0], dtype=F64)}

    def pick(goal, tau):
        def score(hh, f):
            sx = updated_variance(posterior_variance(hh), f)
            return gopre_limit_score(sx, goal) if tau == 0 else gopre_score(sx, goal, tau)
        return greedy_pick(cands, h, score, count=3, maximize=False)[0]
    assert pick(goals["a"], 1.0)[0] != pick(goals["b"], 1.0)[0]
    assert pick(goals["a"], 0) == pick(goals["b"], 0)
    for goal in goals.values():
        assert pick(goal, 1e-5) == pick(goal, 0)  # the limit is the small-tau ranking
