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
        sx = 1 / (1 / s + flat(fishers[c]) / TAU ** 2)
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
    with pytest.raises(ValueError, match=r"no probe poses \(K = 0\)"):
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
