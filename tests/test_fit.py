"""Training: losses, density control and end-to-end fits that must clear a PSNR bar."""

import math

import pytest
import torch

from pipeline.fit import Trainer, evaluate_psnr
from pipeline.fit.config import DensifyConfig, FitConfig
from pipeline.fit.densify import DensifyStats, densify_and_prune, remap, reset_opacity
from pipeline.fit.init import knn_rms_distance, random_in_box
from pipeline.fit.losses import photometric_loss, psnr, ssim, ssim_map
from pipeline.splat import render
from pipeline.splat.scenes import random_scene, sphere_cameras
from tests.conftest import shared_scene


def tiny_preset() -> FitConfig:
    """A few hundred iterations at 48 px with SH degree 1: the trainer's test recipe."""
    return FitConfig(iterations=300, sh_degree=1, sh_degree_interval=100, image_width=48, init_points=1000,
                     densify=DensifyConfig(start=60, stop=200, interval=40, prune_large_after=10_000,
                                           opacity_reset_interval=10_000, max_gaussians=5000))


def test_ssim_properties_and_skimage_agreement():
    from skimage.metrics import structural_similarity
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(64, 64, 3, generator=gen)
    x = torch.nn.functional.avg_pool2d(x.permute(2, 0, 1)[None], 3, 1, 1)[0].permute(1, 2, 0)
    noisy = (x + 0.1 * torch.randn(x.shape, generator=gen)).clamp(0, 1)
    assert ssim(x, x).item() == pytest.approx(1.0, abs=1e-6)
    assert ssim(x, noisy).item() == pytest.approx(ssim(noisy, x).item(), abs=1e-6)
    # skimage drops a 5 px border of the SSIM map; inside it the windows never touch the padding
    ours = ssim_map(x, noisy)[..., 5:-5, 5:-5].mean().item()
    ref = structural_similarity(x.numpy(), noisy.numpy(), channel_axis=2, data_range=1.0,
                                gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    assert ours < 0.95 and ours == pytest.approx(ref, abs=1e-4)


def test_psnr_and_loss_closed_forms():
    a = torch.zeros(4, 4, 3)
    b = torch.full((4, 4, 3), 0.1)
    assert psnr(a, b).item() == pytest.approx(20.0, rel=1e-5)
    assert photometric_loss(a, a).item() == pytest.approx(0.0, abs=1e-6)
    assert photometric_loss(a, b, ssim_weight=0.0).item() == pytest.approx(0.1, rel=1e-6)


def test_knn_rms_distance_on_a_grid():
    g = torch.stack(torch.meshgrid(*[torch.arange(4.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    d = knn_rms_distance(g * 0.5, k=3, block=7)
    assert torch.allclose(d, torch.full_like(d, 0.5))


def test_knn_scale_is_the_root_mean_square_of_the_three_nearest_distances():
    """3DGS initialises scales as sqrt(mean of the squared distances to the 3 nearest points), not
    their mean distance: points on a line at 0, 1, 3, 6, 10, written out by hand."""
    x = torch.tensor([0.0, 1.0, 3.0, 6.0, 10.0], dtype=torch.float64)
    points = torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)], -1)
    d = knn_rms_distance(points, k=3, block=2)
    by_hand = [(1, 3, 6), (1, 2, 5), (2, 3, 3), (3, 4, 5), (4, 7, 9)]  # nearest three of each point
    expected = torch.tensor([math.sqrt(sum(v * v for v in t) / 3) for t in by_hand], dtype=torch.float64)
    assert torch.allclose(d, expected, rtol=1e-12)


def _trainer_with_grads(n=50):
    g = random_scene(n, seed=0)
    cams = sphere_cameras(2, 16, 16)
    with torch.no_grad():
        imgs = render(g, cams).rgb
    t = Trainer(g, cams, imgs, tiny_preset())
    t.train_step()  # creates Adam state
    return t


def test_densify_clones_small_splits_large_and_remaps_adam():
    t = _trainer_with_grads()
    n = len(t.gaussians)
    scales = torch.exp(t.params["log_scales"].detach()).max(1).values
    big = scales > 0.01 * t.extent
    stats = DensifyStats.zeros(n, scales)
    stats.grad_sum[:10] = 1.0  # ten Gaussians over the threshold
    stats.count[:] = 1
    cfg = DensifyConfig(min_opacity=0.0)
    params = densify_and_prune(t.params, t.optimizer, stats, cfg, t.extent, prune_large=False,
                               generator=torch.Generator().manual_seed(0))
    n_big = int(big[:10].sum())
    assert params["means"].shape[0] == n + (10 - n_big) + n_big * (cfg.split_count - 1)
    for group in t.optimizer.param_groups:
        p = group["params"][0]
        assert p is params[group["name"]]
        assert t.optimizer.state[p]["exp_avg"].shape == p.shape


def test_densify_respects_the_cap():
    t = _trainer_with_grads()
    n = len(t.gaussians)
    stats = DensifyStats.zeros(n, t.params["means"])
    stats.grad_sum[:] = 1.0
    stats.count[:] = 1
    cfg = DensifyConfig(min_opacity=0.0, max_gaussians=n + 7)
    params = densify_and_prune(t.params, t.optimizer, stats, cfg, t.extent, prune_large=False)
    assert n < params["means"].shape[0] <= n + 7


def test_prune_by_opacity_and_reset_opacity():
    t = _trainer_with_grads()
    n = len(t.gaussians)
    with torch.no_grad():
        t.params["logit_opacities"][:5] = -20.0
    keep = torch.ones(n, dtype=torch.bool)
    t.params = remap(t.params, t.optimizer, keep)
    stats = DensifyStats.zeros(n, t.params["means"])
    params = densify_and_prune(t.params, t.optimizer, stats, DensifyConfig(), t.extent, False)
    assert params["means"].shape[0] == n - 5
    params = reset_opacity(params, t.optimizer, 0.01)
    assert torch.sigmoid(params["logit_opacities"]).max().item() <= 0.01 + 1e-6


@pytest.mark.slow
def test_fit_known_scene_clears_psnr_bar_on_held_out_views():
    gt = random_scene(300, seed=0, sh_degree=1, extent=0.8, opacity_range=(0.6, 0.99))
    train, test = sphere_cameras(24, 48, 48, seed=1), sphere_cameras(8, 48, 48, seed=2)
    bg = torch.ones(3)
    with torch.no_grad():
        train_imgs, test_imgs = render(gt, train, bg).rgb, render(gt, test, bg).rgb
    cfg = tiny_preset()
    init = random_in_box(cfg.init_points, torch.full((3,), -1.0), torch.full((3,), 1.0),
                         cfg.sh_degree)
    before = evaluate_psnr(init, test, test_imgs, bg)
    trainer = Trainer(init, train, train_imgs, cfg, bg)
    trainer.train(cfg.iterations)
    after = evaluate_psnr(trainer.gaussians, test, test_imgs, bg)
    assert before < 20.0 and after > before + 5.0
    assert after > 24.0  # measured 27.2 dB


@pytest.mark.slow
def test_short_fit_on_lego_clears_psnr_bar():
    from pipeline.data.blender import read_blender
    scene = read_blender(shared_scene("blender", "lego"), width=64)
    train, test = scene.split("train"), scene.split("test")
    idx, test_idx = list(range(0, 100, 4)), list(range(0, 200, 20))
    cfg = tiny_preset().with_changes(iterations=600)
    lo, hi = scene.bounds()
    trainer = Trainer(random_in_box(cfg.init_points, lo, hi, cfg.sh_degree), train.cameras[idx],
                      train.images.stack(idx), cfg, scene.background)
    trainer.train(cfg.iterations)
    value = evaluate_psnr(trainer.gaussians, test.cameras[test_idx], test.images.stack(test_idx),
                          scene.background)
    assert value > 19.0  # measured 22.1 dB


def test_scaled_schedules_and_no_opacity_reset_at_the_end():
    from pipeline.active.config import cpu_episode
    cfg = cpu_episode().fit.scaled_to(1000)
    assert cfg.iterations == 1000 and cfg.densify.stop == 500 and cfg.densify.opacity_reset_interval == 100
    g = random_scene(50, seed=0)
    cams = sphere_cameras(2, 16, 16)
    with torch.no_grad():
        imgs = render(g, cams).rgb
    late = tiny_preset().with_changes(iterations=20, densify=DensifyConfig(
        start=1000, stop=1000, opacity_reset_interval=20))  # a reset due at the very last step
    t = Trainer(g, cams, imgs, late)
    before = torch.sigmoid(t.params["logit_opacities"].detach()).max()
    t.train(20)
    assert torch.sigmoid(t.params["logit_opacities"].detach()).max() > 0.5 * before


def poison_the_step(monkeypatch, trainer_module, poisoned: dict) -> None:
    """Make the trainer's steps non-finite while ``poisoned["on"]`` says so, on whichever path a
    step takes: "gradient" (a finite loss whose gradient is NaN), "loss" (a NaN loss), None."""
    def loss_with_nan(image, target, weight, _real=trainer_module.photometric_loss):
        loss = _real(image, target, weight)
        if poisoned["on"] == "gradient":  # 0 * d sqrt(0) = NaN
            return loss + 0 * (image.sum() * 0).sqrt()
        return loss * float("nan") if poisoned["on"] else loss

    def fused_with_nan(*args, _real=trainer_module.fused_step_gradients):
        step = _real(*args)
        if poisoned["on"] == "gradient":
            step.grads["means"][0, 0] = float("nan")
        elif poisoned["on"]:
            step.loss = float("nan")
        return step

    monkeypatch.setattr(trainer_module, "photometric_loss", loss_with_nan)
    monkeypatch.setattr(trainer_module, "fused_step_gradients", fused_with_nan)


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "autograd"])
def test_a_non_finite_step_is_skipped_saved_counted_and_fails_past_the_limit(tmp_path, monkeypatch,
                                                                              fused):
    import pipeline.fit.trainer as trainer_module
    from pipeline.splat.compiled import fused_paths
    with fused_paths(fused):
        _non_finite_steps_are_skipped(tmp_path, monkeypatch, trainer_module)


