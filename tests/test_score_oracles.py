"""Every acquisition score against its formula, written out here from brute-force Fishers
(autograd Jacobians of the rendered image), at non-default tau and lambda with K = 2 probes; and
coverage against hand geometry. The strategies' own Fisher, posterior and scoring code is what is
checked; nothing here calls it."""

import math

import pytest
import torch

from pipeline.acquisition import SelectionContext, make_strategy
from pipeline.cameras import Cameras, intrinsics_from_fov, look_at
from pipeline.splat import Gaussians, RenderSettings, render
from pipeline.splat.gaussians import PARAM_NAMES
from pipeline.splat.scenes import orbit_cameras, random_scene

F64 = torch.float64
TAU, LAM = 0.3, 1e-3  # not 0.5, where x / tau * 2 == x / tau ** 2 (a mutant that hid)
SETTINGS = RenderSettings(tile_size=4, chunk=4)
DENSE = RenderSettings(tile_size=4, backend="dense")  # the brute force renders with the dense oracle
BACKGROUND = torch.tensor([0.3, 0.6, 0.9], dtype=F64)


@pytest.fixture(scope="module")
def setup():
    g = random_scene(8, seed=11, dtype=F64, sh_degree=1, opacity_range=(0.3, 0.8))
    cams = orbit_cameras(6, 8, 8, dtype=F64, radius=2.4, phase=0.2)
    fishers = {i: brute_force_fisher(g, cams[i]) for i in range(6)}
    return g, cams, fishers


def brute_force_fisher(g: Gaussians, cam: Cameras) -> dict[str, torch.Tensor]:
    """diag(J^T J) per parameter group from autograd Jacobians of the RGB image (channels
    separately, background included), rendered by the dense compositor."""
    params = g.params()

    def image(*values):
        return render(Gaussians(**dict(zip(PARAM_NAMES, values))), cam, BACKGROUND,
                      settings=DENSE).rgb.reshape(-1)

    jac = torch.autograd.functional.jacobian(image, tuple(params[k] for k in PARAM_NAMES),
                                             vectorize=True)
    return {k: j.reshape(j.shape[0], -1).square().sum(0) for k, j in zip(PARAM_NAMES, jac)}


def flat(fisher: dict[str, torch.Tensor], groups=PARAM_NAMES) -> torch.Tensor:
    return torch.cat([fisher[k] for k in groups])


def context(g, cams, probes=(4, 5)):
    return SelectionContext(g, cams[[1, 2, 3]], [1, 2, 3], cams[[0]], BACKGROUND, torch.Generator(),
                            cams[list(probes)], settings=SETTINGS)


def expected_gopre(fishers, score: str, goal: str, probe_ids=(4, 5)):
    h = flat(fishers[0])
    s = 1 / (h + LAM)
    probes = [flat(fishers[k]) for k in probe_ids]
    m = sum(probes) / len(probes) if goal == "probes" else torch.ones_like(h)
    out = {}
    for c in (1, 2, 3):
        sx = 1 / (1 / s + flat(fishers[c]))  # the unit-noise posterior: tau enters the score only
        if score == "logdet":
            out[c] = float(torch.log(1 + sx * m / TAU ** 2).sum())
        elif score == "trace":
            out[c] = float((sx * m).sum() / TAU ** 2)
        else:  # direct Monte-Carlo over the K probes
            out[c] = float(sum(torch.log(1 + sx * p / TAU ** 2).sum() for p in probes) / len(probes))
    return out


@pytest.mark.parametrize("score,goal,probes", [("logdet", "probes", (4, 5)), ("trace", "probes", (4, 5)),
                                               ("mc", "probes", (4, 5)), ("logdet", "identity", (4, 5)),
                                               ("logdet", "probes", (5,))])
def test_gopre_scores_equal_the_formula(setup, score, goal, probes):
    g, cams, fishers = setup
    sel = make_strategy("gopre", tau=TAU, lam=LAM, score=score, goal=goal).select(context(g, cams, probes))
    expected = expected_gopre(fishers, score, goal, probes)
    for c, value in expected.items():
        assert sel.scores[c] == pytest.approx(value, rel=1e-8), f"gopre {score}/{goal} score of view {c}"
    assert sel.chosen == [min(expected, key=expected.get)]  # argmin


