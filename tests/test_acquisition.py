"""Strategies: the goal-directed story, order invariance, determinism, greedy batches."""

import pytest
import torch

from pipeline.acquisition import SelectionContext, make_strategy
from pipeline.data.sampling import reduce_pool
from pipeline.cameras import Cameras, intrinsics_from_fov, look_at
from pipeline.splat.scenes import random_scene, sphere_cameras


def cams_looking(eyes, targets, size=24):
    eyes, targets = torch.tensor(eyes), torch.tensor(targets)
    vm = look_at(eyes.double(), targets.double(), torch.tensor([0, 0, 1.0], dtype=torch.float64))
    return Cameras(vm.float(), intrinsics_from_fov(0.9, size, size, len(eyes)), size, size)


def test_goal_aligned_view_beats_globally_informative_view_only_under_gopre():
    # cluster A (the goal) around (0, 2, 0), a larger cluster B around (0, -2, 0)
    a = random_scene(60, seed=1, extent=0.4)
    b = random_scene(240, seed=2, extent=0.4)
    a = a.replace(means=a.means + torch.tensor([0.0, 2.0, 0.0]))
    b = b.replace(means=b.means + torch.tensor([0.0, -2.0, 0.0]))
    from pipeline.splat import Gaussians
    scene = Gaussians.cat([a, b])
    pool = cams_looking([[3.0, 2.0, 0.0], [2.0, -2.0, 0.0]], [[0.0, 2.0, 0.0], [0.0, -2.0, 0.0]])
    taken = cams_looking([[0.0, 0.0, 6.0]], [[0.0, 0.0, 0.0]])  # a far overview of both
    probes = cams_looking([[3.0, 2.8, 0.5], [3.0, 1.2, -0.5], [2.8, 2.0, 1.0]], [[0.0, 2.0, 0.0]] * 3)
    ctx = SelectionContext(scene, pool, [0, 1], taken, torch.ones(3), torch.Generator().manual_seed(0),
                           probes)
    goal = make_strategy("gopre").select(ctx)
    identity = make_strategy("gopre", goal="identity").select(ctx)
    assert goal.chosen == [0]      # sees the goal region
    assert identity.chosen == [1]  # sees more of the scene, nothing of the goal


@pytest.fixture(scope="module")
def ctx_parts():
    g = random_scene(1500, seed=0)
    pool = sphere_cameras(6, 32, 32, seed=3)
    taken = sphere_cameras(2, 32, 32, seed=4)
    probes = sphere_cameras(3, 32, 32, seed=5)
    return g, pool, taken, probes


def make_ctx(parts, perm=None, seed=0):
    g, pool, taken, probes = parts
    ids = [10 + i for i in range(len(pool))]
    if perm is not None:
        pool, ids = pool[perm], [ids[i] for i in perm]
    from pipeline.splat import render
    images = render(random_scene(1500, seed=9), taken, torch.ones(3)).rgb.detach()
    return SelectionContext(g, pool, ids, taken, torch.ones(3), torch.Generator().manual_seed(seed), probes,
                            taken_images=images)


@pytest.mark.parametrize("name,options", [("random", {}), ("coverage", {}), ("cover", {}), ("fisherrf", {}),
                                          ("popgs", {}), ("gopre", {}), ("gopre", {"score": "mc"}),
                                          ("gopre", {"score": "trace"}), ("gopre", {"goal": "identity"}),
                                          ("gopre", {"tau": 1e-3}), ("gopre", {"tau": 0.0}), ("popgs", {"variant": "block"}),
                                          ("gaussmi", {}), ("activenerf", {"steps": 10}),
                                          ("warprf", {}), ("fisherrf_nbvgym", {})])
