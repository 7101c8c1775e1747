"""The fused compiled paths (issue 27's episode speedup) against the ops they replace and against
oracles that share no code with them: the training step's one-node render, the projection
backward's skip of Gaussians without upstream gradient, the per-view Fisher diagonal kernel and
the in-place GO-PRE score."""

import pytest
import torch

from pipeline.cameras import Cameras
from pipeline.fisher.exact import FisherSpec, view_fisher
from pipeline.fisher.features import PARAM_GROUPS
from pipeline.fisher.posterior import (gopre_score, gopre_score_of_fishers, gopre_scores_sparse,
                                       posterior_variance,
                                       updated_variance)
from pipeline.fit.config import FitConfig, DensifyConfig
from pipeline.fit.losses import photometric_loss
from pipeline.fit.trainer import Trainer
from pipeline.splat import RenderSettings, compiled, render
from pipeline.splat.compiled import fused_paths
from pipeline.splat.project import project
from pipeline.splat.scenes import orbit_cameras, random_scene
from pipeline.splat.training_view import (fused_training_step, training_view_compiled,
                                          training_view_generic)
from tests.test_compiled import with_hard_cases

# the compiled kernels against their oracles, on two threads (their threaded branches) whatever the
# process's share of the cores
pytestmark = [pytest.mark.skipif(compiled.load() is None,
                                 reason=f"compiled backend unavailable: {compiled.load_error()}"),
              pytest.mark.threads(2)]

F64 = torch.float64


def rel(a, b):
    return ((a - b).norm() / b.norm().clamp_min(1e-300)).item()


def view_and_grads(fn, g, cam, background, sh_degree, backend, target):
    leaves = g.clone().requires_grad_()
    out = fn(leaves, cam, background, sh_degree, RenderSettings(backend=backend, tile_size=8))
    photometric_loss(out.image, target, 0.2).backward()
    return out, {k: v.grad for k, v in leaves.params().items()}


@pytest.mark.parametrize("dtype,sh_degree,background", [
    (F64, 3, (0.2, 0.5, 0.9)),
    (F64, 1, (0.0, 0.0, 0.0)),
    (torch.float32, 3, (1.0, 1.0, 1.0)),
])
def test_fused_training_view_equals_render_and_the_dense_oracle(dtype, sh_degree, background):
    """Image, radii, the means2d gradient and every raw gradient: the fused node against
    ``render`` on the compiled backend (the same casts: equal to rounding) and against the dense
    per-pixel oracle (no shared code), with Gaussians behind the camera, off-screen and clamped."""
    cams = orbit_cameras(2, 40, 33, dtype=dtype, radius=2.6)
    g = with_hard_cases(random_scene(300, seed=3, sh_degree=3, dtype=dtype,
                                     opacity_range=(0.3, 0.999)), cams)
    cam, bg = cams[0], torch.tensor(background, dtype=dtype)
    target = torch.rand(33, 40, 3, generator=torch.Generator().manual_seed(0), dtype=dtype)
    fused, fused_grads = view_and_grads(training_view_compiled, g, cam, bg, sh_degree, "compiled",
                                        target)
    tol = 1e-12 if dtype == F64 else 1e-6
    for backend, bound in (("compiled", tol), ("dense", 1e-10 if dtype == F64 else 1e-4)):
        ref, ref_grads = view_and_grads(training_view_generic, g, cam, bg, sh_degree, backend,
                                        target)
        assert rel(fused.image, ref.image) < bound, backend
        assert torch.equal(fused.radii, ref.radii), backend
        assert rel(fused.means2d_grad(), ref.means2d_grad()) < bound * 10, backend
        for name, grad in ref_grads.items():
            if name == "shN" and sh_degree == 0:
                continue
            assert grad.norm() > 0, name
            assert rel(fused_grads[name], grad) < bound * 10, f"{name} vs {backend}"
    assert fused.image.dtype == dtype and fused_grads["means"].dtype == dtype


def test_the_trainer_takes_the_fused_step_on_the_compiled_backend_only():
    cpu = torch.device("cpu")
    assert fused_training_step(RenderSettings(backend="compiled"), cpu)
    assert not fused_training_step(RenderSettings(backend="tiles"), cpu)
    with fused_paths(False):
        assert not fused_training_step(RenderSettings(backend="compiled"), cpu)