def test_fisherrf_score_is_its_information_gain_without_rotations(setup):
    g, cams, fishers = setup
    groups = ("means", "log_scales", "logit_opacities", "sh0", "shN")  # FisherRF omits quats
    h = flat(fishers[0], groups)
    expected = {c: float((flat(fishers[c], groups) / (h + LAM)).sum()) for c in (1, 2, 3)}
    sel = make_strategy("fisherrf", lam=LAM).select(context(g, cams))
    for c, value in expected.items():
        assert sel.scores[c] == pytest.approx(value, rel=1e-8), f"fisherrf score of view {c}"
    assert sel.chosen == [max(expected, key=expected.get)]  # argmax


def released_hessian(g: Gaussians, cam: Cameras) -> torch.Tensor:
    """FisherRF's released Hessian, from its description: (sum_c dI_c / d theta_act)^2 summed over
    pixels for means, scales (= exp) and opacity (= sigmoid), times the activation's derivative
    once; SH entries per-channel sums of squares. Flattened in FisherRF's group order."""
    scales, opac = g.log_scales.exp(), torch.sigmoid(g.logit_opacities)

    def summed(means, s, o):
        h = Gaussians(**{**g.params(), "means": means, "log_scales": s.log(), "logit_opacities": torch.logit(o)})
        return render(h, cam, BACKGROUND, settings=DENSE).rgb.sum(-1).reshape(-1)
    jm, js, jo = torch.autograd.functional.jacobian(summed, (g.means, scales, opac), vectorize=True)
    sq = [j.reshape(j.shape[0], -1).square().sum(0) for j in (jm, js, jo)]
    colour = brute_force_fisher(g, cam)
    return torch.cat([sq[0], sq[1] * scales.reshape(-1), sq[2] * opac * (1 - opac),
                      colour["sh0"], colour["shN"]])


def test_fisherrf_released_scores_with_the_released_hessian(setup):
    g, cams, _ = setup
    h = released_hessian(g, cams[0])
    expected = {c: float((released_hessian(g, cams[c]) / (h + LAM)).sum()) for c in (1, 2, 3)}
    sel = make_strategy("fisherrf", lam=LAM, hessian="fisherrf_released").select(context(g, cams))
    for c, value in expected.items():
        assert sel.scores[c] == pytest.approx(value, rel=1e-8), f"fisherrf_released score of view {c}"
    assert sel.chosen == [max(expected, key=expected.get)]


def test_popgs_diag_score_is_the_diagonal_log_det_gain(setup):
    g, cams, fishers = setup
    h = flat(fishers[0])
    expected = {c: float(torch.log(1 + flat(fishers[c]) / (h + LAM)).sum()) for c in (1, 2, 3)}
    sel = make_strategy("popgs", lam=LAM).select(context(g, cams))
    for c, value in expected.items():
        assert sel.scores[c] == pytest.approx(value, rel=1e-8), f"popgs score of view {c}"
    assert sel.chosen == [max(expected, key=expected.get)]


def circle_cameras(degrees: list[float], radius: float = 2.0) -> Cameras:
    rad = torch.tensor(degrees, dtype=F64) * math.pi / 180
    eyes = torch.stack([radius * torch.cos(rad), radius * torch.sin(rad), torch.zeros_like(rad)], -1)
    viewmats = look_at(eyes, torch.zeros_like(eyes), torch.tensor([0, 0, 1.0], dtype=F64))
    return Cameras(viewmats, intrinsics_from_fov(0.9, 8, 8, len(degrees), dtype=F64), 8, 8)


def chord(degrees: float, radius: float = 2.0) -> float:
    return 2 * radius * math.sin(math.radians(degrees) / 2)


