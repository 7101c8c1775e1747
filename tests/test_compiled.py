"""The compiled CPU backend against the torch tile path, the dense oracle and autograd."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from pipeline.cameras import Cameras
from pipeline.fisher.exact import FisherSpec, view_fisher
from pipeline.fisher.features import PARAM_GROUPS
from pipeline.splat import Gaussians, RenderSettings, compiled, render
from pipeline.splat.compiled import rasterize_compiled
from pipeline.splat.project import project
from pipeline.splat.scenes import orbit_cameras, random_scene

# the compiled kernels against their oracles, on two threads (their threaded branches) whatever the
# process's share of the cores
pytestmark = [pytest.mark.skipif(compiled.load() is None,
                                 reason=f"compiled backend unavailable: {compiled.load_error()}"),
              pytest.mark.threads(2)]

F64 = torch.float64
BG = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
ROOT = Path(__file__).resolve().parents[1]


def rel(a, b):
    return ((a - b).norm() / b.norm().clamp_min(1e-300)).item()


def with_hard_cases(g: Gaussians, cams: Cameras) -> Gaussians:
    """Append Gaussians behind the first camera, far off-screen, and one huge opaque one right in
    front of it (alpha clamped at 0.99 over many pixels, and early termination behind it)."""
    c2w = torch.linalg.inv(cams.viewmats[0])
    eye, forward, right = c2w[:3, 3], c2w[:3, 2], c2w[:3, 0]
    means = torch.stack([eye - 0.5 * forward, eye + 2 * forward + 30 * right,
                         eye + 1.2 * forward + 0.02 * right])
    extra = Gaussians(means, torch.log(torch.tensor([[0.05] * 3, [0.05] * 3, [0.15, 0.12, 0.14]],
                                                    dtype=g.means.dtype)),
                      torch.tensor([[1.0, 0, 0, 0], [0.9, 0.1, 0.2, 0], [0.7, 0.3, -0.2, 0.4]],
                                   dtype=g.means.dtype),
                      torch.tensor([2.0, 2.0, 8.0], dtype=g.means.dtype),
                      torch.rand(3, 1, 3, dtype=g.means.dtype, generator=torch.Generator().manual_seed(1)),
                      g.shN[:3].clone())
    return Gaussians.cat([g, extra])


def render_and_grads(gaussians, cams, backend, tile_size=8, sh_degree=None):
    g = gaussians.clone().requires_grad_()
    out = render(g, cams, background=BG, sh_degree=sh_degree,
                 settings=RenderSettings(backend=backend, tile_size=tile_size, chunk=16))
    w = torch.linspace(0.5, 1.5, 3, dtype=F64)
    loss = (out.rgb * w).square().sum() + (out.alpha * 0.7).sum() + 0.1 * out.depth.sum()
    loss.backward()
    return out, {k: v.grad for k, v in g.params().items()}


@pytest.mark.parametrize("seed,n,size,opacity,tile_size", [
    (0, 300, (40, 33), (0.2, 0.9), 8),      # size not a multiple of the tile
    (1, 500, (48, 48), (0.5, 0.999), 16),   # dense, opaque: early termination, 0.99 clamps
    (2, 150, (37, 29), (0.05, 0.4), 4),     # faint: nothing terminates
])
def test_compiled_matches_dense_and_tiles_images_and_every_gradient(seed, n, size, opacity,
                                                                    tile_size):
    cams = orbit_cameras(2, *size, dtype=F64, radius=2.6, phase=0.3 * seed)
    g = with_hard_cases(random_scene(n, seed=seed, sh_degree=3, dtype=F64, opacity_range=opacity),
                        cams)
    fast, fast_grads = render_and_grads(g, cams, "compiled", tile_size)
    for oracle in ("dense", "tiles"):
        ref, ref_grads = render_and_grads(g, cams, oracle, tile_size)
        assert rel(fast.rgb, ref.rgb) < 1e-10, oracle
        assert rel(fast.alpha, ref.alpha) < 1e-10, oracle
        assert rel(fast.depth, ref.depth) < 1e-10, oracle
        for name, grad in ref_grads.items():
            assert grad.norm() > 0, name
            assert rel(fast_grads[name], grad) < 1e-10, f"{name} vs {oracle}"


def test_hard_cases_are_exercised():
    """The appended Gaussians really are behind the camera, off-screen, and clamped at 0.99."""
    cams = orbit_cameras(1, 40, 40, dtype=F64)
    g = with_hard_cases(random_scene(50, seed=0, dtype=F64), cams)
    proj = project(g, cams.viewmats[0], cams.Ks[0], 40, 40)
    assert proj.depths[-3] < 0 and proj.radii[-3] == 0
    assert proj.radii[-2] == 0  # off-screen
    assert proj.opacities[-1] * 1.0 > 0.99 and proj.radii[-1] > 10


def test_compiled_compositor_gradcheck_float64():
    gen = torch.Generator().manual_seed(4)
    n, w, h = 12, 13, 11
    means2d = (torch.rand(n, 2, generator=gen, dtype=F64) * torch.tensor([w, h], dtype=F64))
    conics = torch.stack([0.15 + 0.1 * torch.rand(n, generator=gen, dtype=F64),
                          0.03 * torch.randn(n, generator=gen, dtype=F64),
                          0.15 + 0.1 * torch.rand(n, generator=gen, dtype=F64)], -1)
    opac = 0.3 + 0.6 * torch.rand(n, generator=gen, dtype=F64)
    feats = torch.rand(n, 4, generator=gen, dtype=F64)
    radii = torch.full((n,), 9, dtype=torch.long)
    depths = torch.rand(n, generator=gen, dtype=F64)

    def fn(m, c, o, f):
        image, alpha = rasterize_compiled(m, c, o, f, radii, depths, w, h, tile_size=4)
        return image, alpha

    inputs = tuple(x.clone().requires_grad_() for x in (means2d, conics, opac, feats))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("sh_degree", [None, 1])
def test_compiled_fisher_equals_torch_fisher_and_autograd_jacobian(sh_degree):
    """Every parameter group, the stored SH degree (3) and a lower active one."""
    g = random_scene(40, seed=5, sh_degree=3, dtype=F64, opacity_range=(0.3, 0.999))
    cams = orbit_cameras(2, 12, 10, dtype=F64, radius=2.4)
    spec = FisherSpec(sh_degree=sh_degree)
    fast = view_fisher(g, cams, BG, spec, RenderSettings(backend="compiled", tile_size=4))
    torch_path = view_fisher(g, cams, BG, spec, RenderSettings(backend="tiles", tile_size=4))
    leaves = g.clone()
    names = list(PARAM_GROUPS)
    for c in range(len(cams)):
        one = Cameras(cams.viewmats[c:c + 1], cams.Ks[c:c + 1], cams.width, cams.height)

        def image(*params):
            out = render(Gaussians(*params), one, BG, sh_degree,
                         RenderSettings(backend="dense", tile_size=4))
            return out.rgb.reshape(-1)

        params = tuple(getattr(leaves, k) for k in ("means", "log_scales", "quats",
                                                    "logit_opacities", "sh0", "shN"))
        jac = torch.autograd.functional.jacobian(image, params, vectorize=True)
        brute = torch.cat([j.reshape(j.shape[0], len(g), -1).square().sum(0) for j in jac], 1)
        assert rel(fast[c], brute) < 1e-10, f"camera {c}"
        assert rel(fast[c], torch_path[c]) < 1e-10, f"camera {c}"
        col = 0
        for name, j in zip(names, jac):
            width = j[0].numel() // len(g)
            assert rel(fast[c][:, col:col + width], brute[:, col:col + width]) < 1e-10, name
            col += width


def test_float32_compiled_matches_float32_torch_at_production_scale():
    """200x200, 50k Gaussians, float32 both: within float32 rounding of each other and of the
    float64 result (the compiled path does its arithmetic in float64)."""
    g32 = random_scene(50000, seed=0)
    cams32 = orbit_cameras(1, 200, 200)
    with torch.no_grad():
        fast = render(g32, cams32, settings=RenderSettings(backend="compiled"))
        slow = render(g32, cams32, settings=RenderSettings(backend="tiles"))
        exact = render(g32.to(dtype=F64), cams32.to(dtype=F64), settings=RenderSettings(backend="compiled"))
    assert rel(fast.rgb.double(), exact.rgb) < 1e-5
    assert rel(slow.rgb.double(), exact.rgb) < 1e-4
    assert (fast.rgb - slow.rgb).abs().max() < 1e-3


def test_kernels_use_the_thread_count_torch_was_given():
    g = random_scene(200, seed=0)
    cams = orbit_cameras(1, 24, 24)
    import numba
    for threads in (1, 2):
        torch.set_num_threads(threads)
        render(g, cams, settings=RenderSettings(backend="compiled"))
        assert torch.get_num_threads() == threads  # loading and running the kernels keep it
        assert compiled.use_threads() == min(threads, numba.config.NUMBA_NUM_THREADS)
        if threads > 1:
            assert numba.get_num_threads() == compiled.use_threads()


def test_backward_is_deterministic():
    g = random_scene(3000, seed=1).requires_grad_()
    cams = orbit_cameras(1, 64, 64)
    grads = []
    for _ in range(2):
        out = render(g, cams, settings=RenderSettings(backend="compiled"))
        grads.append(torch.autograd.grad(out.rgb.square().sum(), g.means)[0])
    assert torch.equal(grads[0], grads[1])


def _run_python(code: str, **env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, **env}, timeout=300)


FALLBACK_PROBE = """
import sys, warnings, torch
{prelude}
from pipeline.splat import RenderSettings, render
from pipeline.splat.scenes import orbit_cameras, random_scene
g, cams = random_scene(100, seed=0, dtype=torch.float64), orbit_cameras(2, 16, 16, dtype=torch.float64)
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    auto = render(g, cams).rgb
    render(g, cams)
