"""The tiled rasterizer against the dense oracle, finite differences and closed forms."""

import math

import pytest
import torch

from pipeline.cameras import Cameras
from pipeline.splat import Gaussians, RenderSettings, render
from pipeline.splat.project import project
from pipeline.splat.rasterize import rasterize
from pipeline.splat.reference import rasterize_dense, rasterize_loop
from pipeline.splat.scenes import orbit_cameras, random_scene

F64 = torch.float64
BG = torch.tensor([0.2, 0.5, 0.9], dtype=F64)


def rel(a, b):
    return ((a - b).norm() / b.norm().clamp_min(1e-300)).item()


def render_and_grads(gaussians, cams, backend, chunk=16, tile_size=16):
    g = gaussians.clone().requires_grad_()
    out = render(g, cams, background=BG,
                 settings=RenderSettings(backend=backend, chunk=chunk, tile_size=tile_size))
    w = torch.linspace(0.5, 1.5, 3, dtype=F64)
    loss = (out.rgb * w).square().sum() + out.alpha.sum() + 0.1 * out.depth.sum()
    loss.backward()
    return out, {k: v.grad for k, v in g.params().items()}


@pytest.mark.parametrize("seed,n,size,opacity", [
    (0, 300, (40, 33), (0.2, 0.9)),      # size not a multiple of the tile
    (1, 500, (48, 48), (0.5, 0.999)),    # dense, opaque: many pixels terminate early
    (2, 150, (37, 29), (0.05, 0.4)),     # faint: nothing terminates
])
def test_tiles_match_dense_images_and_gradients(seed, n, size, opacity):
    g = random_scene(n, seed=seed, sh_degree=3, dtype=F64, opacity_range=opacity)
    cams = orbit_cameras(2, *size, dtype=F64, radius=2.6, phase=0.3 * seed)
    fast, fast_grads = render_and_grads(g, cams, "tiles")
    dense, dense_grads = render_and_grads(g, cams, "dense")
    assert rel(fast.rgb, dense.rgb) < 1e-12
    assert rel(fast.alpha, dense.alpha) < 1e-12
    assert rel(fast.depth, dense.depth) < 1e-12
    for name, grad in dense_grads.items():
        assert grad.norm() > 0, name
        assert rel(fast_grads[name], grad) < 1e-10, name


@pytest.mark.parametrize("tile_size", [4, 8, 16])
def test_every_tile_size_and_chunk_size_matches_the_dense_oracle_at_that_tile_size(tile_size):
    """The tile size is part of the 3DGS support rule (a Gaussian reaches only the tiles its
    3-sigma square touches), so each tile size is compared with the oracle at the same size;
    the chunk size must not matter at all."""
    g = random_scene(200, seed=3, dtype=F64, opacity_range=(0.5, 0.99))
    cams = orbit_cameras(1, 40, 36, dtype=F64)
    ref, _ = render_and_grads(g, cams, "dense", tile_size=tile_size)
    for chunk in (1, 7, 64):
        out, _ = render_and_grads(g, cams, "tiles", chunk=chunk, tile_size=tile_size)
        assert rel(out.rgb, ref.rgb) < 1e-12, f"tile {tile_size}, chunk {chunk}"
        assert rel(out.alpha, ref.alpha) < 1e-12, f"tile {tile_size}, chunk {chunk}"


def test_dense_oracle_matches_literal_3dgs_loop():
    g = random_scene(40, seed=4, dtype=F64, opacity_range=(0.3, 0.999))
    cams = orbit_cameras(1, 20, 18, dtype=F64)
    proj = project(g, cams.viewmats[0], cams.Ks[0], 20, 18)
    args = (proj.means2d, proj.conics, proj.opacities, proj.colors, proj.radii, proj.depths, 20, 18)
    img_d, a_d = rasterize_dense(*args, tile_size=8)
    img_l, a_l = rasterize_loop(*args, tile_size=8)
    assert torch.allclose(img_d, img_l, atol=1e-13) and torch.allclose(a_d, a_l, atol=1e-13)