def _non_finite_steps_are_skipped(tmp_path, monkeypatch, trainer_module):
    g = random_scene(50, seed=0)
    cams = sphere_cameras(2, 16, 16)
    with torch.no_grad():
        imgs = render(g, cams).rgb
    t = Trainer(g, cams, imgs, tiny_preset(), nonfinite_dir=tmp_path)
    t.train_step()
    poisoned = {"on": "gradient"}
    poison_the_step(monkeypatch, trainer_module, poisoned)
    before = {k: v.detach().clone() for k, v in t.params.items()}
    t.train_step()
    assert t.nonfinite_steps == 1
    for name, value in t.params.items():
        assert torch.equal(value.detach(), before[name]), name
    poisoned["on"] = "loss"
    t.train_step()
    assert t.nonfinite_steps == 2
    for name, value in t.params.items():  # the NaN never reached the parameters
        assert torch.equal(value.detach(), before[name]), name
    case = torch.load(tmp_path / "nonfinite_step000003.pt", weights_only=False)
    assert {"gaussians", "viewmats", "Ks", "width", "height", "step", "view"} <= set(case)
    assert case["step"] == 3 and torch.equal(case["gaussians"]["means"], before["means"])
    assert t.state_dict()["nonfinite_steps"] == 2  # checkpointed with the trainer
    poisoned["on"] = None
    t.train_step()  # training goes on
    assert all(bool(torch.isfinite(v).all()) for v in t.params.values())
    poisoned["on"] = "loss"
    with pytest.raises(trainer_module.NonFiniteTraining, match=r"step \d+ \(view \d\).*nonfinite_step"):
        for _ in range(trainer_module.NONFINITE_STEP_LIMIT + 1):
            t.train_step()


