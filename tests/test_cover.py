"""COVER (NBV-Gym): the direction histogram, the per-Gaussian coverage and the pick, by hand."""

import math

import pytest
import torch

from pipeline.acquisition import SelectionContext, make_strategy
from pipeline.acquisition.cover import (coverage_values, cover_score, direction_counts,
                                        fibonacci_directions, nearest_candidates)
from pipeline.cameras import Cameras, intrinsics_from_fov, look_at
from pipeline.splat import Gaussians, RenderSettings, render
from pipeline.splat.scenes import random_scene

SETTINGS = RenderSettings()


def cams_looking(eyes, targets, size=24):
    eyes, targets = torch.tensor(eyes), torch.tensor(targets)
    vm = look_at(eyes.double(), targets.double(), torch.tensor([0, 0, 1.0], dtype=torch.float64))
    return Cameras(vm.float(), intrinsics_from_fov(0.9, size, size, len(eyes)), size, size)


def blobs(points, scale=0.3, opacity=0.8):
    pts = torch.tensor(points, dtype=torch.float32)
    return Gaussians.from_points(pts, torch.full_like(pts, 0.5), sh_degree=0, scale=scale,
                                 opacity=opacity)


def test_fibonacci_directions_are_the_lattice_written_out():
    g = 7
    bins = fibonacci_directions(g)
    golden = (1 + 5 ** 0.5) / 2
    for i in range(g):
        z = 1 - 2 * (i + 0.5) / g
        phi = 2 * math.pi * ((i / golden) % 1.0)
        r = math.sqrt(1 - z * z)
        assert bins[i].tolist() == pytest.approx([r * math.cos(phi), r * math.sin(phi), z], abs=1e-12)
    many = fibonacci_directions(128)
    assert torch.allclose(many.norm(dim=1), torch.ones(128, dtype=torch.float64))
    assert many.mean(0).norm() < 0.02  # spread over the whole sphere
    with pytest.raises(ValueError, match="bins must be >= 1"):
        fibonacci_directions(0)


def test_coverage_is_the_closeness_to_the_nearest_seen_bin():
    bins = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0]], dtype=torch.float64)
    counts = torch.tensor([[2.0, 0, 0],     # seen only from +x
                           [0.0, 0, 0],     # never seen
                           [1.0, 1.0, 0]],  # seen from +x and -x
                          dtype=torch.float64)
    looking = torch.tensor([[-1.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]], dtype=torch.float64)
    x = coverage_values(counts, looking, bins)
    # Gaussian 0 looked at along -x: only bin +x is seen, (1 + (-1)) / 2 = 0
    # Gaussian 1 was never seen: 0 whatever the direction
    # Gaussian 2 looked at along +y: both seen bins are at 90 degrees, (1 + 0) / 2
    assert x.tolist() == pytest.approx([0.0, 0.0, 0.5])
    same = coverage_values(counts, torch.tensor([[1.0, 0, 0]] * 3, dtype=torch.float64), bins)
    assert same.tolist() == pytest.approx([1.0, 0.0, 1.0])


def test_a_taken_view_counts_its_frustum_in_the_bin_of_its_direction():
    # Gaussian 0 at the origin, in view; Gaussian 1 behind the camera at x = 6
    scene = blobs([[0.0, 0, 0], [6.0, 0, 0]])
    taken = cams_looking([[3.0, 0, 0]], [[0.0, 0, 0]])
    bins = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0]], dtype=torch.float64)
    counts = direction_counts(scene, taken, bins, SETTINGS, radius_clip=0.0)
    # camera at +x looking at the origin: the direction camera -> Gaussian 0 is -x
    assert counts.tolist() == [[0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]
    twice = direction_counts(scene, taken[[0, 0]], bins, SETTINGS, radius_clip=0.0)
    assert twice[0, 1] == 2.0
    # a pixel radius limit above the Gaussian's footprint leaves it uncounted
    assert direction_counts(scene, taken, bins, SETTINGS, radius_clip=1e6).sum() == 0


def test_the_score_averages_the_composited_coverage_over_the_reached_pixels():
    scene = blobs([[0.0, 0, 0]], scale=0.2)  # covers part of the image only
    camera = cams_looking([[3.0, 0, 0]], [[0.0, 0, 0]], size=32)
    alpha = render(scene, camera).alpha[0].double()
    reached = alpha > 0
    assert 0 < int(reached.sum()) < 32 * 32
    value = 0.37
    expected = float((alpha[reached] * value).sum() / reached.sum())
    assert cover_score(scene, camera, torch.tensor([value]), SETTINGS) == pytest.approx(expected, rel=1e-5)
    away = cams_looking([[3.0, 0, 0]], [[6.0, 0, 0]])  # looks away from the only Gaussian
    assert cover_score(scene, away, torch.tensor([value]), SETTINGS) == math.inf


def test_cover_picks_the_view_from_the_direction_never_seen():
    scene = random_scene(300, seed=4, extent=0.5)
    taken = cams_looking([[3.0, 0.3, 0.2], [3.0, -0.3, -0.2]], [[0.0, 0, 0]] * 2)
    pool = cams_looking([[3.0, 0.0, 0.0], [-3.0, 0.0, 0.0], [0.0, 3.0, 0.0]], [[0.0, 0, 0]] * 3)
    ctx = SelectionContext(scene, pool, [7, 8, 9], taken, torch.ones(3), torch.Generator())
    sel = make_strategy("cover").select(ctx)
    s = sel.scores
    assert sel.chosen == [8]              # the opposite side: seen from no nearby direction
    assert s[8] < s[9] < s[7]             # the side view lies between
    assert sel.seconds_per_candidate > 0 and sel.fisher_views == 0
    batch = make_strategy("cover").select(ctx, count=2)
    assert batch.chosen == [8, 9]         # NBV-Gym's top-k (no update between picks)


def test_the_neighbourhood_option_scores_only_the_candidates_near_the_last_view():
    centres = torch.tensor([[0.0, 0, 0], [5.0, 0, 0], [1.0, 0, 0], [0.0, 2.0, 0]])
    assert nearest_candidates(centres, torch.tensor([0.9, 0, 0]), 2) == [0, 2]
    scene = random_scene(300, seed=4, extent=0.5)
    taken = cams_looking([[3.0, 0.3, 0.2], [3.0, -0.3, -0.2]], [[0.0, 0, 0]] * 2)
    pool = cams_looking([[3.0, 0.0, 0.0], [-3.0, 0.0, 0.0], [0.0, 3.0, 0.0]], [[0.0, 0, 0]] * 3)
    ctx = SelectionContext(scene, pool, [7, 8, 9], taken, torch.ones(3), torch.Generator())
    sel = make_strategy("cover", neighbours=2).select(ctx)
    assert sel.chosen == [9] and sel.scores[8] == math.inf  # the far side is out of reach


@pytest.mark.parametrize("options,match", [({"bins": 0}, "bins: 0 is not an integer >= 1"),
                                           ({"radius_clip": -1.0}, "radius_clip: -1.0 is not a number >= 0"),
                                           ({"neighbours": 0}, "neighbours: 0 is not an integer >= 1, or null")])
def test_bad_cover_options_name_the_option(options, match):
    with pytest.raises(ValueError, match=match):
        make_strategy("cover", **options)
