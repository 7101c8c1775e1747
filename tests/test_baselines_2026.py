"""The 2026 baselines by hand: WarpRF's backward warp and score, NBV-Gym's FisherRF variant."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from pipeline.acquisition import SelectionContext, make_strategy
from pipeline.acquisition.fisherrf_nbvgym import depth_weighted_map, positive_mean
from pipeline.acquisition.warprf import source_pixels, warp_into
from pipeline.cameras import Cameras, intrinsics_from_fov, look_at
from pipeline.splat import Gaussians, RenderSettings, render
from pipeline.splat.scenes import random_scene

SETTINGS = RenderSettings()


def cams_looking(eyes, targets, size=24, fov=0.9):
    eyes, targets = torch.tensor(eyes), torch.tensor(targets)
    vm = look_at(eyes.double(), targets.double(), torch.tensor([0, 0, 1.0], dtype=torch.float64))
    return Cameras(vm.float(), intrinsics_from_fov(fov, size, size, len(eyes)), size, size)


def translated(offset, focal=20.0, width=16, height=10):
    """A camera looking along +z with its centre at ``offset`` (no rotation)."""
    vm = torch.eye(4, dtype=torch.float64)[None].clone()
    vm[0, :3, 3] = -torch.tensor(offset, dtype=torch.float64)
    k = torch.tensor([[[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]]], dtype=torch.float64)
    return Cameras(vm, k, width, height)


# -- WarpRF ---------------------------------------------------------------------------------------

def test_a_sideways_step_shifts_a_plane_by_focal_times_baseline_over_depth():
    """Target at the origin, source one baseline b to the right, a plane at depth d: the target's
    pixel u lands on the source's u - f b / d. A ramp in u is sampled exactly by bilinear
    interpolation, so the warped ramp is the ramp shifted by that many pixels."""
    f, b, d, w, h = 20.0, 0.5, 4.0, 16, 10
    target, source = translated([0, 0, 0], f, w, h), translated([b, 0, 0], f, w, h)
    depth = torch.full((h, w), d, dtype=torch.float64)
    uv = source_pixels(source, target, depth)[0]
    u = torch.arange(w, dtype=torch.float64) + 0.5
    v = torch.arange(h, dtype=torch.float64) + 0.5
    assert torch.allclose(uv[..., 0], (u - f * b / d).expand(h, w), atol=1e-12)
    assert torch.allclose(uv[..., 1], v[:, None].expand(h, w), atol=1e-12)
    ramp = (u / w + v[:, None] / h)[..., None].expand(h, w, 3)  # value = u / W + v / H
    warped = warp_into(ramp[None], source, target, depth)[0, ..., 0]
    shift = f * b / d  # 2.5 px
    inside = u - shift >= 0.5  # left of the first pixel centre the border is held
    expected = (u - shift) / w + v[:, None] / h
    assert torch.allclose(warped[:, inside], expected[:, inside], atol=1e-12)
    held = 0.5 / w + v[:, None] / h
    assert torch.allclose(warped[:, ~inside], held.expand(h, int((~inside).sum())), atol=1e-12)


def test_the_warp_lands_where_a_per_pixel_brute_force_lands():
    """Rotated cameras and a varying depth: each pixel lifted, moved and projected one at a time
    with 4x4 inverses (numpy), against the batched warp."""
    target = cams_looking([[3.0, 0.4, 0.2]], [[0.0, 0.1, 0]], size=12)
    sources = cams_looking([[2.5, -1.0, 0.6], [0.5, 3.0, -0.3]], [[0.1, 0, 0.1], [0, 0, 0]], size=12)
    depth = 2.0 + torch.rand(12, 12, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    got = source_pixels(sources, target, depth)
    c2w = np.linalg.inv(target.viewmats[0].double().numpy())
    k_inv = np.linalg.inv(target.Ks[0].double().numpy())
    for s in range(2):
        w2c, k = sources.viewmats[s].double().numpy(), sources.Ks[s].double().numpy()
        for i in range(12):
            for j in range(12):
                ray = k_inv @ np.array([j + 0.5, i + 0.5, 1.0])
                point = c2w @ np.append(ray * float(depth[i, j]), 1.0)
                cam = (w2c @ point)[:3]
                pix = k @ cam
                assert got[s, i, j].numpy() == pytest.approx(pix[:2] / pix[2], abs=1e-5)  # float32 poses


def test_warprf_scores_a_taken_pose_zero_and_picks_the_least_consistent_view():
    scene = random_scene(300, seed=4, extent=0.5)
    taken = cams_looking([[3.0, 0.3, 0.2], [3.0, -0.3, -0.2]], [[0.0, 0, 0]] * 2)
    pool = cams_looking([[3.0, 0.3, 0.2], [-3.0, 0.0, 0.0], [3.0, 0.0, 0.0]], [[0.0, 0, 0]] * 3)
    ctx = SelectionContext(scene, pool, [7, 8, 9], taken, torch.ones(3), torch.Generator())
    sel = make_strategy("warprf").select(ctx)
    s = sel.scores
    assert s[7] == pytest.approx(0.0, abs=1e-4)     # a taken pose agrees with itself (float32 poses)
    assert sel.chosen == [8]                        # the far side: the renders disagree most
    assert s[8] > s[9] > s[7]                       # between two taken poses: small but not zero
    assert sel.fisher_views == 0 and sel.seconds_per_candidate > 0
    assert make_strategy("warprf").select(ctx, count=2).chosen == [8, 9]  # top-k, highest first
    costs = make_strategy("warprf").pose_scorer(ctx).cost(pool)
    assert costs.tolist() == pytest.approx([-s[7], -s[8], -s[9]], rel=1e-9, abs=1e-9)


def test_warprf_takes_the_smallest_disagreement_over_the_taken_views():
    """With a second taken view at the candidate's own pose, every pixel has a perfect match."""
    scene = random_scene(300, seed=4, extent=0.5)
    pool = cams_looking([[-3.0, 0.0, 0.0]], [[0.0, 0, 0]])
    one = cams_looking([[3.0, 0.3, 0.2]], [[0.0, 0, 0]])
    ctx = SelectionContext(scene, pool, [1], one, torch.ones(3), torch.Generator())
    alone = make_strategy("warprf").select(ctx).scores[1]
    ctx = SelectionContext(scene, pool, [1], Cameras.cat([one, pool]), torch.ones(3), torch.Generator())
    assert alone > 1.0 and make_strategy("warprf").select(ctx).scores[1] == pytest.approx(0.0, abs=1e-4)