def test_the_fused_step_trains_without_autograd_and_the_others_with_the_torch_ops(monkeypatch):
    import pipeline.fit.trainer as trainer_module
    calls = []
    for name in ("photometric_loss", "fused_step_gradients"):
        original = getattr(trainer_module, name)
        monkeypatch.setattr(trainer_module, name,
                            lambda *a, _f=original, _n=name, **k: calls.append(_n) or _f(*a, **k))
    cams = orbit_cameras(2, 16, 12)
    images = torch.rand(2, 12, 16, 3)
    for backend, fused, want in (("compiled", True, "fused_step_gradients"),
                                 ("compiled", False, "photometric_loss"),
                                 ("tiles", True, "photometric_loss")):
        calls.clear()
        with fused_paths(fused):
            Trainer(random_scene(50, seed=0, sh_degree=0), cams, images,
                    FitConfig(iterations=2, sh_degree=0),
                    render_settings=RenderSettings(backend=backend)).train(2)
        assert calls == [want, want], (backend, fused)


@pytest.mark.parametrize("dtype,sh_degree,background", [
    (torch.float32, 3, (0.0, 0.0, 0.0)), (torch.float32, 1, (0.2, 0.5, 0.9)),
    (F64, 2, (1.0, 1.0, 1.0))])
def test_the_autograd_free_step_is_the_fused_nodes_through_autograd_to_the_bit(dtype, sh_degree,
                                                                               background):
    """``fused_step_gradients`` calls the kernels directly; through autograd the same kernels sit
    in two nodes (``training_view_compiled``, ``photometric_loss_compiled``). Loss, image, radii,
    dLoss/dmeans2d and every raw gradient must be equal to the bit (a dropped cast or a missing
    background term would not be)."""
    from pipeline.fit.fused_step import fused_step_gradients
    from pipeline.fit.losses import photometric_loss_compiled
    cams = orbit_cameras(2, 40, 31, dtype=dtype)
    g = with_hard_cases(random_scene(600, seed=5, sh_degree=3, dtype=dtype), cams)
    bg = torch.tensor(background, dtype=dtype)
    target = torch.rand(31, 40, 3, dtype=dtype, generator=torch.Generator().manual_seed(0))
    settings = RenderSettings(backend="compiled", tile_size=8)
    leaves = g.clone().requires_grad_()
    out = training_view_compiled(leaves, cams[0], bg, sh_degree, settings)
    loss = photometric_loss_compiled(out.image, target, 0.3)
    loss.backward()
    step = fused_step_gradients({k: v.detach() for k, v in g.params().items()}, cams[0], bg,
                                sh_degree, settings, target, 0.3)
    assert step.loss == float(loss.detach())
    assert torch.equal(step.image, out.image.detach()) and torch.equal(step.radii, out.radii)
    assert torch.equal(step.means2d_grad, out.means2d_grad())
    for name, grad in leaves.params().items():
        assert step.grads[name].dtype == dtype and torch.equal(step.grads[name], grad.grad), name
    assert (step.radii > 0).sum() > 100 and step.grads["means"].abs().sum() > 0


def test_fused_and_unfused_training_agree_through_densification():
    """60 steps with densification every 10 from step 20: the same Gaussians and parameters."""
    cams = orbit_cameras(4, 24, 20)
    with torch.no_grad():
        images = render(random_scene(400, seed=1), cams,
                        settings=RenderSettings(backend="tiles")).rgb.clamp(0, 1)
    config = FitConfig(iterations=60, sh_degree=1, sh_degree_interval=20,
                       densify=DensifyConfig(start=20, stop=50, interval=10, grad_threshold=1e-5,
                                             prune_large_after=40, opacity_reset_interval=30))
    results = []
    for fused in (False, True):
        with fused_paths(fused):
            trainer = Trainer(random_scene(150, seed=0, sh_degree=1), cams, images, config,
                              render_settings=RenderSettings(backend="compiled"))
            trainer.train(60)
        results.append(trainer.gaussians)
    unfused, fused = results
    assert len(unfused) == len(fused) != 150  # densification changed the count, equally
    for name in PARAM_GROUPS:
        assert rel(getattr(fused, name), getattr(unfused, name)) < 1e-5, name