def _params_and_adam(means, log_scales, quats, logits):
    """A parameter dict with one named Adam group each, and non-zero Adam moments per row."""
    n = means.shape[0]
    params = {"means": means, "log_scales": log_scales, "quats": quats, "logit_opacities": logits,
              "sh0": torch.zeros(n, 1, 3), "shN": torch.zeros(n, 3, 3)}
    params = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    opt = torch.optim.Adam([{"params": [p], "lr": 1e-3, "name": k} for k, p in params.items()])
    for k, p in params.items():  # moments that identify their row: exp_avg = row index + 1
        rows = torch.arange(1, n + 1, dtype=p.dtype).reshape(-1, *[1] * (p.ndim - 1)).expand_as(p)
        opt.state[p] = {"step": torch.tensor(1.0), "exp_avg": rows.clone(), "exp_avg_sq": rows.clone()}
    return params, opt


def test_clone_and_split_keep_moments_of_kept_rows_and_zero_new_ones():
    """Row 0 small (cloned), row 1 big (split into 2), row 2 idle: kept rows keep their Adam
    moments, new rows start at zero, and split parents are replaced by their children."""
    means = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    log_scales = torch.log(torch.tensor([[0.001] * 3, [0.5, 0.1, 0.1], [0.001] * 3]))
    quats = torch.tensor([[1.0, 0, 0, 0]] * 3)
    params, opt = _params_and_adam(means, log_scales, quats, torch.zeros(3))
    stats = DensifyStats(torch.tensor([1.0, 1.0, 0.0]), torch.ones(3), torch.zeros(3))
    cfg = DensifyConfig(min_opacity=0.0, grad_threshold=0.5, percent_dense=0.01, split_count=2)
    out = densify_and_prune(params, opt, stats, cfg, extent=1.0, prune_large=False,
                            generator=torch.Generator().manual_seed(0))
    # rows: kept originals 0 and 2, then the clone of 0, then the two children of 1
    assert out["means"].shape[0] == 5
    assert torch.equal(out["means"][:2], means[[0, 2]]) and torch.equal(out["means"][2], means[0])
    exp_avg = opt.state[out["means"]]["exp_avg"][:, 0]
    assert exp_avg.tolist() == [1.0, 3.0, 0.0, 0.0, 0.0]  # kept rows 0 and 2 keep theirs
    children = out["log_scales"][3:]
    torch.testing.assert_close(children, log_scales[1].expand(2, 3) - math.log(1.6))
    for group in opt.param_groups:
        assert group["params"][0] is out[group["name"]]