tiles = render(g, cams, settings=RenderSettings(backend="tiles")).rgb
print(len([w for w in caught if "compiled CPU backend unavailable" in str(w.message)]))
print(caught[0].message if caught else "")
print(bool(torch.equal(auto, tiles)))
"""


@pytest.mark.parametrize("how,prelude,env", [
    ("numba missing", "sys.modules['numba'] = None", {}),
    ("disabled", "", {compiled.DISABLE_ENV: "1"}),
])
def test_fallback_to_the_torch_path_warns_once_and_renders(how, prelude, env):
    done = _run_python(FALLBACK_PROBE.format(prelude=prelude), **env)
    assert done.returncode == 0, done.stderr
    count, message, equal = done.stdout.strip().splitlines()
    assert count == "1", how
    assert "tiles" in message, message
    assert equal == "True"


def test_compiled_backend_asked_for_but_unavailable_is_a_clear_error():
    code = ("import sys; sys.modules['numba'] = None\n"
            "from pipeline.splat import RenderSettings, render\n"
            "from pipeline.splat.scenes import orbit_cameras, random_scene\n"
            "render(random_scene(10), orbit_cameras(1, 8, 8), settings=RenderSettings(backend='compiled'))")
    done = _run_python(code)
    assert done.returncode != 0
    assert "backend 'compiled' cannot load" in done.stderr


def projection_cases(dtype=F64):
    """Random Gaussians around and behind a camera, many outside 1.3x the half field of view (the
    clamp of J), one right at the near plane with a huge 2D covariance (culled as not finite)."""
    cams = orbit_cameras(1, 60, 50, dtype=dtype, radius=2.5)
    g = random_scene(400, seed=3, sh_degree=3, dtype=dtype, extent=2.5)
    c2w = torch.linalg.inv(cams.viewmats[0])
    near_plane = Gaussians(c2w[None, :3, 3] + 0.0101 * c2w[None, :3, 2],
                           torch.full((1, 3), 12.0, dtype=dtype), g.quats[:1], g.logit_opacities[:1],
                           g.sh0[:1], g.shN[:1])
    return Gaussians.cat([g, near_plane]), cams


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_compiled_projection_matches_torch_projection_values_and_gradients(sh_degree):
    g, cams = projection_cases()
    proj_t = project(g, cams.viewmats[0], cams.Ks[0], 60, 50, sh_degree)
    x_over_z = proj_t.means2d[:, 0] - cams.Ks[0, 0, 2]
    assert (proj_t.depths < 0).any() and (x_over_z.abs() / cams.Ks[0, 0, 0] > 1.3 * 30 / cams.Ks[0, 0, 0]).any()
    results = {}
    for name, fn in (("torch", project), ("compiled", compiled.project_compiled)):
        leaves = g.clone().requires_grad_()
        proj = fn(leaves, cams.viewmats[0], cams.Ks[0], 60, 50, sh_degree)
        gen = torch.Generator().manual_seed(0)
        loss = sum((x * torch.randn(x.shape, generator=gen, dtype=F64)).sum()
                   for x in (proj.means2d, proj.conics, proj.depths, proj.colors, proj.opacities))
        results[name] = (proj, torch.autograd.grad(loss, list(leaves.params().values())))
    (pt, gt), (pc, gc) = results["torch"], results["compiled"]
    assert torch.equal(pc.radii, pt.radii)
    assert pt.radii[-1] == 0
    for field in ("means2d", "conics", "depths", "colors", "opacities"):
        assert rel(getattr(pc, field), getattr(pt, field)) < 1e-12, field
    for name, a, b in zip(g.params(), gc, gt):
        if name == "shN" and sh_degree == 0:
            assert a.abs().max() == 0 and b.abs().max() == 0
            continue
        assert rel(a, b) < 1e-10, name


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_projection_of_the_visible_colours_equals_the_full_projection_where_visible(dtype):
    """The fused paths' projection computes the colour and conic of visible Gaussians only (and
    culls most others before building their covariance); every other output equals
    ``project_compiled``'s to the bit, and so does every visible colour and conic."""
    g, cams = projection_cases()
    g = Gaussians(**{k: v.to(dtype) for k, v in g.params().items()})
    full = compiled.project_compiled(g, cams.viewmats[0], cams.Ks[0], 60, 50, 3)
    arrays = tuple(compiled.to_numpy(v) for v in g.params().values())
    part = compiled.project_visible(arrays, cams.viewmats[0], cams.Ks[0], 60, 50, 3, 0.01, 1)
    visible = full.radii > 0
    assert visible.any() and (~visible).any()
    for field in ("means2d", "depths", "radii", "opacities"):
        assert getattr(part, field).dtype == getattr(full, field).dtype, field
        assert torch.equal(getattr(part, field), getattr(full, field)), field
    for field in ("colors", "conics"):
        got, want = getattr(part, field), getattr(full, field)
        assert got.dtype == dtype
        assert torch.equal(got[visible], want[visible]), field
        assert (got[~visible] == 0).all() and (want[~visible] != 0).any(), field


