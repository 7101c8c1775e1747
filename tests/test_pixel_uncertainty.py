"""Pixel-level uncertainty metrics against small arrays worked by hand and independent routes:
loops that follow the released code line by line (AaltoML's ause, 3DGS-Uncertainty's ause_torch),
scipy's normal distribution and correlation functions, and exact averages over tie-breaks."""

import itertools
import math

import numpy as np
import pytest
import scipy.stats

from pipeline.eval.pixel_uncertainty import (AUCE_ALPHAS, MAX_FRACTIONS, START_FRACTIONS, auce, ause_max, ause_start,
                                             correlations, gaussian_nll, kept_means, random_curve, sparsification)


def test_curves_by_hand():
    error, unc = np.array([1.0, 2.0, 3.0, 4.0]), np.array([4.0, 3.0, 2.0, 1.0])  # the most uncertain are the best
    s = sparsification(error, unc, [0.0, 0.25, 0.5, 0.75])
    assert s.by_uncertainty.tolist() == [2.5, 3.0, 3.5, 4.0]
    assert s.oracle.tolist() == [2.5, 2.0, 1.5, 1.0] and s.random.tolist() == [2.5] * 4
    rmse = sparsification(error ** 2, unc, [0.0, 0.5], root=True)
    assert rmse.oracle.tolist() == pytest.approx([math.sqrt(7.5), math.sqrt(2.5)])


def test_an_uncertainty_equal_to_the_error_has_zero_ause_in_both_conventions():
    rng = np.random.default_rng(0)
    error = rng.gamma(2.0, 0.1, 5000)
    for convention in (ause_max, ause_start):
        value, s = convention(error, error)
        assert value == pytest.approx(0.0, abs=1e-12) and np.allclose(s.by_uncertainty, s.oracle)
        assert convention(error ** 2, error, root=True)[0] == pytest.approx(0.0, abs=1e-12)
        assert convention(error, 3 * error + 1)[0] == pytest.approx(0.0, abs=1e-12)  # any increasing map


def test_a_constant_uncertainty_gives_the_random_curve_exactly():
    rng = np.random.default_rng(1)
    error = rng.random(997)
    s = sparsification(error, np.full(997, 0.3))
    assert np.allclose(s.by_uncertainty, random_curve(error, MAX_FRACTIONS)) and np.allclose(s.by_uncertainty, error.mean())


def test_ties_are_taken_in_expectation_over_every_tie_break():
    error = np.array([0.5, 0.1, 0.9, 0.3, 0.7, 0.2])
    unc = np.array([1.0, 1.0, 2.0, 2.0, 2.0, 3.0])
    fractions = np.array([0.0, 0.2, 0.4, 0.6, 0.8])
    exact = []
    for perm in itertools.permutations(range(6)):  # every order among equal keys, each equally likely
        tiebreak = np.empty(6)
        tiebreak[list(perm)] = np.arange(6)
        order = np.lexsort((tiebreak, unc))
        exact.append([error[order][:max(1, int((1 - f) * 6))].mean() for f in fractions])
    assert kept_means(error, unc, fractions) == pytest.approx(np.mean(exact, axis=0), abs=1e-12)


def _aalto_ause(unc, err, root):
    """AaltoML's released ause(), line by line (sorted slices, normalised by the max of both curves)."""
    ratios = np.linspace(0, 1, 100, endpoint=False)
    n = len(err)
    err_sorted = np.sort(err)
    by_var = err[np.argsort(unc, kind="stable")]
    f = (lambda x: math.sqrt(x.mean())) if root else (lambda x: x.mean())
    oracle = np.array([f(err_sorted[:int((1 - r) * n)]) for r in ratios])
    curve = np.array([f(by_var[:int((1 - r) * n)]) for r in ratios])
    top = max(oracle.max(), curve.max())
    return np.trapezoid(curve / top - oracle / top, ratios)