def test_split_children_are_drawn_from_the_parent_gaussian():
    """Many children of one rotated, anisotropic parent: their positions have the parent's mean
    and covariance R S^2 R^T (rotation from scipy, not from the code under test)."""
    from scipy.spatial.transform import Rotation
    q = torch.tensor([[0.8, 0.3, -0.4, 0.33]])
    scales = torch.tensor([[0.4, 0.1, 0.05]])
    params, opt = _params_and_adam(torch.tensor([[1.0, -2.0, 0.5]]), torch.log(scales), q, torch.zeros(1))
    k = 4000
    cfg = DensifyConfig(min_opacity=0.0, grad_threshold=0.5, split_count=k, max_gaussians=None)
    stats = DensifyStats(torch.ones(1), torch.ones(1), torch.zeros(1))
    out = densify_and_prune(params, opt, stats, cfg, extent=1.0, prune_large=False,
                            generator=torch.Generator().manual_seed(1))
    pts = out["means"].detach().double()
    assert pts.shape[0] == k
    r = torch.from_numpy(Rotation.from_quat((q[0, [1, 2, 3, 0]] / q.norm()).numpy()).as_matrix())
    cov = r @ torch.diag(scales[0].double() ** 2) @ r.T
    torch.testing.assert_close(pts.mean(0), torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64),
                               rtol=0, atol=0.02)
    torch.testing.assert_close(torch.cov(pts.T), cov, rtol=0, atol=0.012)


def test_both_prune_rules():
    """Transparent Gaussians always go; too large ones (screen radius or world scale) only after
    the first opacity reset (prune_large)."""
    means = torch.zeros(4, 3)
    log_scales = torch.log(torch.tensor([[0.01] * 3, [0.01] * 3, [0.01] * 3, [0.5, 0.01, 0.01]]))
    logits = torch.logit(torch.tensor([0.5, 0.001, 0.5, 0.5]))
    params, opt = _params_and_adam(means, log_scales, torch.tensor([[1.0, 0, 0, 0]] * 4), logits)
    stats = DensifyStats(torch.zeros(4), torch.ones(4), torch.tensor([1.0, 1.0, 50.0, 1.0]))
    cfg = DensifyConfig(min_opacity=0.005, max_screen_radius=20.0, max_world_scale=0.1)
    kept = densify_and_prune(params, opt, stats, cfg, extent=1.0, prune_large=False)
    assert kept["logit_opacities"].shape[0] == 3  # only the transparent one (row 1)
    params, opt = _params_and_adam(means, log_scales, torch.tensor([[1.0, 0, 0, 0]] * 4), logits)
    kept = densify_and_prune(params, opt, stats, cfg, extent=1.0, prune_large=True)
    assert kept["means"].shape[0] == 1  # row 2 (radius 50 px) and row 3 (scale 0.5 > 0.1) go too
    assert opt.state[kept["means"]]["exp_avg"][0, 0] == 1.0  # the survivor is row 0


F64 = torch.float64


def _f64_params(means, log_scales, logits, moments=True):
    """Float64 parameters with identity rotations; one named Adam group each, with (or without:
    before the first step) per-row moments exp_avg = row + 1."""
    n = means.shape[0]
    params = {"means": means, "log_scales": log_scales, "quats": torch.tensor([[1.0, 0, 0, 0]] * n, dtype=F64),
              "logit_opacities": logits, "sh0": torch.zeros(n, 1, 3, dtype=F64),
              "shN": torch.zeros(n, 3, 3, dtype=F64)}
    params = {k: v.to(F64).clone().requires_grad_(True) for k, v in params.items()}
    opt = torch.optim.Adam([{"params": [p], "lr": 1e-3, "name": k} for k, p in params.items()])
    if moments:
        for p in params.values():
            rows = torch.arange(1, n + 1, dtype=F64).reshape(-1, *[1] * (p.ndim - 1)).expand_as(p)
            opt.state[p] = {"step": torch.tensor(1.0), "exp_avg": rows.clone(), "exp_avg_sq": rows.clone()}
    return params, opt