@pytest.mark.parametrize("view_scale", [1.0, 1.7])
def test_a_gaussian_culled_before_its_covariance_is_culled_by_the_full_rule(view_scale):
    """``_surely_off_image`` bounds the radius from the camera-space mean, the largest scale and
    the view's stretch: whenever it culls, the full rule (covariance, eigenvalue, radius, on-image
    test) must give radius 0, on Gaussians of every size just off every edge of the image, behind
    the camera and past the clamped field of view, for a rigid view and a scaled one (a view
    matrix that is not a rotation). And it must cull most of the far ones."""
    import numpy as np
    pk = compiled.projection_kernels()
    cams = orbit_cameras(1, 60, 50, dtype=F64, radius=2.5)
    view = cams.viewmats[0].clone()
    view[:3, :3] *= view_scale
    rng = np.random.default_rng(11)
    n = 20000
    cam_means = np.stack([rng.uniform(-4, 4, n), rng.uniform(-4, 4, n), rng.uniform(-1, 4, n)], 1)
    c2w = torch.linalg.inv(view).numpy()
    means = cam_means @ c2w[:3, :3].T + c2w[:3, 3]
    log_scales = rng.uniform(np.log(1e-3), np.log(2.0), (n, 3))
    quats = rng.normal(size=(n, 4))
    arrays = (means, log_scales, quats, rng.normal(size=n), rng.normal(size=(n, 1, 3)),
              rng.normal(size=(n, 15, 3)))
    camera = compiled.kernel_camera(view, cams.Ks[0], 60, 50, 3, 0.01)
    _, _, _, radii, _, _ = pk.project_forward(*arrays, *camera, 1, True)  # the full rule
    stretch = pk._view_stretch(camera[0])
    surely = np.array([pk._surely_off_image(g, *(camera[0][:3, :3] @ means[g] + camera[0][:3, 3]),
                                            log_scales, camera[1], 60, 50, 0.01, stretch)
                       for g in range(n)])
    assert not (surely & (radii > 0)).any()
    culled = radii == 0
    assert (radii > 0).sum() > 500 and surely.sum() > 0.6 * culled.sum()