def test_coverage_picks_the_view_farthest_from_every_taken_view_by_hand():
    """Taken at 0 and 90 degrees on a circle of radius 2; the candidate at 225 degrees (opposite
    the taken pair) is farthest from its nearest taken view; scores are chord lengths."""
    g = random_scene(5, seed=0, dtype=F64)
    taken = circle_cameras([0.0, 90.0])
    pool = circle_cameras([45.0, 180.0, 225.0, 300.0])
    ctx = SelectionContext(g, pool, [45, 180, 225, 300], taken, BACKGROUND, torch.Generator())
    sel = make_strategy("coverage").select(ctx, count=2)
    expected = {45: chord(45), 180: chord(90), 225: chord(135), 300: chord(60)}
    for view, value in expected.items():
        assert sel.scores[view] == pytest.approx(value, rel=1e-12), f"coverage distance of {view}"
    assert sel.chosen[0] == 225
    # after 225 is taken: 45 and 180 are chord(45) from their nearest, 300 is chord(60) from 0
    assert sel.chosen[1] == 300


def test_diagonal_log_det_information_equals_the_dense_determinant():
    """The diagonal branch of log det(I + tau^-2 S^1/2 F S^1/2) against slogdet of the dense
    matrix with F = diag(f), at tau = 0.3."""
    from pipeline.fisher.posterior import log_det_information
    gen = torch.Generator().manual_seed(3)
    s, f = torch.rand(7, generator=gen, dtype=F64) + 0.1, torch.rand(7, generator=gen, dtype=F64) * 5
    dense = torch.eye(7, dtype=F64) + torch.diag(s.sqrt() * f * s.sqrt()) / TAU ** 2
    expected = torch.linalg.slogdet(dense)[1]
    assert log_det_information(s, f, TAU).item() == pytest.approx(expected.item(), rel=1e-12)
    assert log_det_information(s, torch.diag(f), TAU).item() == pytest.approx(expected.item(), rel=1e-12)


def test_goal_hessian_needs_a_probe():
    from pipeline.fisher.posterior import goal_hessian
    with pytest.raises(ValueError, match=r"^goal_hessian: no probe poses \(K = 0\)$"):
        goal_hessian(torch.zeros(0, 5, dtype=F64))
    f = torch.rand(1, 5, dtype=F64)
    assert torch.equal(goal_hessian(f), f[0])


def test_coverage_with_nothing_taken_starts_at_the_lowest_id_then_goes_farthest():
    g = random_scene(5, seed=0, dtype=F64)
    pool = circle_cameras([0.0, 30.0, 200.0, 90.0])
    nothing = circle_cameras([])
    ctx = SelectionContext(g, pool, [10, 11, 12, 13], nothing, BACKGROUND, torch.Generator())
    sel = make_strategy("coverage").select(ctx, count=2)
    assert all(math.isinf(v) and v > 0 for v in sel.scores.values())  # nothing to be near yet
    assert sel.chosen == [10, 12]  # ties -> lowest id (0 deg); then 200 deg is farthest from it


def compositing_weights(g: Gaussians, cam: Cameras) -> torch.Tensor:
    """w_pg = alpha T of every Gaussian at every pixel, [N, H, W]: the dense oracle rendering a
    one-hot per-Gaussian feature, one Gaussian at a time (no gradients, no strategy code)."""
    n = len(g)
    rows = []
    for k in range(n):
        onehot = torch.zeros(n, 1, dtype=F64)
        onehot[k] = 1
        rows.append(render(g, cam, BACKGROUND, settings=DENSE, extra_features=onehot).rgb[0, ..., 3])
    return torch.stack(rows)


def face_bin(direction: torch.Tensor) -> torch.Tensor:
    """Cube face of each direction [N, 3] as the face normal it is most aligned with, in the order
    (-x, +x, -y, +y, -z, +z)."""
    normals = torch.tensor([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]],
                           dtype=direction.dtype)
    return (direction @ normals.T).argmax(dim=1)


