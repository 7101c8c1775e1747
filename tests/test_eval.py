"""Metrics against direct scikit-image calls and 3DGS's SSIM written out; sparsification and AUSE
against hand computations."""

import math

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from pipeline.eval import (LpipsMetric, ause, evaluate_views, oracle_curve, psnr_value, random_curve,
                           sparsification_curve, ssim_skimage_value, ssim_value)
from pipeline.splat.scenes import orbit_cameras, random_scene


def pair(seed=0, size=24):
    gen = torch.Generator().manual_seed(seed)
    gt = torch.rand(size, size, 3, generator=gen, dtype=torch.float64)
    pred = (gt + 0.1 * torch.randn(size, size, 3, generator=gen, dtype=torch.float64)).clamp(0, 1)
    return pred, gt


def test_psnr_matches_scikit_image_and_clamps_the_render():
    pred, gt = pair()
    assert psnr_value(pred, gt) == pytest.approx(peak_signal_noise_ratio(gt.numpy(), pred.numpy(), data_range=1))
    assert psnr_value(pred + 5.0, gt) == pytest.approx(psnr_value(torch.ones_like(pred), gt))
    assert psnr_value(gt, gt) == math.inf


def ssim_as_3dgs_writes_it(img1: np.ndarray, img2: np.ndarray) -> float:
    """3DGS's utils/loss_utils.py ``ssim`` written out in NumPy for [H, W, 3] images: an 11x11
    Gaussian window (sigma 1.5, normalised), every local statistic a window sum over the image
    padded with 5 zeros on each side, C1 = 0.01^2, C2 = 0.03^2, the map's mean over all pixels."""
    g = np.exp(-((np.arange(11) - 5) ** 2) / (2 * 1.5 ** 2))
    g /= g.sum()
    w = np.outer(g, g)
    padded = lambda a: np.pad(a, ((5, 5), (5, 5), (0, 0)))  # noqa: E731  zeros
    windows = lambda a: np.lib.stride_tricks.sliding_window_view(padded(a), (11, 11), axis=(0, 1))  # noqa: E731
    local = lambda a: np.einsum("hwcij,ij->hwc", windows(a), w)  # noqa: E731
    mu1, mu2 = local(img1), local(img2)
    s11, s22, s12 = local(img1 * img1) - mu1 ** 2, local(img2 * img2) - mu2 ** 2, local(img1 * img2) - mu1 * mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ssim_map = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1 ** 2 + mu2 ** 2 + c1) * (s11 + s22 + c2))
    return float(ssim_map.mean())


def test_ssim_is_3dgs_formula_over_the_whole_zero_padded_image():
    pred, gt = pair(1, 20)
    pred = pred[:, :17]  # not square: rows and columns must not be swapped
    gt = gt[:, :17]
    assert ssim_value(pred, gt) == pytest.approx(ssim_as_3dgs_writes_it(pred.numpy(), gt.numpy()), abs=1e-12)
    assert ssim_value(gt, gt) == pytest.approx(1.0)
    # the render is clamped, as for PSNR
    assert ssim_value(pred + 3.0, gt) == pytest.approx(ssim_value(torch.ones_like(pred), gt))


def test_the_evaluation_ssim_is_the_training_losss_ssim_in_float64():
    """ssim_value (two 1-D window passes, NumPy) against the training loss's ssim_map (the 2-D
    window by conv2d, torch) in float64: a 64 px view, one smaller than the window, a flat one."""
    from pipeline.fit.losses import ssim_map
    for h, w in ((42, 64), (7, 9), (11, 11)):
        pred, gt = pair(2, max(h, w))
        pred, gt = pred[:h, :w].contiguous(), gt[:h, :w].contiguous()
        for a in (pred, torch.full_like(pred, 0.5)):
            expected = float(ssim_map(a.clamp(0, 1).double(), gt.double()).mean())
            assert ssim_value(a, gt) == pytest.approx(expected, abs=1e-14), (h, w)


def test_the_two_ssim_conventions_differ_where_the_border_differs():
    """Errors only in the first rows: scikit-image's valid-interior mean drops the map's 5 border
    rows, where they weigh most, so it scores the pair much higher than 3DGS's full-image mean."""
    _, gt = pair(3, 32)
    pred = gt.clone()
    pred[:3] = 1 - pred[:3]
    assert ssim_skimage_value(pred, gt) > ssim_value(pred, gt) + 0.05
    assert ssim_value(pred, gt) == pytest.approx(ssim_as_3dgs_writes_it(pred.numpy(), gt.numpy()), abs=1e-12)