@pytest.mark.parametrize("sh_degree", [None, 2])
def test_compiled_feature_jacobian_matches_autograd(sh_degree):
    from pipeline.fisher.features import feature_jacobian, feature_jacobian_compiled
    g, cams = projection_cases()
    for groups in (PARAM_GROUPS, ("means", "quats", "sh0")):
        args = (g, cams.viewmats[0], cams.Ks[0], 60, 50, groups, sh_degree, 0.01)
        a, b = feature_jacobian_compiled(*args).dense(), feature_jacobian(*args).dense()
        assert a.shape == b.shape
        assert rel(a, b) < 1e-10, groups


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_radix_depth_order_equals_a_stable_argsort(dtype):
    from pipeline.splat.kernels import depth_order
    gen = torch.Generator().manual_seed(0)
    depths = torch.randn(5000, generator=gen, dtype=dtype) * 3
    depths[::7] = depths[3]  # ties keep index order
    depths[10:20] = torch.tensor([-0.0, 0.0, 1e-30, -1e-30, 1e30, -1e30, 2.5, 2.5, -2.5, 0.0],
                                 dtype=dtype)
    order = torch.from_numpy(depth_order(depths.numpy()))
    assert torch.equal(order, torch.argsort(depths, stable=True))


ONE_THREAD_PROBE = """
import time, torch
torch.set_num_threads(1)
from pipeline.splat import RenderSettings, render
from pipeline.splat.scenes import orbit_cameras, random_scene
g, cams = random_scene(3000, seed=0).requires_grad_(), orbit_cameras(1, 48, 48)
render(g, cams).rgb.sum().backward()  # loads the kernels
threads_after_load = torch.get_num_threads()
wall, cpu = time.perf_counter(), time.process_time()
for _ in range(60):
    render(g, cams).rgb.sum().backward()
    time.sleep(0.002)
print(threads_after_load, time.process_time() - cpu, time.perf_counter() - wall)
"""