@pytest.mark.parametrize("taken", [(0,), (0, 1), (0, 0)])
def test_gaussmi_score_is_the_composited_reliability_entropy(setup, taken):
    """Log-odds per Gaussian and cube face accumulate over every taken view (a view taken twice
    counts twice: views on the same face add up)."""
    g, cams, _ = setup
    sigma = 0.05  # small enough that the worst pixels clamp at 0.05 and the best at 0.95
    target = random_scene(8, seed=12, dtype=F64, sh_degree=1)
    taken_images = render(target, cams[list(taken)], BACKGROUND, settings=DENSE).rgb
    log_odds = torch.zeros(len(g), 6, dtype=F64)
    for k, t in enumerate(taken):
        pred = render(g, cams[[t]], BACKGROUND, settings=DENSE).rgb[0]
        error = (pred - taken_images[k]).square().mean(-1)
        reliable = torch.exp(-error / (2 * sigma ** 2)).clamp(0.05, 0.95)
        sums = (compositing_weights(g, cams[[t]]) * torch.logit(reliable)).sum((1, 2))  # [N]
        log_odds[torch.arange(len(g)), face_bin(cams[[t]].centers[0] - g.means)] += sums
    pool = [c for c in range(1, 6) if c not in taken][:3]  # view 1 shares cube faces with view 0
    expected = {}
    for c in pool:
        p = torch.sigmoid(log_odds[torch.arange(len(g)), face_bin(cams[[c]].centers[0] - g.means)])
        entropy = -(p * torch.log2(p) + (1 - p) * torch.log2(1 - p))
        expected[c] = float((compositing_weights(g, cams[[c]]) * entropy[:, None, None]).sum())
    ctx = SelectionContext(g, cams[pool], pool, cams[list(taken)], BACKGROUND, torch.Generator(),
                           taken_images=taken_images, settings=SETTINGS)
    sel = make_strategy("gaussmi", error_sigma=sigma).select(ctx)
    for c, value in expected.items():
        assert sel.scores[c] == pytest.approx(value, rel=1e-8), f"gaussmi score of view {c}"
    assert sel.chosen == [max(expected, key=expected.get)]


def activenerf_port_variances(weights: torch.Tensor, variance: torch.Tensor, v0: float):
    """FisherRF's 3DGS port of ActiveNeRF, written out per pixel from dense weights w [N, H, W]:
    prior V = v0 + sum_g w^2 beta^2; posterior P = sum_g w^2 / (1/beta^2 + w^2 / V)."""
    w2 = weights.square()
    beta2 = variance[:, None, None]
    prior = (w2 * beta2).sum(0) + v0
    return prior, (w2 / (1 / beta2 + w2 / prior)).sum(0)


def test_activenerf_score_is_the_ports_variance_reduction(setup):
    """With per-Gaussian variances left at their initial values (steps=0): the score is
    sum_p (V_p - P_p) of the port, with squared compositing weights. Varying init across Gaussians
    is not possible through the options, so the brute force uses the same constant beta^2 and a
    second test below checks the per-Gaussian indexing."""
    g, cams, _ = setup
    init, v0 = -2.0, 1e-4
    expected = {}
    for c in (1, 2, 3):
        prior, post = activenerf_port_variances(compositing_weights(g, cams[[c]]),
                                                torch.full((len(g),), math.exp(init), dtype=F64), v0)
        expected[c] = float((prior - post).sum())
    ctx = context(g, cams)
    ctx.taken_images = render(g, cams[[0]], BACKGROUND, settings=DENSE).rgb
    sel = make_strategy("activenerf", steps=0, init_log_var=init, min_variance=v0).select(ctx)
    for c, value in expected.items():
        assert sel.scores[c] == pytest.approx(value, rel=1e-8), f"activenerf score of view {c}"
    assert sel.chosen == [max(expected, key=expected.get)]


def test_activenerf_port_variances_per_gaussian(setup):
    """Prior and posterior maps with a different beta^2 for every Gaussian against the port's
    formula; and the squared weights matter (the linear-weight composite differs)."""
    from pipeline.acquisition.rendered_stats import view_compositing_weights
    g, cams, _ = setup
    variance = torch.linspace(0.05, 2.0, len(g), dtype=F64)
    strategy = make_strategy("activenerf", min_variance=1e-4)
    for c in (1, 4):
        dense = compositing_weights(g, cams[[c]])
        prior, post = activenerf_port_variances(dense, variance, 1e-4)
        w = view_compositing_weights(g, cams[[c]], SETTINGS)
        got_prior = strategy.prior_variance(w, variance)
        assert torch.allclose(got_prior, prior, rtol=1e-10, atol=1e-14)
        assert torch.allclose(strategy.posterior_variance(w, variance, got_prior), post, rtol=1e-10, atol=1e-14)
        linear = (dense * variance[:, None, None]).sum(0) + 1e-4
        assert not torch.allclose(prior, linear, rtol=1e-3)