def test_selection_is_order_invariant_and_deterministic(ctx_parts, name, options):
    strategy = make_strategy(name, **options)
    first = strategy.select(make_ctx(ctx_parts), count=2)
    again = strategy.select(make_ctx(ctx_parts), count=2)
    shuffled = strategy.select(make_ctx(ctx_parts, perm=[3, 0, 5, 1, 4, 2]), count=2)
    assert first.chosen == again.chosen == shuffled.chosen
    assert len(set(first.chosen)) == 2
    for k, v in first.scores.items():
        assert shuffled.scores[k] == pytest.approx(v, rel=1e-6)  # float32 fits: ~1e-9 noise
    assert first.round_seconds >= 0 and first.peak_rss_mb > 0
    assert 0 <= first.fisher_seconds <= first.round_seconds
    assert (first.fisher_seconds > 0) == (first.fisher_views > 0)


@pytest.mark.parametrize("name", ["random", "coverage", "cover", "fisherrf", "popgs", "gopre", "gaussmi", "activenerf",
                                  "warprf", "fisherrf_nbvgym"])
def test_a_selection_picks_one_view_unless_asked_for_more(ctx_parts, name):
    options = {"steps": 5} if name == "activenerf" else {}
    sel = make_strategy(name, **options).select(make_ctx(ctx_parts))
    assert len(sel.chosen) == 1 and set(sel.scores) == {10 + i for i in range(6)}


def test_greedy_second_pick_equals_first_pick_after_adding_the_first(ctx_parts):
    strategy = make_strategy("gopre")
    both = strategy.select(make_ctx(ctx_parts), count=2)
    g, pool, taken, probes = ctx_parts
    first_pos = both.chosen[0] - 10
    rest = [i for i in range(len(pool)) if i != first_pos]
    ctx = SelectionContext(g, pool[rest], [10 + i for i in rest], Cameras.cat([taken, pool[first_pos]]),
                           torch.ones(3), torch.Generator().manual_seed(0), probes)
    assert strategy.select(ctx).chosen == [both.chosen[1]]


def test_random_draws_fresh_each_round_unless_reseeded(ctx_parts):
    ctx = make_ctx(ctx_parts)
    fresh = make_strategy("random")
    draws = [fresh.select(ctx).chosen[0] for _ in range(8)]
    assert len(set(draws)) > 1
    same = make_strategy("random", same_seed_each_round=True)
    assert len({same.select(ctx).chosen[0] for _ in range(4)}) == 1


def test_unknown_strategy_and_bad_options():
    with pytest.raises(ValueError, match="unknown strategy"):
        make_strategy("oracle")
    with pytest.raises(ValueError, match="score"):
        make_strategy("gopre", score="entropy")
    with pytest.raises(ValueError, match="bad options"):
        make_strategy("random", temperature=2)


def test_gopre_requires_probes(ctx_parts):
    g, pool, taken, _ = ctx_parts
    ctx = SelectionContext(g, pool, list(range(len(pool))), taken, torch.ones(3), torch.Generator())
    with pytest.raises(ValueError, match="probe"):
        make_strategy("gopre").select(ctx)


def test_reduce_pool_is_seeded_and_sized():
    ids = list(range(100, 140))
    a = reduce_pool(ids, 0.25, torch.Generator().manual_seed(1))
    b = reduce_pool(list(reversed(ids)), 0.25, torch.Generator().manual_seed(1))
    assert a == b and len(a) == 10 and set(a) <= set(ids)
    assert reduce_pool(ids, 1.0, torch.Generator()) == ids  # keep everything
    assert len(reduce_pool(ids[:3], 0.1, torch.Generator())) == 1  # at least one
    for bad in (0.0, 1.5, -0.2):
        with pytest.raises(ValueError, match=r"^keep_fraction must be in \(0, 1\], got"):
            reduce_pool(ids, bad, torch.Generator())


def test_gaussmi_prefers_directions_not_yet_observed():
    from pipeline.splat import render
    g = random_scene(400, seed=5, extent=0.5)
    seen = cams_looking([[3.0, 0.2, 0.3], [3.0, -0.2, -0.2]], [[0.0, 0.0, 0.0]] * 2)
    images = render(g, seen, torch.ones(3)).rgb.detach()  # the model explains them perfectly
    pool = cams_looking([[3.0, 0.0, 0.0], [-3.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]] * 2)
    ctx = SelectionContext(g, pool, [0, 1], seen, torch.ones(3), torch.Generator(), taken_images=images)
    sel = make_strategy("gaussmi").select(ctx)
    assert sel.chosen == [1] and sel.scores[1] > sel.scores[0]