def test_a_one_thread_job_stays_on_one_thread():
    """Loading numba's OpenMP pool must not raise torch's thread count (it did: every torch op of
    a one-thread Ray job then ran on two threads), and no pool thread may burn CPU beside the job:
    the process's CPU time stays within its wall time."""
    done = _run_python(ONE_THREAD_PROBE)
    assert done.returncode == 0, done.stderr
    threads, cpu, wall = done.stdout.split()
    assert threads == "1"
    assert float(cpu) <= 1.1 * float(wall), f"CPU {cpu} s over wall {wall} s: another thread ran"


def test_walked_row_sums_equal_the_dense_sums_bit_for_bit_and_a_brute_force_sum():
    import numpy as np
    kernels = compiled.load()
    rng = np.random.default_rng(3)
    n, tiles = 50, 12
    counts = rng.integers(0, 40, size=tiles)
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
    longest = rng.integers(0, counts + 1)  # the walked prefix of each tile's list
    gauss_ids = rng.choice(np.arange(5, 40), size=counts.sum())  # 0-4 and 40-49: never listed
    rows = rng.normal(size=(counts.sum(), 7)) * 10.0 ** rng.integers(-8, 8, size=(counts.sum(), 1))
    walked = np.concatenate([offsets[t] + np.arange(longest[t]) for t in range(tiles)])
    ids, sums = kernels.sum_walked_rows(gauss_ids, offsets, longest, rows, n)
    assert np.array_equal(ids, np.unique(gauss_ids[walked]))
    assert np.array_equal(sums, kernels.sum_rows(gauss_ids[walked], rows[walked], n, rows)[ids])
    brute = np.zeros((n, 7))
    for r in walked:  # row order, one row at a time
        brute[gauss_ids[r]] += rows[r]
    assert np.array_equal(sums, brute[ids])
    empty_ids, empty = kernels.sum_walked_rows(gauss_ids, offsets, np.zeros_like(longest), rows, n)
    assert empty_ids.shape == (0,) and empty.shape == (0, 7)


