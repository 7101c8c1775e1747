"""Finite parameters render finite images and gradients, in every backend and dtype.

The captured case (``../shared/data/regressions/tiles_float32_nan.pt``) came from a training run
whose float32 tiled render turned NaN; the adversarial scenes below push the same weak spots
(near-plane Gaussians with enormous 2D covariances, extreme scales, anisotropy and opacities,
unnormalised quaternions) on purpose.
"""

import math

import pytest
import torch

from pipeline.cameras import Cameras, intrinsics_from_fov, look_at
from pipeline.splat import Gaussians, RenderSettings, compiled, render
from pipeline.splat.project import project
from pipeline.splat.backend import COMPOSITORS as REGISTERED_BACKENDS
from tests.conftest import shared_scene

# every backend, including any added later; the compiled one where it can load
BACKENDS = tuple(pytest.param(b, marks=pytest.mark.skipif(
    b == "compiled" and compiled.load() is None,
    reason=f"compiled backend unavailable: {compiled.load_error()}")) for b in REGISTERED_BACKENDS)


def load_regression():
    path = shared_scene("regressions", "tiles_float32_nan.pt")
    case = torch.load(path, weights_only=False)
    cams = Cameras(case["viewmats"], case["Ks"], case["width"], case["height"])
    return case, cams


def render_with_grads(params: dict, cams: Cameras, background, sh_degree, backend):
    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in params.items()}
    out = render(Gaussians(**leaves), cams, background, sh_degree, RenderSettings(backend=backend))
    (out.rgb.sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()
    return out, {k: v.grad for k, v in leaves.items()}


def assert_finite(out, grads, label):
    for name in ("rgb", "alpha", "depth"):
        bad = int((~torch.isfinite(getattr(out, name))).sum())
        assert bad == 0, f"{label}: {bad} non-finite values in {name}"
    for name, grad in grads.items():
        bad = int((~torch.isfinite(grad)).sum())
        assert bad == 0, f"{label}: {bad} non-finite values in the gradient of {name}"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("backend", BACKENDS)
def test_captured_float32_nan_case_renders_finite(backend, dtype):
    case, cams = load_regression()
    params = {k: v.to(dtype) for k, v in case["gaussians"].items()}
    if backend == "loop":  # the literal loop is too slow for 9,751 Gaussians: keep the largest
        radii = project(Gaussians(**case["gaussians"]), cams.viewmats[0], cams.Ks[0], cams.width,
                        cams.height, case["sh_degree"]).radii
        keep = torch.argsort(radii, descending=True)[:150]  # the near-plane culprit among them
        params = {k: v[keep] for k, v in params.items()}
    out, grads = render_with_grads(params, cams.to(dtype=dtype), case["background"].to(dtype),
                                   case["sh_degree"], backend)
    assert_finite(out, grads, f"{backend} {dtype}")


def test_captured_case_conics_are_positive_definite_in_float32():
    """The cause: a near-plane Gaussian whose float32 determinant a c - b^2 cancelled to <= 0."""
    case, cams = load_regression()
    proj = project(Gaussians(**case["gaussians"]), cams.viewmats[0], cams.Ks[0], cams.width,
                   cams.height, case["sh_degree"])
    a, b, c = proj.conics[proj.radii > 0].double().unbind(-1)
    assert bool((a > 0).all()) and bool((c > 0).all()), "conic diagonal not positive"
    assert bool((a * c - b * b > 0).all()), "conic not positive definite"


def test_captured_case_float32_image_close_to_float64():
    case, cams = load_regression()
    images = {}
    for dtype in (torch.float32, torch.float64):
        g = Gaussians(**{k: v.to(dtype) for k, v in case["gaussians"].items()})
        images[dtype] = render(g, cams.to(dtype=dtype), case["background"].to(dtype),
                               case["sh_degree"]).rgb.double()
    assert (images[torch.float32] - images[torch.float64]).abs().max() < 1e-2


def adversarial_scene(kind: str, n: int, seed: int, eye: torch.Tensor, viewmat: torch.Tensor):
    """Finite float32 Gaussians of one adversarial kind, placed relative to a camera at ``eye``."""
    gen = torch.Generator().manual_seed(seed)
    rand = lambda *shape: torch.rand(*shape, generator=gen)  # noqa: E731
    rot_c2w = viewmat[:3, :3].T
    # camera-frame positions mostly in view, at depths 0.5..4
    p_cam = torch.stack([(rand(n) - 0.5) * 2, (rand(n) - 0.5) * 1.5, 0.5 + 3.5 * rand(n)], -1)
    log_scales = torch.log(0.02 + 0.2 * rand(n, 3))
    quats = torch.randn(n, 4, generator=gen)
    logits = torch.logit(0.1 + 0.8 * rand(n))
    if kind == "near_plane":
        p_cam[:, 2] = 0.01 + 1e-4 * rand(n)  # just in front of the near plane (0.01)
        p_cam[:, :2] *= 0.01
        log_scales = torch.log(0.05 + 2 * rand(n, 3))
    elif kind == "behind":
        p_cam[:, 2] = -4 * rand(n)
    elif kind == "off_screen":
        p_cam[:, :2] = (rand(n, 2) - 0.5) * 2e4  # x/z and y/z up to 1e4 outside the frustum
    elif kind == "scales":
        log_scales = math.log(1e-7) + (math.log(1e3) - math.log(1e-7)) * rand(n, 3)
    elif kind == "anisotropic":
        log_scales = torch.full((n, 3), math.log(1e-7))
        log_scales[torch.arange(n), torch.randint(0, 3, (n,), generator=gen)] = math.log(1e3)
    elif kind == "opacity":
        logits = torch.where(rand(n) < 0.5, torch.tensor(20.0), torch.tensor(-20.0))
    elif kind == "quaternions":
        quats = quats * (10 ** (6 * rand(n, 1) - 3))  # norms 1e-3 .. 1e3
    means = p_cam @ rot_c2w.T + eye
    sh0 = rand(n, 1, 3) * 3 - 1.5
    shn = 0.3 * torch.randn(n, 15, 3, generator=gen)
    return {"means": means, "log_scales": log_scales, "quats": quats, "logit_opacities": logits,
            "sh0": sh0, "shN": shn}


KINDS = ("near_plane", "behind", "off_screen", "scales", "anisotropic", "opacity", "quaternions")


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("kind", KINDS)
def test_adversarial_float32_scenes_render_finite(kind, backend):
    eye = torch.tensor([0.3, -2.5, 0.8])
    viewmats = look_at(eye[None], torch.zeros(1, 3), torch.tensor([0.0, 0.0, 1.0]))
    cams = Cameras(viewmats, intrinsics_from_fov(0.9, 40, 32, 1), 40, 32)
    for seed in range(3):
        scene = adversarial_scene(kind, 120, seed, eye, viewmats[0])
        # a few ordinary Gaussians behind them so compositing has something to do
        ordinary = adversarial_scene("ordinary", 60, 100 + seed, eye, viewmats[0])
        params = {k: torch.cat([scene[k], ordinary[k]]) for k in scene}
        out, grads = render_with_grads(params, cams, torch.tensor([0.1, 0.2, 0.3]), 3, backend)
        assert_finite(out, grads, f"{kind} seed {seed} {backend}")