@pytest.mark.parametrize("output", ["means2d", "conics", "depths", "colors", "opacities"])
def test_projection_backward_of_each_upstream_alone(output):
    """The compiled backward skips a Gaussian only when every upstream gradient is zero: one
    output's gradient at a time (the others zero) must still reach the parameters as autograd
    through the torch projection says."""
    cams = orbit_cameras(1, 40, 30, dtype=F64, radius=2.5)
    g = with_hard_cases(random_scene(60, seed=2, sh_degree=2, dtype=F64), cams)
    grads = {}
    for name, fn in (("torch", project), ("compiled", compiled.project_compiled)):
        leaves = g.clone().requires_grad_()
        proj = fn(leaves, cams.viewmats[0], cams.Ks[0], 40, 30, None)
        x = getattr(proj, output)
        weights = torch.randn(x.shape, generator=torch.Generator().manual_seed(1), dtype=F64)
        grads[name] = torch.autograd.grad((x * weights).sum(), list(leaves.params().values()),
                                          allow_unused=True)
    for pname, a, b in zip(g.params(), grads["compiled"], grads["torch"]):
        b = torch.zeros_like(a) if b is None else b
        assert rel(a, b) < 1e-10 or (a.abs().max() == 0 and b.abs().max() == 0), pname
    assert any(b is not None and b.abs().max() > 0 for b in grads["torch"])


SPECS = [FisherSpec(), FisherSpec(sh_degree=1),
         FisherSpec(groups=("means", "log_scales", "logit_opacities", "sh0", "shN"),
                    hessian="fisherrf_released"),
         FisherSpec(groups=("means", "quats", "sh0"))]


@pytest.mark.parametrize("spec", SPECS, ids=["exact", "sh1", "fisherrf_released", "subset"])
def test_fused_fisher_diagonal_equals_the_unfused_and_the_torch_walk(spec):
    cams = orbit_cameras(3, 30, 26, dtype=F64, radius=2.5)
    g = with_hard_cases(random_scene(200, seed=4, sh_degree=3, dtype=F64,
                                     opacity_range=(0.3, 0.999)), cams)
    bg = torch.tensor([0.3, 0.6, 0.9], dtype=F64)
    fused = view_fisher(g, cams, bg, spec, RenderSettings(backend="compiled"))
    with fused_paths(False):
        unfused = view_fisher(g, cams, bg, spec, RenderSettings(backend="compiled"))
    torch_walk = view_fisher(g, cams, bg, spec, RenderSettings(backend="tiles"))
    assert fused.shape == unfused.shape == torch_walk.shape
    for c in range(len(cams)):
        assert rel(fused[c], unfused[c]) < 1e-8, c
        assert rel(fused[c], torch_walk[c]) < 1e-8, c
        col = 0
        for group, width in ((gr, w) for gr, w in zip(PARAM_GROUPS, (3, 3, 4, 1, 3, 45))
                             if gr in spec.groups):
            block = slice(col, col + width)
            assert rel(fused[c][:, block], torch_walk[c][:, block]) < 1e-8, group
            col += width
    unseen = torch_walk.abs().sum((0, 2)) == 0
    assert unseen.any() and (fused[:, unseen] == 0).all()


@pytest.mark.parametrize("tau", [1.0, 0.3])
def test_in_place_gopre_score_is_the_composed_score(tau):
    gen = torch.Generator().manual_seed(0)
    h = torch.rand(500, generator=gen, dtype=F64) * 5
    fishers = torch.rand(7, 500, generator=gen, dtype=F64) * (torch.rand(7, 500, generator=gen) > 0.4)
    goal = torch.rand(500, generator=gen, dtype=F64)
    s = posterior_variance(h)
    composed = gopre_score(updated_variance(s, fishers), goal, tau)
    before = fishers.clone()
    assert torch.equal(gopre_score_of_fishers(s, fishers, goal, tau), composed)
    assert torch.equal(fishers, before)  # the candidates' Fishers are not written to


