"""Bad input to the splatting core fails with a ValueError that names the argument."""

import pytest
import torch

from pipeline.cameras import Cameras
from pipeline.splat import Gaussians, RenderSettings, render
from pipeline.splat.scenes import orbit_cameras, random_scene


def good():
    return random_scene(10, seed=0)


@pytest.mark.parametrize("field,value,match", [  # the field, the shape it needs and the one it got
    ("means", torch.zeros(10, 2), r"means must be \[N, 3\], got \(10, 2\)"),
    ("means", torch.zeros(10), r"means must be \[N, 3\], got \(10,\)"),
    ("log_scales", torch.zeros(9, 3), r"log_scales must have shape \[10, 3\], got \[9, 3\]"),
    ("quats", torch.zeros(10, 3), r"quats must have shape \[10, 4\], got \[10, 3\]"),
    ("logit_opacities", torch.zeros(10, 1), r"logit_opacities must have shape \[10\], got \[10, 1\]"),
    ("sh0", torch.zeros(10, 3), r"sh0 must have shape \[10, 1, 3\], got \[10, 3\]"),
    ("shN", torch.zeros(10, 5, 3), r"shN must be \[N, K-1, 3\] with K in \(1, 4, 9, 16\), got \[10, 5, 3\]"),
    ("shN", torch.zeros(10, 3), r"shN must be \[N, K-1, 3\] with K in \(1, 4, 9, 16\), got \[10, 3\]"),
    ("shN", torch.zeros(9, 3, 3), r"shN must be \[N, K-1, 3\] with K in \(1, 4, 9, 16\), got \[9, 3, 3\]"),
    ("shN", torch.zeros(10, 3, 2), r"shN must be \[N, K-1, 3\] with K in \(1, 4, 9, 16\), got \[10, 3, 2\]"),
])
def test_wrong_shapes(field, value, match):
    params = good().params()
    params[field] = value
    with pytest.raises(ValueError, match=match):
        Gaussians(**params)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
@pytest.mark.parametrize("field", ["means", "log_scales", "quats", "logit_opacities", "sh0", "shN"])
def test_non_finite_parameters_are_refused_by_field(field, bad):
    params = good().params()
    params[field] = params[field].clone()
    params[field].view(-1)[-1] = bad  # the last Gaussian: every row is checked, not only the first
    with pytest.raises(ValueError, match=f"^{field} contains NaN or inf$"):
        Gaussians(**params)


def test_a_zero_quaternion_is_refused():
    params = good().params()
    params["quats"] = params["quats"].clone()
    params["quats"][3] = 0.0  # one row only: the check is per Gaussian
    with pytest.raises(ValueError, match="^quats contains a zero quaternion$"):
        Gaussians(**params)


def test_nan_introduced_after_construction_is_caught_by_render():
    g = good()
    g.means.data[0, 0] = float("nan")
    with pytest.raises(ValueError, match="means"):
        render(g, orbit_cameras(1, 8, 8))


def test_non_positive_focal_length():
    cams = orbit_cameras(1, 8, 8)
    ks = cams.Ks.clone()
    ks[0, 0, 0] = 0
    with pytest.raises(ValueError, match="focal"):
        Cameras(cams.viewmats, ks, 8, 8)


def test_camera_shapes_and_size():
    cams = orbit_cameras(2, 8, 8)
    with pytest.raises(ValueError, match="viewmats"):
        Cameras(cams.viewmats[:, :3], cams.Ks, 8, 8)
    with pytest.raises(ValueError, match="Ks"):
        Cameras(cams.viewmats, cams.Ks[:1], 8, 8)
    with pytest.raises(ValueError, match="width"):
        Cameras(cams.viewmats, cams.Ks, 0, 8)


def test_empty_scene():
    empty = Gaussians(**{k: v[:0] for k, v in good().params().items()})
    with pytest.raises(ValueError, match=r"^gaussians: cannot render an empty scene \(N = 0\)$"):
        render(empty, orbit_cameras(1, 8, 8))