@pytest.mark.parametrize("channel_summed", [False, True])
def test_one_pass_walk_gives_the_fisher_rows_of_the_forward_then_backward_walks(channel_summed):
    """``walk_fisher`` (forward and Fisher walks per tile, each pair's alpha kept) against the two
    kernels it replaces (``composite_forward`` + ``walked_rows`` + ``fisher_rows``): the same walked
    intersections and per-Gaussian sums to float rounding, with early termination, clamped alpha
    and off-screen Gaussians; one thread and two give the same bits."""
    import numpy as np
    kernels = compiled.load()
    cams = orbit_cameras(3, 30, 26, dtype=F64, radius=2.5)
    g = with_hard_cases(random_scene(300, seed=7, sh_degree=2, dtype=F64,
                                     opacity_range=(0.3, 0.999)), cams)
    background = np.array([0.3, 0.6, 0.9])
    for c in range(len(cams)):
        proj = compiled.project_compiled(g, cams.viewmats[c], cams.Ks[c], 30, 26)
        bins = compiled.CompiledBins(proj.means2d, proj.conics, proj.opacities, proj.radii,
                                     proj.depths, 30, 26, 8)
        colors = compiled.to_numpy(proj.colors.detach())
        _, final, walked = bins.forward(np.empty((colors.shape[0], 0)), 1)
        row_start, row_ids = bins.walked_rows(walked)
        rows = kernels.fisher_rows(bins.gauss_ids, bins.offsets, row_start, row_ids.shape[0],
                                   bins.packed, colors, final, walked, background, bins.tiles_x,
                                   8, channel_summed, 1)
        want_ids = np.unique(row_ids)
        want = kernels.sum_rows(row_ids, rows, len(g), rows)[want_ids]
        results = []
        for workers in (1, 2):
            longest, fused_rows = kernels.walk_fisher(
                bins.gauss_ids, bins.offsets, bins.counts, bins.packed, colors, background, 30, 26,
                bins.tiles_x, 8, channel_summed, workers)
            assert np.array_equal(np.diff(np.append(row_start, row_ids.shape[0])), longest)
            results.append(kernels.sum_walked_rows(bins.gauss_ids, bins.offsets, longest,
                                                   fused_rows, len(g)))
        (ids, got), (ids2, got2) = results
        assert np.array_equal(ids, want_ids) and np.array_equal(ids, ids2)
        assert np.array_equal(got, got2)
        scale = np.abs(want).max(axis=0) + 1e-300
        assert (np.abs(got - want) / scale).max() < 1e-12, c
        if c == 0:  # the huge opaque Gaussian in front of camera 0 ends walks early
            assert (longest < bins.counts).any(), "no walk ended early: the case is too easy"


def _span_cases():
    """Packed rows of random and adversarial Gaussians: elongated and rotated (tiny determinant),
    tiny and huge, means far off the tile, opacity at and around the alpha threshold."""
    import numpy as np
    rng = np.random.default_rng(7)
    n = 4000
    means2d = rng.uniform(-40, 56, size=(n, 2))
    angle = rng.uniform(0, np.pi, n)
    s1 = np.exp(rng.uniform(np.log(0.05), np.log(60), n))
    s2 = s1 * np.exp(rng.uniform(np.log(1e-4), 0, n))  # down to 1e4:1 elongation
    cos, sin = np.cos(angle), np.sin(angle)
    # Sigma = R diag(s1^2, s2^2) R^T, conic = Sigma^-1
    sxx = cos ** 2 * s1 ** 2 + sin ** 2 * s2 ** 2
    syy = sin ** 2 * s1 ** 2 + cos ** 2 * s2 ** 2
    sxy = cos * sin * (s1 ** 2 - s2 ** 2)
    det = sxx * syy - sxy ** 2
    conics = np.stack([syy / det, -sxy / det, sxx / det], 1)
    alpha_min = 1 / 255
    edges = [alpha_min, alpha_min * (1 + 1e-9), alpha_min * (1 - 1e-9), 1.0, 0.0, 1e-3]
    opacities = np.concatenate([rng.uniform(0.01, 1, n - len(edges)), edges])
    return compiled.load().pack(means2d, conics, opacities)