def test_sparse_gopre_scores_equal_the_dense_scores():
    from pipeline.fisher.exact import SparseFisher
    gen = torch.Generator().manual_seed(3)
    n, p = 40, 6
    s = posterior_variance(torch.rand(n, p, generator=gen, dtype=F64) * 3)
    goal = torch.rand(n, p, generator=gen, dtype=F64) * (torch.rand(n, p, generator=gen) > 0.3)
    views = []
    for k in range(5):
        ids = torch.sort(torch.randperm(n, generator=gen)[:10 + 5 * k]).values
        views.append(SparseFisher(ids, torch.rand(len(ids), p, generator=gen, dtype=F64)))
    for tau in (1.0, 0.4):
        dense = torch.stack([gopre_score(updated_variance(s.flatten(), v.dense(n).flatten()),
                                         goal.flatten(), tau) for v in views])
        sparse = gopre_scores_sparse(s, goal, views, tau)
        assert torch.allclose(sparse, dense, rtol=1e-13, atol=0), tau


@pytest.mark.parametrize("options,count", [({}, 1), ({"tau": 0.5}, 3), ({"goal": "identity"}, 2)])
def test_gopre_over_compact_fishers_picks_and_scores_as_the_dense_path(options, count):
    from pipeline.acquisition import SelectionContext, make_strategy
    from pipeline.splat.scenes import sphere_cameras
    g = random_scene(800, seed=0)
    pool, taken = sphere_cameras(14, 24, 24, seed=1), sphere_cameras(3, 24, 24, seed=2)
    probes = sphere_cameras(5, 24, 24, seed=3)
    results = []
    for fused in (True, False):
        with fused_paths(fused):
            ctx = SelectionContext(g, pool, list(range(100, 114)), taken, torch.ones(3),
                                   torch.Generator().manual_seed(0), probes,
                                   settings=RenderSettings(backend="compiled"))
            results.append(make_strategy("gopre", **options).select(ctx, count))
    sparse, dense = results
    assert sparse.chosen == dense.chosen and len(sparse.chosen) == count
    for k, v in dense.scores.items():
        assert sparse.scores[k] == pytest.approx(v, rel=1e-9), k
    assert sparse.fisher_views == dense.fisher_views


def test_a_probe_that_is_a_candidate_or_a_taken_view_reuses_its_fisher():
    """The episode names its probes and taken views by pool id; probes among the candidates or the
    taken views reuse those Fishers. The picks and every score equal the run that recomputes each
    probe's Fisher, bit for bit, and fewer views are computed. A probe id mapped to the wrong view
    (by position instead of id) would change the goal Hessian and the scores."""
    from pipeline.acquisition import SelectionContext, make_strategy
    from pipeline.splat.scenes import sphere_cameras
    g = random_scene(600, seed=0)
    views = sphere_cameras(20, 24, 24, seed=1)  # pool ids 0..19
    taken_ids, candidate_ids = [17, 3, 11], [i for i in range(20) if i not in (17, 3, 11)]
    probe_ids = [11, 5, 19, 0, 3]  # two taken views, three candidates
    outside = sphere_cameras(1, 24, 24, seed=9)
    results = []
    for named in (False, True):
        ctx = SelectionContext(g, views[candidate_ids], candidate_ids, views[taken_ids], torch.ones(3),
                               torch.Generator().manual_seed(0), views[probe_ids],
                               settings=RenderSettings(backend="compiled"),
                               taken_ids=taken_ids if named else None,
                               probe_ids=probe_ids if named else None)
        results.append(make_strategy("gopre").select(ctx, 2))
    recomputed, reused = results
    assert reused.chosen == recomputed.chosen and reused.scores == recomputed.scores
    assert recomputed.fisher_views - reused.fisher_views == len(probe_ids)
    with pytest.raises(ValueError, match="probe_ids has 2 entries for 5 cameras"):
        SelectionContext(g, views[candidate_ids], candidate_ids, views[taken_ids], torch.ones(3),
                         torch.Generator().manual_seed(0), views[probe_ids], probe_ids=[1, 2])
    # a probe outside the pool (no known Fisher under its id) is computed
    ctx = SelectionContext(g, views[candidate_ids], candidate_ids, views[taken_ids], torch.ones(3),
                           torch.Generator().manual_seed(0), Cameras.cat([views[[5]], outside]),
                           settings=RenderSettings(backend="compiled"), taken_ids=taken_ids,
                           probe_ids=[5, 99])
    assert make_strategy("gopre").select(ctx, 1).fisher_views == len(candidate_ids) + len(taken_ids) + 1