def test_compositor_gradcheck_float64():
    g = random_scene(12, seed=5, dtype=F64, opacity_range=(0.3, 0.9))
    cams = orbit_cameras(1, 12, 10, dtype=F64, radius=2.2)
    proj = project(g, cams.viewmats[0], cams.Ks[0], 12, 10)
    radii, depths = proj.radii, proj.depths.detach()
    inputs = [x.detach().clone().requires_grad_() for x in
              (proj.means2d, proj.conics, proj.opacities, proj.colors)]

    def fn(m, c, o, f):
        img, alpha = rasterize(m, c, o, f, radii, depths, 12, 10, tile_size=4, chunk=3)
        return img, alpha
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


def test_render_gradcheck_raw_parameters_float64():
    g = random_scene(6, seed=6, dtype=F64, sh_degree=1, opacity_range=(0.3, 0.8))
    cams = orbit_cameras(1, 10, 10, dtype=F64, radius=2.5)
    names = list(g.params())

    def fn(*params):
        out = render(Gaussians(**dict(zip(names, params))), cams, background=BG,
                     settings=RenderSettings(tile_size=4, chunk=4))
        return out.rgb, out.alpha
    inputs = [p.detach().clone().requires_grad_() for p in g.params().values()]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_alpha_in_unit_interval_and_colour_bounded():
    g = random_scene(2000, seed=7, opacity_range=(0.5, 0.999))
    out = render(g, orbit_cameras(2, 64, 64))
    assert out.alpha.min() >= 0 and out.alpha.max() <= 1
    assert out.alpha.max() > 0.99  # the scene is dense: some pixel is nearly opaque


def test_permuting_gaussians_leaves_the_image_unchanged():
    g = random_scene(500, seed=8, dtype=F64)
    cams = orbit_cameras(1, 48, 40, dtype=F64)
    perm = torch.randperm(len(g), generator=torch.Generator().manual_seed(0))
    a = render(g, cams).rgb
    b = render(g.permute(perm), cams).rgb
    assert torch.allclose(a, b, atol=1e-12)