def test_a_pairs_pixel_box_holds_every_pixel_it_reaches():
    """The box of ``pack`` (ex, ey), cut to a tile by ``_span``, is where the walks look for a
    Gaussian's pixels: every pixel ``_pair`` does not skip must lie inside it (brute force over
    whole tiles; a missed pixel would silently drop part of the image and its gradients), and on
    typical Gaussians it is much smaller than the tile."""
    k = compiled.load()
    packed = _span_cases()
    tile, width, height = 8, 53, 45  # edge tiles cut by the image
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    inside = total = reached = 0
    for g in range(packed.shape[0]):
        row = packed[g]
        for t in range(tiles_x * tiles_y):
            x0, y0 = (t % tiles_x) * tile, (t // tiles_x) * tile
            tw, th = min(tile, width - x0), min(tile, height - y0)
            lx0, lx1 = k._span(row[0], row[7], x0, tw)
            ly0, ly1 = k._span(row[1], row[8], y0, th)
            assert 0 <= lx0 <= lx1 <= tw and 0 <= ly0 <= ly1 <= th
            for ly in range(th):
                for lx in range(tw):
                    alpha = k._pair(x0 + lx + 0.5, y0 + ly + 0.5, row)[0]
                    total += 1
                    if alpha != 0.0:
                        reached += 1
                        assert lx0 <= lx < lx1 and ly0 <= ly < ly1, (g, t, lx, ly, row)
            inside += (lx1 - lx0) * (ly1 - ly0)
    assert reached > 1000  # the cases reach pixels at all
    assert inside < 0.25 * total  # and the box cuts most of the walk


def test_span_edges_no_box_and_nothing_reachable():
    """An infinite extent (no box) or a NaN centre spans the whole tile row; a negative extent
    (no pixel can reach the threshold) spans none; a box past either end is cut to the tile."""
    import math
    k = compiled.load()
    assert k._span(3.0, math.inf, 0, 8) == (0, 8)
    assert k._span(math.nan, 2.0, 0, 8) == (0, 8)
    assert k._span(3.0, -1.0, 0, 8)[1] == k._span(3.0, -1.0, 0, 8)[0]
    assert k._span(-50.0, 2.0, 0, 8) == (0, 0)
    assert k._span(100.0, 2.0, 0, 8)[0] == k._span(100.0, 2.0, 0, 8)[1]
    assert k._span(12.5, 1.0, 8, 8) == (3, 6)  # centres 11.5, 12.5, 13.5 within 1.0 of 12.5
    assert k._span(12.5, 0.99, 8, 8) == (4, 5)


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_one_pass_packing_equals_pack_and_rects_where_a_tile_lists_the_gaussian(workers):
    """``pack_rects`` (the bins' packing, threaded, culled Gaussians skipped) against ``pack`` and
    ``alpha_tile_rects`` run over every Gaussian: the same rects for all, the same packed row
    for every Gaussian some tile lists; ``listed`` finds exactly those."""
    import numpy as np
    k = compiled.load()
    full = _span_cases()
    rng = np.random.default_rng(3)
    means2d, conics, opacities = full[:, 0:2].copy(), full[:, 2:5].copy(), full[:, 5].copy()
    radii = np.where(rng.random(full.shape[0]) < 0.2, rng.integers(-1, 1, size=full.shape[0]),
                     rng.integers(1, 40, size=full.shape[0]))  # a fifth culled (0 and -1)
    packed, rects = k.pack_rects(means2d, conics, opacities, radii, 7, 6, 8, workers)
    expected_rects = k.alpha_tile_rects(full, radii, 7, 6, 8)
    np.testing.assert_array_equal(rects, expected_rects)
    ids = k.listed(rects)
    nonempty = np.flatnonzero((rects[:, 1] > rects[:, 0]) & (rects[:, 3] > rects[:, 2]))
    np.testing.assert_array_equal(ids, nonempty)
    assert 100 < ids.size < full.shape[0] - 100  # some listed, some culled or off the tiles
    np.testing.assert_array_equal(packed[radii > 0], full[radii > 0])  # every block's every row
    assert not packed[radii <= 0].any()


def test_bins_from_the_listed_gaussians_equal_bins_from_all():
    """The bins sort only the listed Gaussians by depth (the cut of the stable order): the tile
    lists must equal those of ``bin_tiles`` given the stable order of every Gaussian."""
    import numpy as np
    k = compiled.load()
    full = _span_cases()
    rng = np.random.default_rng(4)
    n = full.shape[0]
    radii = rng.integers(0, 30, size=n)
    depths = rng.choice(np.linspace(0.5, 3.0, 50), size=n).astype(np.float32)  # many ties
    bins = compiled.CompiledBins(full[:, 0:2], full[:, 2:5], full[:, 5], radii, depths, 53, 45, 8)
    rects = k.alpha_tile_rects(full, radii, 7, 6, 8)
    ids, offsets, counts = k.bin_tiles(rects, np.argsort(depths, kind="stable"), 7, 6)
    np.testing.assert_array_equal(bins.gauss_ids, ids)
    np.testing.assert_array_equal(bins.offsets, offsets)
    np.testing.assert_array_equal(bins.counts, counts)