def test_stats_accumulate_ndc_gradient_norms_of_seen_gaussians_only():
    """Per update: |grad * (W/2, H/2)| for Gaussians with radius > 0, a count per update; the mean
    divides by the count (0 for never-seen Gaussians)."""
    stats = DensifyStats.zeros(3, torch.zeros(1, dtype=F64))
    grad = torch.tensor([[1.0, 2.0], [3.0, 4.0], [0.5, 0.5]], dtype=F64)
    radii = torch.tensor([0, 1, 3])
    stats.update(grad, radii, width=40, height=20)  # NDC scale (20, 10)
    expected = torch.tensor([0.0, math.hypot(60, 40), math.hypot(10, 5)], dtype=F64)
    torch.testing.assert_close(stats.grad_sum, expected, rtol=1e-15, atol=0)
    assert stats.count.tolist() == [0, 1, 1] and stats.max_radii.tolist() == [0, 1, 3]
    torch.testing.assert_close(stats.mean_grads(), expected, rtol=1e-15, atol=0)  # count 1
    stats.update(grad, radii, width=40, height=20)
    assert stats.count.tolist() == [0, 2, 2]
    torch.testing.assert_close(stats.mean_grads(), expected, rtol=1e-15, atol=0)  # sum 2x over count 2


def test_the_cap_takes_the_highest_gradients_first_and_fills_the_room_exactly():
    from pipeline.fit.densify import _select_under_cap
    grads = torch.tensor([0.1, 0.5, 0.3, 0.9])
    every = torch.ones(4, dtype=torch.bool)
    ones = torch.ones(4, dtype=torch.long)
    assert _select_under_cap(grads, every, ones, 2).tolist() == [False, True, False, True]
    assert _select_under_cap(grads, every, ones, 0).tolist() == [False] * 4
    assert _select_under_cap(grads, every, ones, -3).tolist() == [False] * 4
    # in gradient order 3, 1, 2, 0 the cumulative cost is 2, 3, 4, 5: only row 3 fits in 2
    assert _select_under_cap(grads, every, torch.tensor([1, 1, 1, 2]), 2).tolist() == [False, False, False, True]
    assert _select_under_cap(grads, every, ones, None).tolist() == [True] * 4


def test_clone_split_and_cap_thresholds_at_their_boundaries_with_a_scene_extent():
    """extent 2, percent_dense 0.25: a max scale of exactly 0.5 clones, 0.3 clones (it would split
    if the threshold were divided by the extent), 0.6 splits; a gradient exactly at the threshold
    densifies; a split into 3 costs 2 rows, a clone 1, and a room of exactly that fits."""
    scale = torch.tensor([0.5, 0.3, 0.6, 0.01], dtype=F64)
    assert torch.exp(torch.log(scale[0])).item() == 0.5  # the boundary is exact
    log_scales = torch.log(torch.stack([scale, torch.full_like(scale, 0.01), torch.full_like(scale, 0.01)], 1))
    means = torch.arange(12, dtype=F64).reshape(4, 3)
    cfg = DensifyConfig(min_opacity=0.0, grad_threshold=0.5, percent_dense=0.25, split_count=3, max_gaussians=None)

    def run(grad_sum, max_gaussians=None):
        params, opt = _f64_params(means, log_scales, torch.zeros(4))
        stats = DensifyStats(torch.tensor(grad_sum, dtype=F64), torch.ones(4, dtype=F64), torch.zeros(4, dtype=F64))
        c = DensifyConfig(**{**cfg.__dict__, "max_gaussians": max_gaussians})
        return densify_and_prune(params, opt, stats, c, extent=2.0, prune_large=False,
                                 generator=torch.Generator().manual_seed(0))["means"].detach()
    out = run([0.5, 0.5, 0.5, 0.4])  # rows 0-2 at the threshold, row 3 under it
    # kept: 0, 1, 3 (row 2 is split away); clones of 0 and 1; three children of 2
    assert out.shape[0] == 3 + 2 + 3
    assert torch.equal(out[:5], means[[0, 1, 3, 0, 1]])
    assert run([0.0, 0.0, 0.5, 0.0], max_gaussians=4 + 2).shape[0] == 4 - 1 + 3  # split fits exactly
    assert run([0.0, 0.0, 0.5, 0.0], max_gaussians=4 + 1).shape[0] == 4  # it does not fit
    assert run([0.0, 0.6, 0.0, 0.0], max_gaussians=4 + 1).shape[0] == 5  # a clone fits in 1