def _3dgsu_ause(err, unc):
    """The 3DGS-Uncertainty code's ause_torch, line by line (zeros dropped, cumulative sums, start-normalised)."""
    keep = (err != 0) & (unc != 0)
    err, unc = err[keep], unc[keep]
    ratios = np.linspace(0, 0.999, 100)
    idx = ((1 - ratios) * len(err)).astype(int)[:-1]
    oracle = np.cumsum(np.sort(err))[idx - 1] / idx
    curve = np.cumsum(err[np.argsort(unc, kind="stable")])[idx - 1] / idx
    return np.trapezoid(curve / oracle[0] - oracle / oracle[0], ratios[:len(oracle)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_each_convention_equals_its_released_code(seed):
    rng = np.random.default_rng(seed)
    truth = rng.random(3000)
    err = np.abs(truth + rng.normal(0, 0.2, 3000))
    unc = np.abs(truth + rng.normal(0, 0.5, 3000))
    err[:50] = 0.0  # pixels with no error: 3DGS-Uncertainty drops them
    assert ause_max(err, unc)[0] == pytest.approx(_aalto_ause(unc, err, False), abs=1e-12)
    assert ause_max(err ** 2, unc, root=True)[0] == pytest.approx(_aalto_ause(unc, err ** 2, True), abs=1e-12)
    assert ause_start(err, unc)[0] == pytest.approx(_3dgsu_ause(err, unc), abs=1e-12)
    backwards = 1.0 - unc  # a map that ranks the worst pixels as the surest: its curve rises above the oracle's top
    assert ause_max(err, backwards)[0] == pytest.approx(_aalto_ause(backwards, err, False), abs=1e-12)
    assert ause_start(err, backwards)[0] == pytest.approx(_3dgsu_ause(err, backwards), abs=1e-12)
    assert ause_max(err, unc)[0] != pytest.approx(ause_start(err, unc)[0], abs=1e-3)  # two numbers, named apart
    assert len(START_FRACTIONS) == 100 and START_FRACTIONS[-1] == 0.999


def test_a_worse_ranking_has_a_larger_ause():
    rng = np.random.default_rng(3)
    err = rng.random(2000)
    good = err + rng.normal(0, 0.05, 2000)
    bad = err + rng.normal(0, 0.5, 2000)
    assert 0 < ause_max(err, good)[0] < ause_max(err, bad)[0] < ause_max(err, -err)[0]


def test_gaussian_nll_against_scipy_with_the_floor():
    rng = np.random.default_rng(4)
    mean, target = rng.random((500, 3)), rng.random((500, 3))
    sigma = rng.uniform(0.0, 0.2, 500)  # per pixel, shared by channels; many below the 0.03 floor
    expected = -scipy.stats.norm.logpdf(target, mean, np.maximum(sigma, 0.03)[:, None]).mean()
    assert gaussian_nll(mean, target, sigma) == pytest.approx(expected, rel=1e-12)
    assert gaussian_nll(mean, target, sigma, floor=1.0) == pytest.approx(
        -scipy.stats.norm.logpdf(target, mean, 1.0).mean(), rel=1e-12)


def test_auce_is_near_zero_when_calibrated_and_large_when_overconfident():
    rng = np.random.default_rng(5)
    mean = rng.random((100_000, 1))
    sigma = rng.uniform(0.01, 0.1, 100_000)
    target = mean + sigma[:, None] * rng.standard_normal((100_000, 1))
    calibrated, coverage = auce(mean, target, sigma)
    assert calibrated < 0.01
    # the coverage of each interval by scipy's own interval
    lo, hi = scipy.stats.norm.interval(1 - AUCE_ALPHAS[:, None], loc=mean[:, 0], scale=sigma)
    assert coverage == pytest.approx(((target[:, 0] >= lo) & (target[:, 0] <= hi)).mean(1), abs=1e-9)
    assert auce(mean, target, sigma / 3)[0] > 0.2 and auce(mean, target, sigma * 3)[0] > 0.2


def test_correlations_against_scipy_with_ties():
    rng = np.random.default_rng(6)
    err = rng.integers(0, 20, 400).astype(float)  # many ties
    unc = err + rng.integers(0, 10, 400)
    r, rho = correlations(unc, err)
    assert r == pytest.approx(scipy.stats.pearsonr(unc, err).statistic, rel=1e-10)
    assert rho == pytest.approx(scipy.stats.spearmanr(unc, err).statistic, rel=1e-10)
    assert math.isnan(correlations(np.ones(5), np.arange(5.0))[0])


def test_bad_inputs_name_the_problem():
    with pytest.raises(ValueError, match="equal-size"):
        sparsification([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="finite"):
        ause_max([1.0, float("nan")], [1.0, 2.0])


def test_the_final_model_record_ranks_and_calibrates_as_its_parts_say():
    """A variance equal to each channel's squared error ranks RMSE (and MAE per pixel) perfectly."""
    import torch

    from pipeline.eval.model_uncertainty import pixel_uncertainty
    gen = torch.Generator().manual_seed(0)
    truth = torch.rand(2, 12, 16, 3, generator=gen, dtype=torch.float64)
    render = (truth + 0.1 * torch.randn(2, 12, 16, 3, generator=gen, dtype=torch.float64)).clamp(0, 1)
    exact = (render - truth) ** 2
    record = pixel_uncertainty(truth, render, exact)
    assert record.views == 2 and record.ause_rmse_max == pytest.approx(0.0, abs=1e-12)
    assert record.ause_rmse_start == pytest.approx(0.0, abs=1e-12)
    assert record.pearson > 0.5 and record.spearman > 0.5
    flat = pixel_uncertainty(truth, render, torch.full_like(exact, 0.01))  # the error's own scale, no ranking
    assert flat.ause_mae_max > record.ause_mae_max and flat.spearman != flat.spearman  # constant: NaN
    with pytest.raises(ValueError, match=r"\[T, H, W, 3\] alike"):
        pixel_uncertainty(truth, render, exact[..., 0])


def test_the_kept_curves_are_the_ones_the_ause_integrates():
    """At the AUSE's own fractions the kept curves give back the record's max-norm. AUSE per error;
    an exact variance puts the RMSE curve on the oracle, a constant one every curve on random."""
    import numpy as np
    import torch

    from pipeline.eval.model_uncertainty import CURVE_FRACTIONS, pixel_uncertainty, sparsification_curves
    gen = torch.Generator().manual_seed(1)
    truth = torch.rand(2, 12, 16, 3, generator=gen, dtype=torch.float64)
    render = (truth + 0.1 * torch.randn(2, 12, 16, 3, generator=gen, dtype=torch.float64)).clamp(0, 1)
    noisy = (render - truth) ** 2 + 0.01 * torch.rand(2, 12, 16, 3, generator=gen, dtype=torch.float64)
    record = pixel_uncertainty(truth, render, noisy)
    curves = sparsification_curves(truth, render, noisy, tuple(MAX_FRACTIONS))
    for error in ("mae", "rmse", "dssim"):
        by, oracle = np.array(curves[error]["by_uncertainty"]), np.array(curves[error]["oracle"])
        top = max(by.max(), oracle.max())
        assert np.trapezoid((by - oracle) / top, MAX_FRACTIONS) == pytest.approx(getattr(record, f"ause_{error}_max"))
        assert by[0] == pytest.approx(curves[error]["random"][0])  # nothing removed: every pixel
    from pipeline.eval.model_uncertainty import final_model_uncertainty
    both = final_model_uncertainty(truth, render, noisy)  # what a job measures, the pixels read once
    assert both == (record, sparsification_curves(truth, render, noisy))
    exact = sparsification_curves(truth, render, (render - truth) ** 2)
    assert exact["fractions"] == list(CURVE_FRACTIONS) and len(exact["fractions"]) == 20
    assert exact["rmse"]["by_uncertainty"] == pytest.approx(exact["rmse"]["oracle"], rel=1e-12)
    flat = sparsification_curves(truth, render, torch.full_like(truth, 0.01))
    for error in ("mae", "rmse", "dssim"):
        assert flat[error]["by_uncertainty"] == pytest.approx(flat[error]["random"], rel=1e-9)


def test_the_camera_path_by_hand():
    import torch

    from pipeline.eval.camera_path import diameter, path_length, picked_path
    square = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    assert path_length(square) == pytest.approx(3.0) and diameter(square) == pytest.approx(math.sqrt(2))
    # 2 initial views, then picks [1,1,0] and [0,1,0]: from [1,0,0] -> [1,1,0] -> [0,1,0] = 2, over sqrt(2)
    assert picked_path(square, 2, square) == pytest.approx(2 / math.sqrt(2))
    assert picked_path(square[:2], 2, square) is None and path_length(square[:1]) == 0.0


def test_depth_errors_by_hand():
    import torch

    from pipeline.eval.depth import depth_errors
    truth = torch.tensor([[[2.0, 4.0], [float("inf"), 1.0]]])
    depth = torch.tensor([[[2.2, 3.0], [5.0, 9.0]]])
    alpha = torch.tensor([[[1.0, 0.9], [1.0, 0.1]]])  # the last pixel is transparent: not scored
    e = depth_errors(depth, alpha, truth)
    assert e.pixels == 2 and e.abs_rel == pytest.approx((0.1 + 0.25) / 2) and e.rmse == pytest.approx(math.sqrt((0.04 + 1) / 2))
    assert depth_errors(depth, torch.zeros_like(alpha), truth) is None


def test_the_generated_scenes_true_depth_is_its_silhouette_and_projects_back(tmp_path):
    """Independent of how depth_truth builds its rays: the written image's coverage (its own
    OpenGL rays, supersampled) agrees with where a depth exists, and each surface point at that depth
    projects back onto its pixel centre through the OpenCV camera."""
    import numpy as np
    import torch
    from PIL import Image

    from pipeline.data.load import load_scene
    from pipeline.data.synthetic import depth_truth, generate
    root = generate(tmp_path / "g", seed=0, size=48, n_train=2, n_test=3)
    test = load_scene(root).split("test")
    depth = depth_truth(test.cameras)
    for k, path in enumerate(test.images.paths):
        alpha = np.asarray(Image.open(path))[..., 3]
        finite = torch.isfinite(depth[k]).numpy()
        assert finite[alpha == 255].all() and not finite[alpha == 0].any()
    from pipeline.data.synthetic import _intersect_reference
    k = 0
    v, u = torch.nonzero(torch.isfinite(depth[k]), as_tuple=True)
    z = depth[k][v, u]
    kk, vm = test.cameras.Ks[k].double(), test.cameras.viewmats[k].double()
    cam = torch.stack([(u + 0.5 - kk[0, 2]) / kk[0, 0] * z, (v + 0.5 - kk[1, 2]) / kk[1, 1] * z, z], 1)
    world = (cam - vm[:3, 3]) @ vm[:3, :3]  # the surface point each pixel's depth names, in the world
    centre = -vm[:3, :3].T @ vm[:3, 3]
    towards = world - centre
    hit = _intersect_reference(centre.float().expand(len(world), 3), (towards / towards.norm(dim=1, keepdim=True)).float())
    assert torch.allclose(hit.t.double(), towards.norm(dim=1), rtol=1e-4)  # the first surface on that ray, there
    assert float(z.min()) > 2.0 and float(z.max()) < 6.0  # cameras at distance 4 from an object about the origin


def test_depth_ause_is_zero_for_an_uncertainty_that_orders_the_error_and_larger_for_a_reversed_one():
    import torch

    from pipeline.eval.depth import depth_errors
    truth = torch.full((1, 4, 5), 2.0)
    depth = truth + torch.arange(20, dtype=torch.float32).reshape(1, 4, 5) / 100  # error grows with the index
    alpha = torch.ones_like(depth)
    ordered = depth_errors(depth, alpha, truth, uncertainty=depth - truth)
    reversed_ = depth_errors(depth, alpha, truth, uncertainty=-(depth - truth))
    assert ordered.ause_abs_rel == pytest.approx(0.0, abs=1e-12)
    assert reversed_.ause_abs_rel > 0.3 and depth_errors(depth, alpha, truth).ause_abs_rel is None


def test_sparse_depth_errors_compare_each_point_with_the_pixel_it_falls_in():
    """One 4x3 view (f = 1, principal point (2, 1.5)) of a camera turned 30 degrees about y and moved:
    points are placed in its camera frame, sent to the world by the inverse pose, and each must be
    compared at floor(u), floor(v) of its projection (pixel centres at .5); points behind the camera,
    outside the image or on a transparent pixel are not scored."""
    import torch
    from scipy.spatial.transform import Rotation

    from pipeline.eval.depth import sparse_depth_errors
    rot = torch.tensor(Rotation.from_euler("y", 30, degrees=True).as_matrix(), dtype=torch.float64)
    t = torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64)
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3], vm[:3, 3] = rot, t
    k = torch.tensor([[[1.0, 0, 2.0], [0, 1.0, 1.5], [0, 0, 1]]])
    depth = (torch.arange(12, dtype=torch.float32).reshape(1, 3, 4) + 1.0)  # depth[y, x] = 4y + x + 1
    alpha = torch.ones_like(depth)
    alpha[0, 2, 3] = 0.2  # a transparent pixel
    in_camera = torch.tensor([[-2.6, -2.2, 2.0],   # (u, v) = (0.7, 0.4): pixel (0, 0), rendered 1, truth 2
                              [1.0, 0.4, 2.0],     # (2.5, 1.7): pixel (2, 1), rendered 7, truth 2
                              [1.5, 1.0, 1.0],     # (3.5, 2.5): pixel (3, 2), transparent: not scored
                              [0.0, 0.0, -1.0],    # behind the camera
                              [10.0, 0.0, 1.0]], dtype=torch.float64)  # outside the image
    world = (in_camera - t) @ rot  # rot^T (x - t), row by row
    e = sparse_depth_errors(depth, alpha, vm[None].float(), k, [world])
    assert e.pixels == 2
    assert e.abs_rel == pytest.approx((abs(1 - 2) / 2 + abs(7 - 2) / 2) / 2, rel=1e-5)
    assert e.rmse == pytest.approx(math.sqrt((1 + 25) / 2), rel=1e-5)
    score = torch.zeros_like(depth)
    score[0, 1, 2] = 1.0  # the worse point is the more uncertain one: a perfect ranking
    assert sparse_depth_errors(depth, alpha, vm[None], k, [world], score).ause_abs_rel == pytest.approx(0.0, abs=1e-12)
    assert sparse_depth_errors(depth, alpha, vm[None], k, [torch.zeros(0, 3)]) is None


def test_a_colmap_scenes_observed_points_land_on_their_keypoints_at_the_working_resolution():
    """The points each bonsai view observed, projected with the scene's own (scaled) cameras, fall
    where COLMAP measured them: the frames, the scale and the pixel convention agree."""
    import torch

    from pipeline.data.colmap import observations, observed_points
    from pipeline.data.load import load_scene
    from tests.conftest import shared_scene
    scene = load_scene(shared_scene("colmap", "bonsai"), width=200)
    test = scene.split("test")
    root = scene.info.get("undistorted", scene.root)
    names = test.names[:2]
    for name, world in zip(names, observed_points(root, names)):
        xy, xyz = observations(root, name)
        assert torch.allclose(world, xyz) and len(world) > 100
        cam = test.cameras[[test.names.index(name)]]
        c = world @ cam.viewmats[0, :3, :3].double().T + cam.viewmats[0, :3, 3].double()
        uv = c @ cam.Ks[0].double().T
        uv = uv[:, :2] / uv[:, 2:]
        scale = cam.width / scene.info["model_size"][0]
        err = (uv - xy * scale).norm(dim=1)
        assert float(err.median()) < 2.0 * scale and (c[:, 2] > 0).all()  # within two model pixels