def test_activenerf_fit_lowers_the_nll_of_the_taken_views(setup):
    """The fitted variance attribute explains the taken view's residuals better than its start."""
    g, cams, _ = setup
    strategy = make_strategy("activenerf", steps=80, init_log_var=-3.0)
    ctx = context(g, cams)
    target = random_scene(8, seed=12, dtype=F64, sh_degree=1)
    ctx.taken_images = render(target, cams[[0]], BACKGROUND, settings=DENSE).rgb
    residual = (render(g, cams[[0]], BACKGROUND, settings=DENSE).rgb[0]
                - ctx.taken_images[0]).square().sum(-1)
    weights = compositing_weights(g, cams[[0]])

    def nll(log_var):
        v = (weights.square() * torch.exp(log_var)[:, None, None]).sum(0) + strategy.min_variance
        return float((residual / (2 * v) + 0.5 * torch.log(v)).mean())
    fitted = strategy.fit_variance(ctx)
    assert nll(fitted) < nll(torch.full((len(g),), -3.0, dtype=F64)) - 1e-3


def test_gopre_without_the_sh_rest_scores_on_the_other_groups_only(setup):
    g, cams, fishers = setup
    groups = ("means", "log_scales", "quats", "logit_opacities", "sh0")
    h = flat(fishers[0], groups)
    m = (flat(fishers[4], groups) + flat(fishers[5], groups)) / 2
    expected = {c: float(torch.log1p(1 / (h + LAM + flat(fishers[c], groups)) * m / TAU ** 2).sum())
                for c in (1, 2, 3)}
    sel = make_strategy("gopre", tau=TAU, lam=LAM, fisher_groups="without_sh_rest").select(context(g, cams))
    for c, value in expected.items():
        assert sel.scores[c] == pytest.approx(value, rel=1e-8), f"gopre without SH rest, view {c}"
    with pytest.raises(ValueError, match="fisher_groups: 'some' is not one of all, without_sh_rest"):
        make_strategy("gopre", fisher_groups="some")


def test_gopre_scores_a_pool_of_one_and_needs_probes_for_a_probe_goal(setup):
    """The last round can leave one candidate: M = I is built from it alone."""
    g, cams, fishers = setup
    ctx = SelectionContext(g, cams[[2]], [2], cams[[0]], BACKGROUND, torch.Generator(), None, settings=SETTINGS)
    sel = make_strategy("gopre", tau=TAU, lam=LAM, goal="identity").select(ctx)
    assert sel.chosen == [2]
    assert sel.scores[2] == pytest.approx(expected_gopre(fishers, "logdet", "identity")[2], rel=1e-8)
    with pytest.raises(ValueError, match=r"^gopre needs probe poses from the target manifold \(ctx\.probes\)$"):
        make_strategy("gopre").select(ctx)


def test_gaussmi_direction_bins_are_the_cube_faces():
    from pipeline.acquisition.gaussmi import direction_bins
    directions = torch.tensor([[-2.0, 0.3, 0.1], [3.0, -1, 0], [0.2, -5, 1], [0, 4, -1], [1, 1, -6], [0, -2, 7]],
                              dtype=F64) / 10  # not unit: the bins take the raw offset
    assert direction_bins(torch.zeros(6, 3, dtype=F64), directions).tolist() == [0, 1, 2, 3, 4, 5]
    assert torch.equal(direction_bins(torch.zeros(6, 3, dtype=F64), directions), face_bin(directions))


@pytest.mark.parametrize("name", ["gaussmi", "activenerf"])
def test_error_driven_strategies_need_the_taken_images(setup, name):
    g, cams, _ = setup
    with pytest.raises(ValueError, match=rf"^{name} needs the taken views' images \(ctx\.taken_images\)$"):
        make_strategy(name).select(context(g, cams))