def test_split_children_are_the_parent_mean_plus_rotated_scaled_draws_from_the_generator():
    """Children = mean + R (std * z) with z the generator's standard normal draws in the
    parameters' dtype; R from scipy (an independent rotation)."""
    from scipy.spatial.transform import Rotation
    q = torch.tensor([[0.8, 0.3, -0.4, 0.33]], dtype=F64)
    scales = torch.tensor([[0.4, 0.1, 0.05]], dtype=F64)
    params, opt = _f64_params(torch.tensor([[1.0, -2.0, 0.5]]), torch.log(scales), torch.zeros(1))
    with torch.no_grad():
        params["quats"].copy_(q)
    cfg = DensifyConfig(min_opacity=0.0, grad_threshold=0.5, split_count=3)
    stats = DensifyStats(torch.ones(1, dtype=F64), torch.ones(1, dtype=F64), torch.zeros(1, dtype=F64))
    torch.manual_seed(123)  # the global generator must not matter
    out = densify_and_prune(params, opt, stats, cfg, extent=1.0, prune_large=False,
                            generator=torch.Generator().manual_seed(7))["means"].detach()
    z = torch.randn((3, 3), generator=torch.Generator().manual_seed(7), dtype=F64) * scales
    r = torch.from_numpy(Rotation.from_quat((q[0, [1, 2, 3, 0]] / q.norm()).numpy()).as_matrix())
    torch.testing.assert_close(out, torch.tensor([1.0, -2.0, 0.5], dtype=F64) + z @ r.T, rtol=1e-12, atol=1e-14)


def test_prune_limits_are_strict_and_scale_with_the_extent():
    """Opacity exactly at min_opacity, a screen radius exactly at the limit and a world scale
    exactly at max_world_scale * extent all stay; above them they go."""
    logits = torch.tensor([-3.0, -3.0 - 1e-9, 0.0, 0.0, 0.0, 0.0], dtype=F64)
    limit = 0.1 * 2.0
    world = torch.tensor([0.01, 0.01, 0.01, 0.01, limit, 0.15], dtype=F64)
    assert torch.exp(torch.log(world[4])).item() == limit  # the boundary is exact
    log_scales = torch.log(world)[:, None].expand(6, 3).clone()
    radii = torch.tensor([1.0, 1.0, 20.0, 20.5, 1.0, 1.0], dtype=F64)
    params, opt = _f64_params(torch.zeros(6, 3), log_scales, logits)
    cfg = DensifyConfig(min_opacity=float(torch.sigmoid(torch.tensor(-3.0, dtype=F64))), max_screen_radius=20.0,
                        max_world_scale=0.1, grad_threshold=1e9)
    stats = DensifyStats(torch.zeros(6, dtype=F64), torch.ones(6, dtype=F64), radii)
    kept = densify_and_prune(params, opt, stats, cfg, extent=2.0, prune_large=True)
    rows = opt.state[kept["means"]]["exp_avg"][:, 0].tolist()  # moments name their original rows
    assert rows == [1.0, 3.0, 5.0, 6.0]  # row 1 (opacity below), row 3 (radius 20.5 > 20) go


def test_pruning_never_removes_the_whole_scene():
    logits = torch.tensor([-9.0, -7.0, -8.0], dtype=F64)  # all below min_opacity
    params, opt = _f64_params(torch.zeros(3, 3), torch.full((3, 3), -4.0, dtype=F64), logits)
    stats = DensifyStats(torch.zeros(3, dtype=F64), torch.ones(3, dtype=F64), torch.zeros(3, dtype=F64))
    kept = densify_and_prune(params, opt, stats, DensifyConfig(), extent=1.0, prune_large=False)
    assert kept["logit_opacities"].tolist() == [-7.0]  # the most opaque one stays
    assert opt.state[kept["means"]]["exp_avg"][:, 0].tolist() == [2.0]