def test_bad_background_and_backend():
    with pytest.raises(ValueError, match=r"^background must be \[3\], got \(4,\)$"):
        render(good(), orbit_cameras(1, 8, 8), background=torch.zeros(4))
    with pytest.raises(ValueError, match=r"^backend must be one of \['auto', .*\], got 'cuda'$"):
        render(good(), orbit_cameras(1, 8, 8), settings=RenderSettings(backend="cuda"))


def test_at_sh_degree_renders_as_the_full_model_at_that_degree():
    import torch
    from pipeline.splat import render
    from pipeline.splat.scenes import orbit_cameras, random_scene
    g = random_scene(30, seed=2, dtype=torch.float64, sh_degree=3)
    cams = orbit_cameras(1, 16, 16, dtype=torch.float64)
    for degree in range(4):
        low = g.at_sh_degree(degree)
        assert low.sh_degree == degree
        assert torch.equal(render(low, cams).rgb, render(g, cams, sh_degree=degree).rgb)
    with pytest.raises(ValueError, match=r"sh degree 4 outside 0..3 \(the stored degree\)"):
        g.at_sh_degree(4)


def test_each_backend_projects_with_its_own_projector(monkeypatch):
    """``compiled`` projects in the kernels, the torch backends with ``project`` (equal values, so
    only the calls tell a compiled render served by the torch projector)."""
    import importlib

    from pipeline.splat import compiled
    render_module = importlib.import_module("pipeline.splat.backend")  # the package exports render()
    if compiled.load() is None:
        pytest.skip(f"compiled backend unavailable: {compiled.load_error()}")
    calls = []
    for name in ("project", "project_compiled"):
        original = getattr(render_module, name)
        monkeypatch.setattr(render_module, name, lambda *a, _f=original, _n=name: calls.append(_n) or _f(*a))
    cams = orbit_cameras(2, 8, 8)
    render(good(), cams, settings=RenderSettings(backend="compiled"))
    assert calls == ["project_compiled"] * 2
    calls.clear()
    render(good(), cams, settings=RenderSettings(backend="tiles"))
    assert calls == ["project"] * 2


def test_render_passes_the_settings_performance_knobs_to_its_compositor(monkeypatch):
    """Tile size, chunk and the dense pixel block never change a value (tested elsewhere), so only
    the compositor's arguments show that a render honours them."""
    import importlib
    render_module = importlib.import_module("pipeline.splat.backend")
    seen = {}
    for name, fn in list(render_module.COMPOSITORS.items()):
        monkeypatch.setitem(render_module.COMPOSITORS, name,
                            lambda *a, _f=fn, _n=name, **kw: (seen.setdefault(_n, kw), _f(*a, **kw))[1])
    cams = orbit_cameras(1, 8, 8)
    render(good(), cams, settings=RenderSettings(backend="tiles", tile_size=4, chunk=5))
    render(good(), cams, settings=RenderSettings(backend="dense", tile_size=4, dense_pixel_block=7))
    render(good(), cams, settings=RenderSettings(backend="loop", tile_size=2))
    assert seen == {"tiles": {"tile_size": 4, "chunk": 5}, "dense": {"tile_size": 4, "pixel_block": 7},
                    "loop": {"tile_size": 2}}


@pytest.mark.parametrize("backend", ["tiles", "dense", "auto"])
def test_cameras_are_taken_to_the_gaussians_dtype(backend):
    """float32 cameras (the loaders' dtype) render float64 Gaussians as the same cameras in float64."""
    g = random_scene(6, seed=3, dtype=torch.float64)
    cams = orbit_cameras(1, 8, 8)
    settings = RenderSettings(backend=backend)
    out = render(g, cams, settings=settings).rgb
    assert out.dtype == torch.float64
    assert torch.equal(out, render(g, cams.to(dtype=torch.float64), settings=settings).rgb)