def test_ssim_skimage_matches_scikit_image_with_the_3dgs_window():
    pred, gt = pair(1, 32)
    direct = structural_similarity(gt.numpy(), pred.numpy(), channel_axis=-1, data_range=1.0,
                                   gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    assert ssim_skimage_value(pred, gt) == pytest.approx(direct, abs=1e-12)
    assert ssim_skimage_value(gt, gt) == pytest.approx(1.0)
    # a different window would give a different number: the settings matter
    plain = structural_similarity(gt.numpy(), pred.numpy(), channel_axis=-1, data_range=1.0)
    assert abs(plain - direct) > 1e-4


def test_metrics_reject_mismatched_images():
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        psnr_value(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))


def test_lpips_is_unavailable_not_a_number_when_it_cannot_run():
    metric = LpipsMetric()
    pred, gt = pair(2, 32)
    if metric.available:  # a machine with lpips + torchvision + weights: a real distance
        value = metric(pred, gt)
        assert value > 0 and metric(gt, gt) == pytest.approx(0, abs=1e-6)
    else:
        assert metric(pred, gt) is None
        assert "unavailable" in metric.reason


def test_evaluate_views_averages_per_view_metrics_and_records_lpips_status():
    g = random_scene(300, seed=0)
    cams = orbit_cameras(3, 24, 24)
    from pipeline.splat import render
    images = render(g, cams, torch.ones(3)).rgb.detach().clamp(0, 1)
    noisy = (images + 0.05 * torch.randn(images.shape, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    m = evaluate_views(g, cams, noisy, torch.ones(3), LpipsMetric())
    assert m.psnr == pytest.approx([psnr_value(images[i], noisy[i]) for i in range(3)])
    assert m.mean()["psnr"] == pytest.approx(np.mean(m.psnr))
    assert m.ssim == pytest.approx([ssim_as_3dgs_writes_it(render(g, cams[i], torch.ones(3)).rgb[0].clamp(0, 1)
                                                           .double().numpy(), noisy[i].double().numpy())
                                    for i in range(3)], abs=1e-6)
    assert m.ssim_skimage == pytest.approx([ssim_skimage_value(render(g, cams[i], torch.ones(3)).rgb[0], noisy[i])
                                            for i in range(3)])
    if m.lpips is None:
        assert m.mean()["lpips"] is None and "unavailable" in m.lpips_status


def test_sparsification_by_hand():
    quality = [10.0, 20.0, 30.0, 40.0]
    uncertainty = [0.1, 0.4, 0.3, 0.2]  # ranks views 1, 2, 3, 0 as most uncertain first
    fr = (0.0, 0.25, 0.5, 0.75)
    assert sparsification_curve(quality, uncertainty, fr).tolist() == [25.0, 80 / 3, 25.0, 10.0]
    assert oracle_curve(quality, fr).tolist() == [25.0, 30.0, 35.0, 40.0]
    # AUSE = trapezoid of oracle - curve = [0, 10/3, 10, 30] over steps of 0.25
    expected = 0.25 * ((0 + 10 / 3) / 2 + (10 / 3 + 10) / 2 + (10 + 30) / 2)
    assert ause(sparsification_curve(quality, uncertainty, fr), oracle_curve(quality, fr), fr) == pytest.approx(expected)


def test_oracle_has_zero_ause_and_bounds_every_ranking():
    rng = np.random.default_rng(0)
    quality = rng.normal(25, 3, size=50)
    oracle = oracle_curve(quality)
    assert ause(oracle, oracle) == 0
    for seed in range(5):
        curve = random_curve(quality, seed)
        assert (curve <= oracle + 1e-12).all() and ause(curve, oracle) >= 0
    # ranking by the true error is the oracle; ranking by the quality itself is the worst case
    assert ause(sparsification_curve(quality, -quality), oracle) == 0
    assert ause(sparsification_curve(quality, quality), oracle) > ause(random_curve(quality), oracle)


def test_sparsification_rejects_bad_input():
    with pytest.raises(ValueError, match="equal-length"):
        sparsification_curve([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="finite"):
        sparsification_curve([1.0, float("nan")], [1.0, 2.0])