def test_activenerf_fit_follows_the_gradient_of_its_nll(setup, monkeypatch):
    """The fit's first step sees the gradient of the explicit Gaussian NLL of the taken view,
    mean_p [r_p / (2 V_p) + log(V_p) / 2], V_p = sum_g w_pg^2 e^(log_var_g) + v_min (the port's
    squared weights), at v_min = 0.05."""
    g, cams, _ = setup
    init, v_min = -1.5, 0.05
    ctx = context(g, cams)
    target = random_scene(8, seed=12, dtype=F64, sh_degree=1)
    ctx.taken_images = render(target, cams[[0]], BACKGROUND, settings=DENSE).rgb
    residual = (render(g, cams[[0]], BACKGROUND, settings=DENSE).rgb[0] - ctx.taken_images[0]).square().sum(-1)
    weights = compositing_weights(g, cams[[0]])
    log_var = torch.full((len(g),), init, dtype=F64, requires_grad=True)
    v = (weights.square() * torch.exp(log_var)[:, None, None]).sum(0) + v_min
    (residual / (2 * v) + 0.5 * torch.log(v)).mean().backward()
    seen = []

    class Recording(torch.optim.SGD):
        def step(self, closure=None):
            seen.append(self.param_groups[0]["params"][0].grad.clone())
            return super().step(closure)
    monkeypatch.setattr(torch.optim, "Adam", lambda params, lr: Recording(params, lr=lr))
    make_strategy("activenerf", steps=1, init_log_var=init, min_variance=v_min).fit_variance(ctx)
    assert torch.allclose(seen[0], log_var.grad, rtol=1e-8, atol=1e-15)


def test_a_colour_only_fisher_equals_the_brute_force_colour_entries(setup):
    """FisherSpec without any geometric group (SH only) takes its own branch of the Jacobian."""
    from pipeline.fisher.exact import FisherSpec, view_fisher
    g, cams, fishers = setup
    got = view_fisher(g, cams[[2]], BACKGROUND, FisherSpec(groups=("sh0", "shN")), SETTINGS).flatten(1)[0]
    n = len(g)  # view_fisher is per Gaussian: [N, P] with P = sh0 then shN of that Gaussian
    expected = torch.cat([fishers[2]["sh0"].reshape(n, -1), fishers[2]["shN"].reshape(n, -1)], 1).flatten()
    assert torch.allclose(got, expected, rtol=1e-9, atol=1e-12)


def test_gopre_tau0_is_the_limit_formula_and_the_goal_drops_out(setup):
    """tau = 0: score = sum over the goal's support of log Sx_i (Sx the unit-noise posterior),
    written out here; goals with the same support but different values (probes (4, 5), probe 5
    alone, M = I) rank alike, while at tau = 1 their scores differ."""
    g, cams, fishers = setup
    h = flat(fishers[0])
    goals = {"probes45": (sum(flat(fishers[k]) for k in (4, 5)) / 2, dict(goal="probes"), (4, 5)),
             "probe5": (flat(fishers[5]), dict(goal="probes"), (5,)),
             "identity": (torch.ones_like(h), dict(goal="identity"), (4, 5))}
    limit, unit = {}, {}
    for name, (m, options, probes) in goals.items():
        assert bool((m > 0).all()), "precondition: every goal sees every parameter"
        sx = {c: 1 / (h + LAM + flat(fishers[c])) for c in (1, 2, 3)}
        expected = {c: float(torch.log(sx[c]).sum()) for c in (1, 2, 3)}
        sel = make_strategy("gopre", tau=0.0, lam=LAM, **options).select(context(g, cams, probes))
        for c, value in expected.items():
            assert sel.scores[c] == pytest.approx(value, rel=1e-10), f"tau0 {name}, view {c}"
        limit[name] = sorted(sel.scores, key=sel.scores.get)
        unit[name] = make_strategy("gopre", tau=1.0, lam=LAM, **options).select(context(g, cams, probes)).scores
    assert limit["probes45"] == limit["probe5"] == limit["identity"]
    assert unit["probes45"] != pytest.approx(unit["probe5"], rel=1e-3)


def test_gopre_tau0_counts_only_the_parameters_the_goal_sees():
    """Where M_i = 0 the limit has no term: zeroing the goal on a parameter removes log Sx_i."""
    from pipeline.fisher.posterior import gopre_limit_score
    sx = torch.tensor([[0.5, 0.25, 2.0]], dtype=F64)
    assert gopre_limit_score(sx, torch.tensor([1.0, 3.0, 0.0], dtype=F64)).item() == pytest.approx(
        math.log(0.5) + math.log(0.25), rel=1e-14)
