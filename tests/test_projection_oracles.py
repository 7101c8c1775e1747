"""Projection, rotation and SH against witnesses that share no code with ``pipeline.splat``:
gsplat's pure-PyTorch reference (``gsplat.cuda._torch_impl``), scipy's rotations, finite
differences of the pinhole map, quadrature on the sphere and a hand-computed pixel."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from pipeline.cameras import Cameras, look_at
from pipeline.splat import Gaussians, RenderSettings, render
from pipeline.splat.gaussians import quat_to_rotmat
from pipeline.splat.project import EPS_2D, project
from pipeline.splat.sh import eval_sh, sh_basis

gsplat_ref = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat (dev extra) not installed")

F64 = torch.float64


def off_axis_camera(seed: int, width=64, height=48):
    """A rotated camera off the origin, principal point at the image centre (3DGS's clamp rule is
    symmetric; gsplat's is the same there)."""
    gen = torch.Generator().manual_seed(seed)
    eye = (torch.rand(1, 3, generator=gen, dtype=F64) - 0.5) * 4 + torch.tensor([[0, -4.0, 1.0]], dtype=F64)
    target = (torch.rand(1, 3, generator=gen, dtype=F64) - 0.5)
    viewmat = look_at(eye, target, torch.tensor([0.1, 0.2, 1.0], dtype=F64))
    fx, fy = 70.0 + 10 * seed, 65.0 + 5 * seed
    K = torch.tensor([[[fx, 0, width / 2], [0, fy, height / 2], [0, 0, 1]]], dtype=F64)
    return Cameras(viewmat, K, width, height)


def random_gaussians(n: int, seed: int, sh_degree: int = 3) -> Gaussians:
    """Gaussians around the origin, some far outside the field of view and some behind cameras."""
    gen = torch.Generator().manual_seed(100 + seed)
    means = (torch.rand(n, 3, generator=gen, dtype=F64) - 0.5) * torch.tensor([12.0, 24.0, 6.0], dtype=F64)
    log_scales = torch.log(0.02 + 0.4 * torch.rand(n, 3, generator=gen, dtype=F64))
    quats = torch.randn(n, 4, generator=gen, dtype=F64) * 3  # unnormalised on purpose
    logits = torch.randn(n, generator=gen, dtype=F64)
    k = (sh_degree + 1) ** 2
    sh0 = torch.randn(n, 1, 3, generator=gen, dtype=F64)
    shn = 0.5 * torch.randn(n, k - 1, 3, generator=gen, dtype=F64)
    return Gaussians(means, log_scales, quats, logits, sh0, shn)


def gsplat_projection(g: Gaussians, cams: Cameras):
    covars, _ = gsplat_ref._quat_scale_to_covar_preci(g.quats, torch.exp(g.log_scales),
                                                      compute_preci=False)
    means_c, covars_c = gsplat_ref._world_to_cam(g.means, covars, cams.viewmats)
    means2d, cov2d = gsplat_ref._persp_proj(means_c, covars_c, cams.Ks, cams.width, cams.height)
    radii, means2d_f, depths, conics, _ = gsplat_ref._fully_fused_projection(
        g.means, covars, cams.viewmats, cams.Ks, cams.width, cams.height, eps2d=EPS_2D)
    return means2d_f[0], conics[0], depths[0], cov2d[0] + EPS_2D * torch.eye(2, dtype=F64), radii[0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_projection_matches_gsplat_reference(seed):
    g, cams = random_gaussians(400, seed), off_axis_camera(seed)
    ours = project(g, cams.viewmats[0], cams.Ks[0], cams.width, cams.height)
    means2d, conics, depths, cov2d, radii_gs = gsplat_projection(g, cams)
    front = depths > 0.01
    x_over_z = (ours.means2d[:, 0] - cams.width / 2) / cams.Ks[0, 0, 0]
    clamped = front & (x_over_z.abs() > 1.3 * 0.5 * cams.width / cams.Ks[0, 0, 0])
    assert clamped.sum() > 10 and (~front).sum() > 10  # the clamp and culling are exercised
    torch.testing.assert_close(ours.depths, depths, rtol=1e-12, atol=1e-12, msg="depths")
    torch.testing.assert_close(ours.means2d[front], means2d[front], rtol=1e-10, atol=1e-9,
                               msg="means2d")
    torch.testing.assert_close(ours.conics[front], conics[front], rtol=1e-9, atol=1e-12, msg="conics")
    # 3DGS's radius rule on gsplat's covariance: ceil(3 sqrt(lambda_max)) with the CUDA code's
    # floor, lambda_max = mid + sqrt(max(0.1, mid^2 - det)); 0 when culled or off the image
    a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    mid = 0.5 * (a + c)
    lam_max = mid + torch.sqrt(torch.clamp(mid * mid - (a * c - b * b), min=0.1))
    radius = torch.ceil(3 * torch.sqrt(lam_max))
    u, v = means2d.unbind(-1)
    visible = front & (u + radius > 0) & (u - radius < cams.width) & (v + radius > 0) & (v - radius < cams.height)
    expected = torch.where(visible, radius, torch.zeros_like(radius)).long()
    assert torch.equal(ours.radii, expected), "radii"
    assert torch.equal(ours.radii[~front], radii_gs.amax(-1)[~front])  # both cull behind the near plane


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_colours_match_gsplat_reference(degree):
    g, cams = random_gaussians(300, 3, sh_degree=3), off_axis_camera(3)
    ours = project(g, cams.viewmats[0], cams.Ks[0], cams.width, cams.height, sh_degree=degree)
    centre = -cams.viewmats[0, :3, :3].T @ cams.viewmats[0, :3, 3]
    ref = gsplat_ref._spherical_harmonics(degree, g.means - centre, g.sh)
    torch.testing.assert_close(ours.colors, torch.clamp_min(ref + 0.5, 0.0), rtol=1e-12, atol=1e-12)


def test_quat_to_rotmat_is_a_rotation_and_matches_scipy():
    gen = torch.Generator().manual_seed(0)
    quats = torch.randn(200, 4, generator=gen, dtype=F64) * 2
    rot = quat_to_rotmat(quats)
    eye = torch.eye(3, dtype=F64).expand(200, 3, 3)
    torch.testing.assert_close(rot @ rot.transpose(1, 2), eye, rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(200, dtype=F64), rtol=0, atol=1e-12)
    scipy_rot = Rotation.from_quat(quats[:, [1, 2, 3, 0]].numpy()).as_matrix()  # scalar last
    torch.testing.assert_close(rot, torch.from_numpy(scipy_rot), rtol=0, atol=1e-12)


def test_quat_to_rotmat_takes_any_batch_shape():
    quats = torch.randn(2, 3, 4, generator=torch.Generator().manual_seed(1), dtype=F64)
    rot = quat_to_rotmat(quats)
    assert rot.shape == (2, 3, 3, 3)
    torch.testing.assert_close(rot.reshape(6, 3, 3), quat_to_rotmat(quats.reshape(6, 4)), rtol=0, atol=0)
    torch.testing.assert_close(quat_to_rotmat(quats[1, 2]), rot[1, 2], rtol=0, atol=0)  # one quaternion [4]


@pytest.mark.parametrize("quat,matrix", [
    ((1, 0, 0, 0), [[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
    ((math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)), [[0, -1, 0], [1, 0, 0], [0, 0, 1]]),  # +90 deg about z
    ((math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0), [[1, 0, 0], [0, 0, -1], [0, 1, 0]]),  # +90 deg about x
    ((math.cos(math.pi / 4), 0, math.sin(math.pi / 4), 0), [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]),  # +90 deg about y
    ((0, 1, 0, 0), [[1, 0, 0], [0, -1, 0], [0, 0, -1]]),  # 180 deg about x
])
def test_quat_to_rotmat_known_rotations(quat, matrix):
    rot = quat_to_rotmat(torch.tensor([quat], dtype=F64) * 2.5)[0]  # scale must not matter
    torch.testing.assert_close(rot, torch.tensor(matrix, dtype=F64), rtol=0, atol=1e-12)


def test_sh_basis_is_orthonormal_on_the_sphere():
    """Gauss-Legendre in cos(theta) x uniform phi integrates products of degree <= 6 exactly."""
    nodes, weights = np.polynomial.legendre.leggauss(8)
    phi = np.arange(16) * 2 * np.pi / 16
    cz, ph = np.meshgrid(nodes, phi, indexing="ij")
    w = np.repeat(weights[:, None], 16, 1) * (2 * np.pi / 16)
    sz = np.sqrt(1 - cz ** 2)
    dirs = torch.from_numpy(np.stack([sz * np.cos(ph), sz * np.sin(ph), cz], -1).reshape(-1, 3))
    basis = torch.stack(sh_basis(3, dirs), -1)  # [Q, 16]
    gram = basis.T @ (basis * torch.from_numpy(w.reshape(-1, 1)))
    torch.testing.assert_close(gram, torch.eye(16, dtype=F64), rtol=0, atol=1e-12)


def pinhole(p_cam: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    return torch.stack([K[0, 0] * p_cam[0] / p_cam[2] + K[0, 2], K[1, 1] * p_cam[1] / p_cam[2] + K[1, 2]])


def test_conics_equal_the_finite_difference_linearisation_of_the_pinhole_map():
    """Sigma_2d = J Sigma_cam J^T + 0.3 I with J from central differences, for Gaussians inside
    the clamp; the rotation from scipy, the camera frame by hand."""
    g, cams = random_gaussians(300, 4), off_axis_camera(4)
    viewmat, K = cams.viewmats[0], cams.Ks[0]
    ours = project(g, viewmat, K, cams.width, cams.height)
    rot_c = viewmat[:3, :3]
    p_cam = g.means @ rot_c.T + viewmat[:3, 3]
    limit_x, limit_y = 1.3 * 0.5 * cams.width / K[0, 0], 1.3 * 0.5 * cams.height / K[1, 1]
    inside = (p_cam[:, 2] > 0.5) & ((p_cam[:, 0] / p_cam[:, 2]).abs() < limit_x) & \
        ((p_cam[:, 1] / p_cam[:, 2]).abs() < limit_y)
    idx = torch.nonzero(inside)[:, 0][:40]
    assert len(idx) >= 20
    h = 1e-6
    for i in idx.tolist():
        jac = torch.stack([(pinhole(p_cam[i] + h * e, K) - pinhole(p_cam[i] - h * e, K)) / (2 * h)
                           for e in torch.eye(3, dtype=F64)], dim=1)  # [2, 3]
        r = torch.from_numpy(Rotation.from_quat(g.quats[i, [1, 2, 3, 0]].numpy()).as_matrix())
        cov_world = r @ torch.diag(torch.exp(2 * g.log_scales[i])) @ r.T
        cov2d = jac @ rot_c @ cov_world @ rot_c.T @ jac.T + EPS_2D * torch.eye(2, dtype=F64)
        conic = torch.linalg.inv(cov2d)
        expected = torch.stack([conic[0, 0], conic[0, 1], conic[1, 1]])
        torch.testing.assert_close(ours.conics[i], expected, rtol=1e-6, atol=1e-9,
                                   msg=f"conic of Gaussian {i}")


def test_an_off_axis_pixel_equals_its_hand_computed_value():
    """One isotropic Gaussian at camera point (0.6, -0.3, 3); camera at the origin looking down +z
    (OpenCV). The pixel value is background (1 - alpha) + colour alpha with alpha from the EWA
    formula written out here."""
    f, w, h = 50.0, 40, 30
    cams = Cameras(torch.eye(4, dtype=F64)[None], torch.tensor([[[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]]],
                                                                dtype=F64), w, h)
    x, y, z, s, opacity = 0.6, -0.3, 3.0, 0.05, 0.7
    colour = torch.tensor([0.9, 0.2, 0.4], dtype=F64)
    g = Gaussians(torch.tensor([[x, y, z]], dtype=F64), torch.full((1, 3), math.log(s), dtype=F64),
                  torch.tensor([[1.0, 0, 0, 0]], dtype=F64), torch.logit(torch.tensor([opacity], dtype=F64)),
                  ((colour - 0.5) / 0.28209479177387814)[None, None], torch.zeros(1, 0, 3, dtype=F64))
    background = torch.tensor([0.1, 0.1, 0.1], dtype=F64)
    image = render(g, cams, background, settings=RenderSettings(backend="tiles"))
    u0, v0 = f * x / z + w / 2, f * y / z + h / 2  # 30.0, 10.0
    row, col = 11, 31  # pixel centre (31.5, 11.5)
    j = np.array([[f / z, 0, -f * x / z ** 2], [0, f / z, -f * y / z ** 2]])
    cov = s ** 2 * j @ j.T + EPS_2D * np.eye(2)
    d = np.array([col + 0.5 - u0, row + 0.5 - v0])
    alpha = opacity * math.exp(-0.5 * d @ np.linalg.inv(cov) @ d)
    expected = background * (1 - alpha) + colour * alpha
    torch.testing.assert_close(image.rgb[0, row, col], expected, rtol=1e-12, atol=1e-12)
    assert 0.05 < alpha < 0.6  # a pixel on the Gaussian's flank, off its centre


def test_gaussians_too_large_to_draw_are_culled_and_smaller_ones_drawn():
    """On the optical axis at depth 1 with scale s, M = J R S has squared norm 2 (f s)^2. Past
    MAX_VARIANCE_2D (1e15 px^2) the Gaussian is culled (radius 0, finite conic); a factor 100
    below it, it is drawn with radius 3 sqrt(lambda_max) = 3 f s."""
    from pipeline.cameras import intrinsics_from_fov
    from pipeline.splat.project import MAX_VARIANCE_2D
    K = intrinsics_from_fov(0.9, 64, 64, 1, dtype=F64)[0]
    f = K[0, 0].item()
    scales = torch.tensor([math.sqrt(100 * MAX_VARIANCE_2D / 2) / f,
                           math.sqrt(MAX_VARIANCE_2D / 100 / 2) / f], dtype=F64)
    g = Gaussians(torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=F64), torch.log(scales)[:, None].repeat(1, 3),
                  torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=F64), torch.zeros(2, dtype=F64),
                  torch.zeros(2, 1, 3, dtype=F64), torch.zeros(2, 0, 3, dtype=F64))
    proj = project(g, torch.eye(4, dtype=F64), K, 64, 64)
    assert proj.radii[0] == 0 and bool(torch.isfinite(proj.conics[0]).all())
    assert proj.radii[1] == pytest.approx(math.ceil(3 * f * scales[1].item()), abs=1)


@pytest.mark.parametrize("backend", ["tiles", "compiled"])
def test_an_active_sh_degree_above_the_stored_one_is_refused_by_name(backend):
    from pipeline.splat import compiled
    if backend == "compiled" and compiled.load() is None:
        pytest.skip(f"compiled backend unavailable: {compiled.load_error()}")
    g = random_gaussians(4, seed=0, sh_degree=1)
    cams = off_axis_camera(0)
    with pytest.raises(ValueError, match="sh_degree 2 exceeds the stored degree 1"):
        render(g, cams, sh_degree=2, settings=RenderSettings(backend=backend))


@pytest.mark.parametrize("backend", ["tiles", "compiled"])
def test_a_gaussian_exactly_on_the_near_plane_is_culled(backend):
    """The rule is 'at or behind the near plane': depth == near is culled, just beyond is drawn."""
    from pipeline.cameras import intrinsics_from_fov
    from pipeline.splat import compiled
    if backend == "compiled" and compiled.load() is None:
        pytest.skip(f"compiled backend unavailable: {compiled.load_error()}")
    near = 0.25
    depths = torch.tensor([near, near * (1 + 1e-9)], dtype=F64)
    g = Gaussians(torch.stack([torch.zeros(2, dtype=F64), torch.zeros(2, dtype=F64), depths], -1),
                  torch.full((2, 3), math.log(0.01), dtype=F64), torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=F64),
                  torch.zeros(2, dtype=F64), torch.zeros(2, 1, 3, dtype=F64), torch.zeros(2, 0, 3, dtype=F64))
    K = intrinsics_from_fov(0.9, 32, 32, 1, dtype=F64)[0]
    projector = compiled.project_compiled if backend == "compiled" else project
    proj = projector(g, torch.eye(4, dtype=F64), K, 32, 32, near=near)
    assert proj.radii[0] == 0 and proj.radii[1] > 0


def test_from_points_builds_the_documented_initial_gaussians():
    points = torch.tensor([[0.0, 1.0, 2.0], [3.0, -1.0, 0.5]], dtype=F64)
    colors = torch.tensor([[0.1, 0.5, 0.9], [1.0, 0.0, 0.25]], dtype=F64)
    g = Gaussians.from_points(points, colors, sh_degree=2, scale=torch.tensor([0.02, 0.5], dtype=F64),
                              opacity=0.3)
    assert torch.equal(g.means, points)
    assert torch.equal(g.quats, torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=F64))  # w first
    assert torch.allclose(g.scales, torch.tensor([[0.02] * 3, [0.5] * 3], dtype=F64), rtol=1e-12)
    assert torch.allclose(g.opacities, torch.full((2,), 0.3, dtype=F64), rtol=1e-12)
    # the DC term alone reproduces the colour: C0 * sh0 + 0.5
    assert torch.allclose(eval_sh(0, g.sh, torch.tensor([[0, 0, 1.0]] * 2, dtype=F64)) + 0.5, colors)
    assert g.shN.shape == (2, 8, 3) and g.shN.abs().max() == 0
    with pytest.raises(ValueError, match="^points: cannot build Gaussians from an empty point cloud$"):
        Gaussians.from_points(points[:0], colors[:0])


def test_sh_degrees_outside_0_to_3_are_refused_by_value():
    coeffs = torch.zeros(1, 25, 3, dtype=F64)
    dirs = torch.tensor([[0, 0, 1.0]], dtype=F64)
    for degree in (-1, 4):
        with pytest.raises(ValueError, match=f"sh degree must be in 0..3, got {degree}"):
            eval_sh(degree, coeffs, dirs)


def test_too_few_sh_coefficients_for_the_degree_are_refused_with_both_counts():
    dirs = torch.tensor([[0, 0, 1.0]], dtype=F64)
    with pytest.raises(ValueError, match="coeffs has 4 bases, degree 2 needs 9"):
        eval_sh(2, torch.zeros(1, 4, 3, dtype=F64), dirs)
    with pytest.raises(ValueError, match="coeffs has 9 bases, degree 3 needs 16"):
        eval_sh(3, torch.zeros(1, 9, 3, dtype=F64), dirs)
    assert eval_sh(1, torch.zeros(1, 4, 3, dtype=F64), dirs).shape == (1, 3)  # exactly enough


@pytest.mark.parametrize("shape", [(4,), (4, 2), (4, 3, 1)])
def test_means_of_the_wrong_shape_are_refused_with_the_shape(shape):
    good = random_gaussians(4, seed=0, sh_degree=0)
    with pytest.raises(ValueError, match=rf"means must be \[N, 3\], got {re_tuple(shape)}"):
        Gaussians(torch.zeros(shape, dtype=F64), good.log_scales, good.quats, good.logit_opacities,
                  good.sh0, good.shN)


def re_tuple(shape) -> str:
    import re
    return re.escape(str(tuple(shape)))


def test_from_points_defaults_and_to_dtype():
    """The documented defaults (degree 3, scale 0.01, opacity 0.1) and ``to`` converting every
    field."""
    points, colors = torch.zeros(2, 3), torch.full((2, 3), 0.5)
    g = Gaussians.from_points(points, colors)
    assert g.sh_degree == 3
    assert torch.allclose(g.scales, torch.full((2, 3), 0.01), rtol=1e-6)
    assert torch.allclose(g.opacities, torch.full((2,), 0.1), rtol=1e-6)
    g64 = g.to(dtype=F64)
    assert all(v.dtype == F64 for v in g64.params().values())
    assert torch.equal(g64.means, points.double())


@pytest.mark.parametrize("backend", ["tiles", "compiled"])
def test_a_gaussian_whose_square_only_touches_the_image_edge_is_culled(backend):
    """gsplat's rule: drawn iff u + r > 0, u - r < W, v + r > 0, v - r < H (r the integer radius).
    Off-axis past the 1.3 half-FOV clamp the radius no longer depends on the position, so a square
    can be put exactly on each edge (culled) and half a pixel inside it (drawn)."""
    from pipeline.splat import compiled
    if backend == "compiled" and compiled.load() is None:
        pytest.skip(f"compiled backend unavailable: {compiled.load_error()}")
    projector = compiled.project_compiled if backend == "compiled" else project
    K = torch.tensor([[8.0, 0, 0], [0, 8.0, 0], [0, 0, 1]], dtype=F64)  # principal point at a corner
    size = 16

    def radius_at(u, v):
        g = Gaussians(torch.tensor([[u / 8, v / 8, 1.0]], dtype=F64), torch.full((1, 3), math.log(0.6), dtype=F64),
                      torch.tensor([[1.0, 0, 0, 0]], dtype=F64), torch.zeros(1, dtype=F64),
                      torch.zeros(1, 1, 3, dtype=F64), torch.zeros(1, 0, 3, dtype=F64))
        proj = projector(g, torch.eye(4, dtype=F64), K, size, size, None, 0.01)
        assert proj.means2d[0].tolist() == [u, v]
        return int(proj.radii[0])

    r = radius_at(14.0, 14.0)  # on the image, both clamped (|u|, |v| > 1.3 * 8 px)
    assert r > 11
    for u, v in ((size + r, -r + 0.5), (-r, size + r - 0.5), (size + r - 0.5, -r), (-r + 0.5, size + r)):
        assert radius_at(float(u), float(v)) == 0, (u, v)  # one side exactly on an edge
    for u, v in ((size + r - 0.5, -r + 0.5), (-r + 0.5, size + r - 0.5)):
        assert radius_at(float(u), float(v)) == r, (u, v)  # half a pixel inside on both