def test_opacity_reset_zeroes_only_the_opacity_moments_and_works_before_any_step():
    params, opt = _f64_params(torch.zeros(2, 3), torch.full((2, 3), -4.0, dtype=F64), torch.tensor([2.0, -6.0]))
    out = reset_opacity(params, opt, 0.01)
    torch.testing.assert_close(out["logit_opacities"].detach(),
                               torch.tensor([math.log(0.01 / 0.99), -6.0], dtype=F64), rtol=1e-12, atol=0)
    state = opt.state[out["logit_opacities"]]
    assert state["step"].item() == 1.0  # the state is kept, its moments zeroed
    assert state["exp_avg"].abs().sum() == 0 and state["exp_avg_sq"].abs().sum() == 0
    assert set(state) == {"step", "exp_avg", "exp_avg_sq"}
    assert opt.state[out["means"]]["exp_avg"][:, 0].tolist() == [1.0, 2.0]  # others untouched
    fresh, opt = _f64_params(torch.zeros(2, 3), torch.full((2, 3), -4.0, dtype=F64), torch.zeros(2), moments=False)
    reset_opacity(fresh, opt, 0.01)  # no Adam state yet: nothing to zero, no error
    stats = DensifyStats(torch.ones(2, dtype=F64), torch.ones(2, dtype=F64), torch.zeros(2, dtype=F64))
    densify_and_prune(fresh, opt, stats, DensifyConfig(min_opacity=0.0), 1.0, False)  # nor here


def test_presets_switch_big_gaussian_pruning_on_at_a_tenth_of_the_run_as_3dgs():
    """3DGS prunes big Gaussians from iteration 3000 of 30k on. Every preset, and the CPU episode
    recipe rescaled to a real scene's 5,100 iterations, keeps that tenth (it was a third at CPU
    scale, tied to the opacity-reset interval, and pruning switched on mid-episode)."""
    from pipeline.active.config import cpu_episode
    from pipeline.active.config import tiny_episode
    from pipeline.fit.config import paper_preset
    paper = paper_preset()
    assert paper.densify.prune_large_after == 3000 and paper.densify.max_world_scale == 0.1
    assert tiny_episode().fit.densify.prune_large_after > tiny_episode().fit.iterations  # off in smoke runs
    for fit in (paper, cpu_episode().fit, cpu_episode().fit.scaled_to(5100)):
        assert fit.densify.prune_large_after / fit.iterations == pytest.approx(0.1, abs=0.002)


def test_pruning_of_big_gaussians_starts_after_prune_large_after_not_the_reset_interval(monkeypatch):
    from pipeline.fit import trainer as trainer_module
    seen = []
    real = trainer_module.densify_and_prune

    def spy(params, opt, stats, cfg, extent, prune_large, generator=None):
        seen.append((int(t.step), prune_large))
        return real(params, opt, stats, cfg, extent, prune_large, generator)
    monkeypatch.setattr(trainer_module, "densify_and_prune", spy)
    g = random_scene(40, seed=0)
    cams = sphere_cameras(2, 16, 16)
    with torch.no_grad():
        imgs = render(g, cams).rgb
    cfg = tiny_preset().with_changes(iterations=40, densify=DensifyConfig(
        start=1, stop=40, interval=5, prune_large_after=12, opacity_reset_interval=30))
    t = Trainer(g, cams, imgs, cfg)
    t.train(40)
    assert seen == [(s, s > 12) for s in range(5, 40, 5)]


def test_the_first_iterations_of_a_recipe_keep_its_schedules():
    """The sparsification fit: the paper recipe's first 2,000 iterations densify every 100 from
    500, reset no opacity, raise the SH degree every 1,000 and decay the lr over 30k."""
    from pipeline.active.uncertainty import sparsification_fit
    from pipeline.fit.config import paper_preset
    fit = sparsification_fit(paper_preset(), 2000, seed=3)
    d = fit.densify
    assert (fit.iterations, fit.seed, fit.sh_degree_interval, fit.lr_decay_iterations) == (2000, 3, 1000, 30_000)
    assert (d.start, d.interval, d.opacity_reset_interval, d.prune_large_after) == (500, 100, 3000, 3000)
    g = random_scene(20, seed=0)
    cams = sphere_cameras(2, 16, 16)
    with torch.no_grad():
        imgs = render(g, cams).rgb
    t = Trainer(g, cams, imgs, fit)
    t.step = 1000  # the means' lr at 1000 of a 30k decay, not of a 2k one
    lr = fit.lr
    expected = t.extent * math.exp((1 - 1000 / 30_000) * math.log(lr.means_init) + 1000 / 30_000 * math.log(lr.means_final))
    assert t._means_lr() == pytest.approx(expected, rel=1e-12)
    assert sparsification_fit(fit, 5000, seed=3) == fit  # a shorter recipe is used as it is