def test_views_side_by_side_equal_one_view_at_a_time_bit_for_bit():
    """Several cameras run one per thread with serial kernels; one camera splits its kernels over
    tiles. The Fisher of every view is the same to the bit either way (the per-tile rows are summed
    in a fixed order whatever thread wrote them), with two threads and with one."""
    from pipeline.fisher.exact import view_fisher_sparse
    cams = orbit_cameras(5, 30, 26, dtype=F64, radius=2.5)
    g = with_hard_cases(random_scene(300, seed=5, sh_degree=3, dtype=F64,
                                     opacity_range=(0.3, 0.999)), cams)
    bg = torch.tensor([0.3, 0.6, 0.9], dtype=F64)
    settings = RenderSettings(backend="compiled")
    before = torch.get_num_threads()
    try:
        for threads in (2, 1):
            torch.set_num_threads(threads)
            for spec in (FisherSpec(), SPECS[2]):
                together = view_fisher_sparse(g, cams, bg, spec, settings)
                alone = [view_fisher_sparse(g, cams[c:c + 1], bg, spec, settings)[0]
                         for c in range(len(cams))]
                assert len(together) == len(cams)
                for c, (a, b) in enumerate(zip(together, alone)):
                    assert torch.equal(a.ids, b.ids) and torch.equal(a.rows, b.rows), (threads, c)
    finally:
        torch.set_num_threads(before)


def test_map_in_threads_keeps_order_bounds_the_work_in_flight_and_raises():
    import threading
    import time
    lock, state = threading.Lock(), {"running": 0, "most": 0, "threads": set()}

    def work(i):
        with lock:
            state["running"] += 1
            state["most"] = max(state["most"], state["running"])
            state["threads"].add(threading.get_ident())
        time.sleep(0.002 * (7 - i % 7))  # later items finish first
        with lock:
            state["running"] -= 1
        return i * i

    assert list(compiled.map_in_threads(work, 23, 2)) == [i * i for i in range(23)]
    assert state["most"] <= 2 and len(state["threads"]) == 2
    assert list(compiled.map_in_threads(work, 4, 1)) == [0, 1, 4, 9]
    asked = []
    lazy = compiled.map_in_threads(lambda i: asked.append(i) or i, 100, 2)
    assert next(lazy) == 0
    time.sleep(0.05)
    assert len(asked) <= 5  # 2 x threads ahead of what was taken, not the whole pool
    lazy.close()
    assert list(compiled.map_in_threads(work, 0, 2)) == []
    started = []

    def fails_at_3(i):
        started.append(i)
        if i == 3:
            raise ValueError("view 3")
        return i

    results = compiled.map_in_threads(fails_at_3, 1000, 2)
    with pytest.raises(ValueError, match="view 3"):
        list(results)
    assert len(started) < 20  # the pool was not run through after the failure


def test_views_evaluated_side_by_side_score_as_one_at_a_time():
    """``evaluate_views`` renders views one per thread on the compiled backend: every per-view
    PSNR and SSIM equals the one-thread loop's to the bit, in order."""
    from pipeline.eval.metrics import evaluate_views
    cams = orbit_cameras(5, 30, 26, radius=2.5)
    g = random_scene(400, seed=6)
    images = torch.rand(5, 26, 30, 3, generator=torch.Generator().manual_seed(1))
    bg, settings = torch.ones(3), RenderSettings(backend="compiled")
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        serial = evaluate_views(g, cams, images, bg, settings=settings)
        torch.set_num_threads(2)
        together = evaluate_views(g, cams, images, bg, settings=settings)
        alone = [evaluate_views(g, cams[i:i + 1], images[i:i + 1], bg, settings=settings)
                 for i in range(len(cams))]
    finally:
        torch.set_num_threads(before)
    assert together.psnr == serial.psnr == [a.psnr[0] for a in alone]
    assert together.ssim == serial.ssim == [a.ssim[0] for a in alone]
    assert together.ssim_skimage == serial.ssim_skimage
    assert len(set(together.psnr)) == len(cams)  # five different views, not one repeated