def test_isotropic_gaussian_facing_camera_closed_form():
    # camera at the origin looking down +z; one isotropic Gaussian on the optical axis
    width = height = 33
    f, z, s, opacity = 40.0, 4.0, 0.05, 0.7
    k = torch.tensor([[[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]]], dtype=F64)
    cams = Cameras(torch.eye(4, dtype=F64)[None], k, width, height)
    colour = torch.tensor([0.9, 0.4, 0.1], dtype=F64)
    g = Gaussians.from_points(torch.tensor([[0.0, 0.0, z]], dtype=F64), colour[None], sh_degree=0,
                              scale=s, opacity=opacity)
    out = render(g, cams)
    var = (f * s / z) ** 2 + 0.3  # EWA footprint + dilation, pixels^2
    centre = out.rgb[0, height // 2, width // 2]  # pixel centre (16.5, 16.5) = principal point
    assert torch.allclose(centre, opacity * colour, atol=1e-12)
    assert (out.alpha[0] == out.alpha[0].max()).nonzero().tolist() == [[height // 2, width // 2]]
    for dv, du in ((0, 1), (1, 1), (0, 2)):
        expect = opacity * math.exp(-0.5 * (du * du + dv * dv) / var)
        got = out.alpha[0, height // 2 + dv, width // 2 + du].item()
        assert got == pytest.approx(expect, rel=1e-12)
    assert out.depth[0, height // 2, width // 2].item() == pytest.approx(z)


def test_gaussians_behind_the_camera_are_culled():
    g = random_scene(50, seed=9, dtype=F64)
    cams = orbit_cameras(1, 20, 20, dtype=F64, radius=0.2)  # camera inside the cloud
    out = render(g, cams)
    assert (out.radii[0] == 0).any() and torch.isfinite(out.rgb).all()


def test_checkpointed_dense_oracle_equals_plain_dense():
    g = random_scene(100, seed=10, dtype=F64)
    cams = orbit_cameras(1, 20, 17, dtype=F64)
    plain, plain_grads = render_and_grads(g, cams, "dense")
    gg = g.clone().requires_grad_()
    out = render(gg, cams, background=BG, settings=RenderSettings(backend="dense", dense_pixel_block=50))
    w = torch.linspace(0.5, 1.5, 3, dtype=F64)
    ((out.rgb * w).square().sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()
    assert rel(out.rgb, plain.rgb) < 1e-14
    assert rel(gg.means.grad, plain_grads["means"]) < 1e-12


def test_gaussians_at_equal_depth_composite_in_index_order():
    """Ties in depth keep the lower index in front (a stable order), as the literal loop composites
    them: 64 overlapping Gaussians all at depth 2, each its own colour."""
    gen = torch.Generator().manual_seed(5)
    n = 64
    means2d = torch.rand(n, 2, generator=gen, dtype=F64) * 4 + 6
    conics = torch.tensor([0.05, 0.0, 0.05], dtype=F64).repeat(n, 1)
    opacities = torch.rand(n, generator=gen, dtype=F64) * 0.3 + 0.2
    colours = torch.rand(n, 3, generator=gen, dtype=F64)
    radii = torch.full((n,), 12, dtype=torch.int64)
    depths = torch.full((n,), 2.0, dtype=F64)
    args = (means2d, conics, opacities, colours, radii, depths, 16, 16)
    loop_image, _ = rasterize_loop(*args, tile_size=4)
    tiles_image, _ = rasterize(*args, tile_size=4)
    reversed_image, _ = rasterize_loop(*(x.flip(0) for x in args[:6]), 16, 16, tile_size=4)
    assert (loop_image - reversed_image).abs().max() > 1e-3  # the order shows in the image
    assert (tiles_image - loop_image).abs().max() < 1e-12


def test_the_alpha_threshold_and_a_one_pixel_radius_as_the_3dgs_loop():
    """A Gaussian of opacity 1/255 at a pixel centre is composited there as the loop does (the
    tiles evaluate exp(log o - q), equal to the threshold up to rounding), and one of radius 1 is
    drawn: tiles against the literal loop."""
    from pipeline.splat.rasterize import ALPHA_MIN
    means2d = torch.tensor([[4.5, 4.5], [10.5, 3.5], [12.5, 12.5]], dtype=F64)  # on pixel centres
    conics = torch.tensor([[2.0, 0.0, 2.0], [0.5, 0.1, 0.4], [3.0, 0.0, 3.0]], dtype=F64)
    opacities = torch.tensor([ALPHA_MIN, 0.6, 0.8], dtype=F64)  # alpha = opacity at the centre
    colours = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    radii = torch.tensor([3, 4, 1])
    args = (means2d, conics, opacities, colours, radii, torch.tensor([1.0, 2.0, 3.0], dtype=F64), 16, 16)
    loop_image, loop_alpha = rasterize_loop(*args, tile_size=4)
    tiles_image, tiles_alpha = rasterize(*args, tile_size=4)
    assert loop_image[4, 4, 0].item() == pytest.approx(ALPHA_MIN, rel=1e-12)  # the threshold pixel
    assert loop_image[12, 12, 2].item() == pytest.approx(0.8, rel=1e-12)  # the radius-1 Gaussian
    assert (tiles_image - loop_image).abs().max() < 1e-12
    assert (tiles_alpha - loop_alpha).abs().max() < 1e-12


def test_a_gaussian_is_composited_inside_its_square_only():
    """The radius bounds where a Gaussian is drawn (tiles touched by the square of side 2r), even
    where its alpha beyond would be large: a wide Gaussian (sigma 10 px) given radius 2 lights the
    tiles of [u - 2, u + 2] x [v - 2, v + 2] only, as the literal loop says."""
    means2d = torch.tensor([[5.2, 9.7]], dtype=F64)
    conics = torch.tensor([[0.01, 0.0, 0.01]], dtype=F64)
    args = (means2d, conics, torch.tensor([0.9], dtype=F64), torch.ones(1, 3, dtype=F64),
            torch.tensor([2]), torch.tensor([1.0], dtype=F64), 16, 16)
    loop_image, _ = rasterize_loop(*args, tile_size=4)
    tiles_image, _ = rasterize(*args, tile_size=4)
    lit = loop_image[..., 0] > 0
    rows, cols = torch.nonzero(lit, as_tuple=True)
    assert (cols.min(), cols.max(), rows.min(), rows.max()) == (0, 7, 4, 11)  # tiles x 0-1, y 1-2
    assert (tiles_image - loop_image).abs().max() < 1e-12


def test_one_intersection_and_none():
    """A single Gaussian inside one tile (one tile-Gaussian pair to walk) against the loop, and a
    culled one (radius 0: nothing to walk) leaving the image empty."""
    args = (torch.tensor([[13.5, 13.5]], dtype=F64), torch.tensor([[1.0, 0.2, 1.5]], dtype=F64),
            torch.tensor([0.7], dtype=F64), torch.tensor([[0.2, 0.4, 0.8]], dtype=F64))
    rest = (torch.tensor([1.0], dtype=F64), 16, 16)
    loop_image, loop_alpha = rasterize_loop(*args, torch.tensor([1]), *rest, tile_size=4)
    tiles_image, tiles_alpha = rasterize(*args, torch.tensor([1]), *rest, tile_size=4)
    assert loop_alpha[13, 13].item() == pytest.approx(0.7, rel=1e-12)
    assert (tiles_image - loop_image).abs().max() < 1e-12 and (tiles_alpha - loop_alpha).abs().max() < 1e-12
    empty_image, empty_alpha = rasterize(*args, torch.tensor([0]), *rest, tile_size=4)
    assert not empty_image.any() and not empty_alpha.any()


@pytest.mark.parametrize("seed,opacity", [(0, (0.2, 0.7)), (1, (0.85, 0.99))])
def test_compositing_weight_list_equals_the_dense_oracle_weights(seed, opacity):
    """Every listed w = alpha T against the dense compositor rendering a one-hot feature per
    Gaussian (the oracle); opaque scenes exercise early termination. And composite() of any
    per-Gaussian values equals the production (compiled) render of them."""
    from pipeline.acquisition.rendered_stats import view_compositing_weights
    g = random_scene(12, seed=seed, dtype=F64, opacity_range=opacity)
    cam = orbit_cameras(1, 13, 11, dtype=F64, radius=2.4, phase=0.4 * seed)  # W != H, edge tiles
    settings = RenderSettings(tile_size=4, chunk=3)
    cw = view_compositing_weights(g, cam, settings)
    dense = torch.zeros(len(g), 11 * 13, dtype=F64)
    dense[cw.gaussian, cw.pixel] += cw.weight  # duplicates would add up and fail below
    for k in range(len(g)):
        onehot = torch.zeros(len(g), 1, dtype=F64)
        onehot[k] = 1
        oracle = render(g, cam, BG, settings=RenderSettings(backend="dense"), extra_features=onehot).rgb[0, ..., 3]
        assert torch.allclose(dense[k].reshape(11, 13), oracle, rtol=1e-9, atol=1e-12), f"Gaussian {k}"
    values = torch.linspace(-1.0, 2.0, len(g), dtype=F64)
    compiled = render(g, cam, BG, settings=RenderSettings(backend="compiled"), extra_features=values[:, None])
    assert torch.allclose(cw.composite(values), compiled.rgb[0, ..., 3], rtol=1e-9, atol=1e-12)
    assert torch.allclose(cw.composite(values, power=2), (dense.reshape(len(g), 11, 13).square()
                                                          * values[:, None, None]).sum(0), rtol=1e-12)