def test_a_steps_psnr_is_that_of_its_render_before_the_update_and_nan_when_skipped(monkeypatch):
    import pipeline.fit.trainer as trainer_module
    g = random_scene(80, seed=2)
    cams = sphere_cameras(3, 16, 16)
    with torch.no_grad():
        imgs = render(random_scene(80, seed=3), cams).rgb
    t = Trainer(g, cams, imgs, tiny_preset())
    for _ in range(3):
        before = t.gaussians.clone()
        info = t.train_step()
        view = next(i for i in range(len(cams)) if torch.equal(imgs[i], info.target))
        with torch.no_grad():
            rendered = render(before, cams[view], t.background, t.active_sh_degree).rgb[0]
            expected = psnr(rendered, imgs[view])
        assert info.psnr == pytest.approx(float(expected), abs=1e-4)
        assert all(p.grad is not None for p in t.params.values())
    poison_the_step(monkeypatch, trainer_module, {"on": "loss"})
    skipped = t.train_step()
    assert math.isnan(skipped.psnr) and math.isnan(skipped.loss)


def _image_pair(dtype, seed=0, shape=(13, 17, 3)):
    gen = torch.Generator().manual_seed(seed)
    img = torch.rand(shape, generator=gen, dtype=dtype)
    ref = (img + 0.3 * torch.rand(shape, generator=gen, dtype=dtype)).clamp(0, 1)
    ref[0, 0] = img[0, 0]  # equal pixels: the L1 part's subgradient is 0 there, as torch's
    return img, ref


@pytest.mark.parametrize("weight", [0.2, 0.0, 1.0])
def test_compiled_loss_is_the_torch_loss_value_and_gradient(weight):
    from pipeline.fit.losses import photometric_loss_compiled
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 2e-6)):
        img, ref = _image_pair(dtype)
        a = img.clone().requires_grad_()
        b = img.clone().requires_grad_()
        want = photometric_loss(a, ref, weight)
        got = photometric_loss_compiled(b, ref, weight)
        want.backward()
        got.backward()
        assert got.dtype == dtype and got.shape == ()
        assert abs(float(got) - float(want)) < tol, dtype
        assert b.grad.dtype == dtype
        assert float((b.grad - a.grad).norm() / a.grad.norm()) < tol * 10, dtype


def test_compiled_loss_gradient_against_finite_differences():
    """Independent of the torch loss: central differences of the compiled value itself."""
    from pipeline.fit.losses import photometric_loss_compiled
    img, ref = _image_pair(torch.float64, seed=1, shape=(9, 11, 3))
    img = img.clamp(0.05, 0.95)
    ref = (ref + 0.02).clamp(0, 1)  # no pixel at the L1 kink
    x = img.clone().requires_grad_()
    photometric_loss_compiled(x, ref, 0.2).backward()
    h = 1e-6
    gen = torch.Generator().manual_seed(2)
    for flat in torch.randint(0, img.numel(), (12,), generator=gen).tolist():
        up, down = img.clone().reshape(-1), img.clone().reshape(-1)
        up[flat] += h
        down[flat] -= h
        numeric = (photometric_loss_compiled(up.reshape(img.shape), ref, 0.2)
                   - photometric_loss_compiled(down.reshape(img.shape), ref, 0.2)) / (2 * h)
        assert abs(float(numeric) - float(x.grad.reshape(-1)[flat])) < 1e-7


def test_compiled_loss_refuses_what_it_cannot_compute():
    from pipeline.fit.losses import photometric_loss_compiled
    img, ref = _image_pair(torch.float32)
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        photometric_loss_compiled(img[None], ref[None])
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        photometric_loss_compiled(img, ref[:-1])


@pytest.mark.parametrize("workers", [2, 3])
def test_compiled_loss_is_the_same_to_the_bit_on_any_number_of_threads(workers):
    """The window's passes run plane by plane on the kernels' threads: value and gradient must
    not depend on how many there are (a plane skipped or blurred twice by a worker would)."""
    from pipeline.fit import loss_kernels
    img, ref = _image_pair(torch.float32, seed=3, shape=(23, 31, 3))
    taps = loss_kernels.gaussian_taps(11, 1.5)
    one = loss_kernels.photometric_value_and_grad(img.numpy(), ref.numpy(), 0.2, taps, 1)
    many = loss_kernels.photometric_value_and_grad(img.numpy(), ref.numpy(), 0.2, taps, workers)
    assert one[0] == many[0]
    assert (one[1] == many[1]).all()