def test_activenerf_variance_grows_with_the_error_it_has_to_explain():
    from pipeline.splat import render
    g = random_scene(400, seed=6, extent=0.5)
    seen = cams_looking([[3.0, 0.2, 0.3], [0.2, 3.0, -0.2]], [[0.0, 0.0, 0.0]] * 2)
    clean = render(g, seen, torch.ones(3)).rgb.detach()
    noisy = (clean + 0.3 * torch.randn(clean.shape, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    pool = cams_looking([[2.0, 2.0, 0.5]], [[0.0, 0.0, 0.0]])
    scores = []
    for images in (clean, noisy):
        ctx = SelectionContext(g, pool, [0], seen, torch.ones(3), torch.Generator(), taken_images=images)
        scores.append(make_strategy("activenerf").select(ctx).scores[0])
    assert scores[1] > 2 * scores[0]


def test_probe_count_and_sampling():
    from pipeline.data.sampling import probe_count, sample_probes
    assert probe_count(25, 100) == 25 and probe_count(25, 10) == 10
    assert probe_count(0.125, 160) == 20 and probe_count(0.125, 3) == 1
    assert probe_count(25.0, 100) == 25 and probe_count(1.0, 10) == 1 and probe_count(1, 10) == 1  # counts
    assert probe_count(1.5, 10) == 1  # a float above 1 is a count, cut to an integer
    for bad in (0, 0.0, -3):
        with pytest.raises(ValueError, match="probe count must be >= 1 or a fraction in"):
            probe_count(bad, 10)
    a = sample_probes(list(range(50)), 5, torch.Generator().manual_seed(0))
    assert a == sample_probes(list(range(49, -1, -1)), 5, torch.Generator().manual_seed(0))
    assert len(set(a)) == 5
    with pytest.raises(ValueError, match=r"^sample_probes: the target manifold has no views to probe$"):
        sample_probes([], 5, torch.Generator())


def test_scores_are_finite_with_zero_fisher_entries():
    from pipeline.fisher.posterior import (gopre_score, monte_carlo_score, posterior_variance,
                                           trace_score, updated_variance)
    h = torch.zeros(5, dtype=torch.float64)
    f = torch.tensor([[0.0, 0, 0, 0, 0], [1.0, 0, 2.0, 0, 0]], dtype=torch.float64)
    sx = updated_variance(posterior_variance(h), f)
    for value in (gopre_score(sx, f[1], 1e-4), trace_score(sx, f[1]), monte_carlo_score(sx, f)):
        assert torch.isfinite(value).all()


@pytest.mark.parametrize("options", [{}, {"score": "mc"}, {"score": "trace"}])
def test_scores_in_small_candidate_blocks_equal_whole_pool_scores(ctx_parts, monkeypatch, options):
    from pipeline.acquisition import base
    strategy = make_strategy("gopre", **options)
    whole = strategy.select(make_ctx(ctx_parts), count=2)
    g = ctx_parts[0]
    d = len(g) * sum(v[0].numel() for v in g.params().values())  # Fisher entries per candidate
    monkeypatch.setattr(base, "SCORE_BLOCK_ELEMENTS", 2 * d)  # two candidates per block
    blocked = strategy.select(make_ctx(ctx_parts), count=2)
    assert blocked.chosen == whole.chosen
    for k, v in whole.scores.items():
        assert blocked.scores[k] == pytest.approx(v, rel=1e-12)


@pytest.mark.parametrize("name,options,match", [("gopre", {"tau": -1.0}, "tau: -1.0 is not a number >= 0"),
                                                ("gopre", {"tau": 0.0, "score": "mc"}, "tau = 0 .*logdet"),
                                                ("gopre", {"goal": "everything"}, "goal: 'everything' is not one of probes, identity"),
                                                ("popgs", {"variant": "full"}, "variant: 'full' is not one of diag, block")])
def test_bad_strategy_options_name_the_option(name, options, match):
    with pytest.raises(ValueError, match=match):
        make_strategy(name, **options)


def test_popgs_block_greedy_batch_over_two_taken_views_matches_dense_blocks():
    """The block variant against dense per-Gaussian blocks from autograd Jacobians. Two taken views
    (H is their sum, not the last one) and a greedy batch of four from seven: the first pick's
    scores and every later pick (H grown by each pick's blocks) follow the dense blocks."""
    from pipeline.splat import Gaussians, RenderSettings, render
    from pipeline.splat.scenes import orbit_cameras
    f64 = torch.float64
    g = random_scene(8, seed=4, dtype=f64, sh_degree=0)
    cams = orbit_cameras(9, 8, 8, dtype=f64, radius=2.4)
    settings = RenderSettings(tile_size=4, chunk=4)
    groups = ("means", "log_scales", "quats", "logit_opacities", "sh0")

    def block(cam):
        def fn(*sel):
            params = dict(g.params())
            params.update(dict(zip(groups, sel)))
            return render(Gaussians(**params), cam, torch.ones(3, dtype=f64), settings=settings).rgb.reshape(-1)
        js = torch.autograd.functional.jacobian(fn, tuple(g.params()[k] for k in groups))
        j = torch.cat([j.reshape(j.shape[0], 8, -1) for j in js], 2)  # [O, N, 14]
        return torch.einsum("onp,onq->npq", j, j)
    blocks = [block(cams[i]) for i in range(9)]
    lam = 1e-2
    sigma_inv = blocks[0] + blocks[1] + lam * torch.eye(14, dtype=f64)

    def gain(base, b):
        return (torch.linalg.slogdet(base + b)[1] - torch.linalg.slogdet(base)[1]).sum().item()
    pool = list(range(2, 9))
    first = {c: gain(sigma_inv, blocks[c]) for c in pool}
    picks = []
    for _ in range(4):
        best = max((c for c in pool if c not in picks), key=lambda c: gain(sigma_inv, blocks[c]))
        picks.append(best)
        sigma_inv = sigma_inv + blocks[best]
    ctx = SelectionContext(g, cams[pool], pool, cams[[0, 1]], torch.ones(3, dtype=f64),
                           torch.Generator(), settings=settings)
    sel = make_strategy("popgs", variant="block", lam=lam).select(ctx, count=4)
    for c, value in first.items():
        assert sel.scores[c] == pytest.approx(value, rel=1e-8), f"popgs block first-pick score of {c}"
    assert sel.chosen == picks


def test_a_greedy_batch_reports_the_first_picks_scores_and_counts_its_fisher_work(ctx_parts, monkeypatch):
    """Scores are those of the first pick; a batch larger than the pool takes each view once; the
    Fisher views and seconds add up over the candidate, taken and probe passes (a fake clock that
    only the acquisition module reads: each call one second later)."""
    from types import SimpleNamespace

    from pipeline.acquisition import base
    one = make_strategy("gopre").select(make_ctx(ctx_parts), count=1)
    ticks = iter(range(100, 1000))  # not from 0: a sum instead of a difference must show
    monkeypatch.setattr(base, "time", SimpleNamespace(perf_counter=lambda: float(next(ticks))))
    many = make_strategy("gopre").select(make_ctx(ctx_parts), count=10)
    assert many.scores.keys() == one.scores.keys() and many.chosen[0] == one.chosen[0]
    for view, value in one.scores.items():
        assert many.scores[view] == pytest.approx(value, rel=1e-12), view
    assert sorted(many.chosen) == [10 + i for i in range(6)]  # every view once, then the pool is empty
    assert many.fisher_views == 6 + 2 + 3  # candidates, taken, probes
    # clock: selection start 100; three Fisher passes (101->102, 103->104, 105->106); end 107
    assert many.fisher_seconds == 3.0 and many.round_seconds == 7.0 and many.seconds_per_candidate == 7.0 / 6


@pytest.mark.parametrize("name", ["gopre", "fisherrf", "popgs"])
def test_nothing_taken_yet_means_a_zero_train_fisher(ctx_parts, name):
    g, pool, _, probes = ctx_parts
    ctx = SelectionContext(g, pool[[2]], [7], pool[[]], torch.ones(3), torch.Generator(), probes)
    sel = make_strategy(name, **({"goal": "identity"} if name == "gopre" else {})).select(ctx)
    assert sel.chosen == [7] and torch.isfinite(torch.tensor(sel.scores[7]))


def test_a_selection_context_names_a_bad_pool(ctx_parts):
    g, pool, taken, _ = ctx_parts
    with pytest.raises(ValueError, match=r"^candidate_ids has 2 entries for 6 candidate cameras$"):
        SelectionContext(g, pool, [1, 2], taken, torch.ones(3), torch.Generator())
    with pytest.raises(ValueError, match=r"^candidates: the pool is empty$"):
        SelectionContext(g, pool[[]], [], taken, torch.ones(3), torch.Generator())


@pytest.mark.parametrize("name,options", [("gopre", {}), ("gopre", {"score": "mc"}), ("gopre", {"score": "trace"}),
                                          ("gopre", {"goal": "identity"}), ("gopre", {"tau": 1e-3}),
                                          ("gopre", {"tau": 0.0}), ("fisherrf", {}),
                                          ("fisherrf", {"hessian": "fisherrf_released"}), ("popgs", {}),
                                          ("popgs", {"variant": "block"})])
@pytest.mark.parametrize("taken", [2, 0])
def test_a_pose_scorer_costs_any_camera_as_select_scores_it_as_a_candidate(ctx_parts, name, options, taken):
    """What a search over poses minimises is the strategy's own score: on the pool's cameras the
    cost equals select's score (negated where the strategy maximises), the least cost is select's
    pick, and a camera off the pool gets a finite cost."""
    g, pool, taken_cams, probes = ctx_parts

    def ctx():  # the taken views' images play no part in these scores
        return SelectionContext(g, pool, [10 + i for i in range(len(pool))], taken_cams[list(range(taken))],
                                torch.ones(3), torch.Generator().manual_seed(0), probes)
    strategy = make_strategy(name, **options)
    sel = strategy.select(ctx())
    scorer = strategy.pose_scorer(ctx())
    costs = scorer.cost(pool)
    assert costs.shape == (len(pool),) and costs.dtype == torch.float64
    expected = scorer.pool_costs(sel.scores)
    for k, view in enumerate(10 + i for i in range(len(pool))):
        assert float(costs[k]) == pytest.approx(expected[view], rel=1e-6, abs=1e-9)
    assert 10 + int(torch.argmin(costs)) == sel.chosen[0]
    assert scorer.maximizes == (name != "gopre")
    off_pool = sphere_cameras(2, 32, 32, seed=11)
    assert torch.isfinite(scorer.cost(off_pool)).all()


@pytest.mark.parametrize("helper", ["sparse_fishers", "fisher_vectors"])
def test_a_fisher_pass_heard_chunk_by_chunk_gives_the_same_bits(ctx_parts, helper, monkeypatch):
    """Progress inside a selection: with a listener the Fisher of the views is computed a chunk
    at a time and each chunk heard; every view's numbers are those of the one-call pass."""
    from pipeline.acquisition import base
    monkeypatch.setattr(base, "FISHER_CHUNK", 4)
    g, pool, _, _ = ctx_parts
    quiet = make_ctx(ctx_parts)
    heard = []
    loud = make_ctx(ctx_parts)
    loud.on_fisher = lambda done, total: heard.append((done, total))
    spec = base.FisherSpec()
    one, chunked = getattr(base, helper)(quiet, pool, spec), getattr(base, helper)(loud, pool, spec)
    assert heard == [(4, 6), (6, 6)]
    assert loud.fisher_views == quiet.fisher_views == 6
    if helper == "fisher_vectors":
        assert torch.equal(one, chunked)
    else:
        assert len(one) == len(chunked) == 6
        assert all(torch.equal(a.ids, b.ids) and torch.equal(a.rows, b.rows) for a, b in zip(one, chunked))
    picks = [make_strategy("gopre").select(c, count=2).chosen for c in (quiet, loud)]
    assert picks[0] == picks[1]