def test_warprf_needs_a_taken_view():
    scene = random_scene(50, seed=1, extent=0.5)
    pool = cams_looking([[3.0, 0, 0]], [[0.0, 0, 0]])
    ctx = SelectionContext(scene, pool, [1], pool[[]], torch.ones(3), torch.Generator())
    with pytest.raises(ValueError, match="none is taken yet"):
        make_strategy("warprf").select(ctx)


# -- NBV-Gym's FisherRF ---------------------------------------------------------------------------

def one_blob(opacity=0.8):
    pts = torch.zeros(1, 3)
    return Gaussians.from_points(pts, torch.full_like(pts, 0.5), sh_degree=0, scale=0.3, opacity=opacity)


def test_the_map_is_hessian_times_depth_times_the_blobs_weight():
    """One Gaussian: sum_g w_pg H_g z_g = alpha_p H z, so the score is H z times the mean opacity
    over the pixels it reaches (alpha read from the plain render)."""
    scene, h = one_blob(), torch.tensor([2.5], dtype=torch.float64)
    camera = cams_looking([[3.0, 0, 0]], [[0.0, 0, 0]], size=32)
    alpha = render(scene, camera).alpha[0].double()
    reached = alpha > 0
    assert 0 < int(reached.sum()) < 32 * 32
    expected = 2.5 * 3.0 * float(alpha[reached].mean())
    assert positive_mean(depth_weighted_map(scene, camera, h, SETTINGS)) == pytest.approx(expected, rel=1e-5)


def test_twice_as_far_with_twice_the_focal_length_scores_twice():
    """Same footprint (the projection scales with f / z), twice the depth: the depth weight alone."""
    scene, h = one_blob(), torch.tensor([1.0], dtype=torch.float64)
    near = cams_looking([[3.0, 0, 0]], [[0.0, 0, 0]], size=32, fov=0.9)
    far_vm = look_at(torch.tensor([[6.0, 0, 0]]).double(), torch.zeros(1, 3).double(),
                     torch.tensor([0, 0, 1.0], dtype=torch.float64)).float()
    k = near.Ks.clone()
    k[:, 0, 0] *= 2
    k[:, 1, 1] *= 2
    far = Cameras(far_vm, k, 32, 32)
    a = positive_mean(depth_weighted_map(scene, near, h, SETTINGS))
    b = positive_mean(depth_weighted_map(scene, far, h, SETTINGS))
    assert b == pytest.approx(2 * a, rel=1e-4)


def test_nbvgym_fisherrf_picks_the_view_of_the_most_observed_gaussians_where_fisherrf_does_not():
    """Two clusters; the taken views see only cluster A. The variant's map grows with the summed
    training Hessian, so it looks at A again; FisherRF's information gain looks at B, unseen."""
    a = random_scene(120, seed=2, extent=0.3)
    b = random_scene(120, seed=3, extent=0.3)
    b = dataclasses.replace(b, means=b.means + torch.tensor([0.0, 6.0, 0.0]))
    scene = Gaussians.cat([a, b])
    taken = cams_looking([[3.0, 0.3, 0.2], [3.0, -0.3, -0.2]], [[0.0, 0, 0]] * 2)
    pool = cams_looking([[3.0, 0.0, 0.0], [3.0, 6.0, 0.0]], [[0.0, 0, 0], [0.0, 6.0, 0.0]])
    ctx = SelectionContext(scene, pool, [4, 5], taken, torch.ones(3), torch.Generator())
    nbv = make_strategy("fisherrf_nbvgym").select(ctx)
    assert nbv.chosen == [4] and nbv.scores[5] == 0.0  # B has no training Hessian at all
    assert nbv.fisher_views == 2 and nbv.fisher_seconds > 0
    assert make_strategy("fisherrf").select(ctx).chosen == [5]
    assert not math.isnan(nbv.scores[4])
