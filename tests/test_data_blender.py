"""Blender reader and the generated scene: layout, determinism, pose conventions, bad input."""

import json
import shutil

import pytest
import torch

from pipeline.data.blender import read_blender
from pipeline.data.images import DataError
from pipeline.data.load import load_scene
from pipeline.data.synthetic import RADIUS, generate, sample_directions
from tests.conftest import shared_scene


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    return generate(tmp_path_factory.mktemp("gen") / "scene", seed=3, size=32, n_train=6, n_test=4)


def project(cams, points):
    p = points @ cams.viewmats[:, :3, :3].transpose(1, 2) + cams.viewmats[:, None, :3, 3]
    uv = p @ cams.Ks.transpose(1, 2)
    return uv[..., :2] / uv[..., 2:], p[..., 2]


def test_generated_scene_reads_back_with_expected_counts(small_scene):
    scene = read_blender(small_scene)
    assert {k: len(v) for k, v in scene.splits.items()} == {"train": 6, "test": 4}
    img = scene.split("train").images[0]
    assert img.shape == (32, 32, 3) and 0 <= img.min() and img.max() <= 1
    assert (img < 0.99).any() and (img == 1).any()  # object over a white background


def test_generation_is_deterministic(small_scene, tmp_path):
    again = generate(tmp_path / "again", seed=3, size=32, n_train=6, n_test=4)
    for name in ("train/r_0.png", "test/r_3.png", "transforms_train.json"):
        assert (small_scene / name).read_bytes() == (again / name).read_bytes()
    other = generate(tmp_path / "other", seed=4, size=32, n_train=1, n_test=1)
    assert (other / "train/r_0.png").read_bytes() != (small_scene / "train/r_0.png").read_bytes()


def test_pose_convention_of_reader_matches_generator(small_scene):
    cams = read_blender(small_scene).split("train").cameras
    eyes = sample_directions(6, seed=3 * 2 + 1).float() * RADIUS
    assert torch.allclose(cams.centers, eyes, atol=1e-4)
    uv, z = project(cams, torch.tensor([[0.0, 0, 0], [0, 0, 1.0]]))
    assert torch.allclose(uv[:, 0], torch.full((6, 2), 16.0), atol=1e-3)  # looks at the origin
    assert (z > 0).all()
    assert (uv[:, 1, 1] < 16).all()  # world up appears above the image centre


def test_rendered_object_lies_inside_its_projected_bounding_box(small_scene):
    scene = read_blender(small_scene)
    cams, images = scene.split("train").cameras, scene.split("train").images.stack()
    corners = torch.tensor([[x, y, z] for x in (-0.9, 0.9) for y in (-1.05, 0.9)
                            for z in (-0.75, 0.95)])
    uv, _ = project(cams, corners)
    for i in range(len(cams)):
        rows, cols = torch.nonzero((images[i] < 0.98).any(-1), as_tuple=True)
        assert len(rows) > 20
        lo, hi = uv[i].min(0).values - 1, uv[i].max(0).values + 1
        assert (cols + 0.5 >= lo[0]).all() and (cols + 0.5 <= hi[0]).all()
        assert (rows + 0.5 >= lo[1]).all() and (rows + 0.5 <= hi[1]).all()
        # and it fills a good part of that box (a mirrored pose would leave it elsewhere)
        box_area = (hi - lo).prod()
        assert len(rows) > 0.2 * box_area


def test_lego_reader_and_downscale():
    scene = read_blender(shared_scene("blender", "lego"), width=50)
    train = scene.split("train")
    assert len(train) == 100 and len(scene.split("test")) == 200
    assert train.images[0].shape == (50, 50, 3)
    focal = 0.5 * 50 / torch.tan(torch.tensor(0.6911112070083618 / 2))
    assert train.cameras.Ks[0, 0, 0].item() == pytest.approx(focal.item(), rel=1e-6)


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


def test_missing_folder_and_file(tmp_path, small_scene):
    with pytest.raises(DataError, match="does not exist"):
        read_blender(tmp_path / "nope")
    bad = _copy(small_scene, tmp_path / "s")
    (bad / "transforms_train.json").unlink()
    with pytest.raises(DataError, match="transforms_train.json"):
        read_blender(bad)


def test_malformed_json_names_the_file(tmp_path, small_scene):
    bad = _copy(small_scene, tmp_path / "s")
    (bad / "transforms_test.json").write_text("{not json")
    with pytest.raises(DataError, match="transforms_test.json.*malformed"):
        read_blender(bad)


def test_missing_frame_image_and_empty_split(tmp_path, small_scene):
    bad = _copy(small_scene, tmp_path / "s")
    (bad / "train" / "r_2.png").unlink()
    with pytest.raises(DataError, match="frame 2"):
        read_blender(bad)
    bad2 = _copy(small_scene, tmp_path / "s2")
    data = json.loads((bad2 / "transforms_test.json").read_text())
    data["frames"] = []
    (bad2 / "transforms_test.json").write_text(json.dumps(data))
    with pytest.raises(DataError, match="no frames"):
        read_blender(bad2)


def test_images_of_inconsistent_size_are_named(tmp_path, small_scene):
    from PIL import Image
    bad = _copy(small_scene, tmp_path / "s")
    Image.open(bad / "train" / "r_1.png").resize((20, 20)).save(bad / "train" / "r_1.png")
    scene = read_blender(bad)
    scene.split("train").images[0]
    with pytest.raises(DataError, match="r_1.png.*inconsistent"):
        scene.split("train").images[1]


def hand_made_blender_scene(root, c2w, rgba):
    """One train frame with an explicit OpenGL camera-to-world and one RGBA image."""
    from PIL import Image
    (root / "train").mkdir(parents=True)
    Image.fromarray(rgba, "RGBA").save(root / "train" / "r_0.png")
    frames = [{"file_path": "./train/r_0", "transform_matrix": c2w}]
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.9, "frames": frames}))
    return root


def test_blender_opengl_pose_becomes_opencv_world_to_camera(tmp_path):
    """A camera at (0, -4, 0) looking along +y with +z up (OpenGL: it looks down its -z axis and
    its +y is up). In OpenCV terms it looks along world +y, image right is world +x and image
    down is world -z, so the world point (0, 0, 0) is straight ahead at depth 4 and (1, 0, -0.5)
    lands right of and below the centre."""
    import numpy as np
    c2w = [[1, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0], [0, 0, 0, 1]]
    scene = read_blender(hand_made_blender_scene(tmp_path / "s", c2w, np.zeros((8, 8, 4), np.uint8)))
    cams = scene.split("train").cameras
    expected = torch.tensor([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 4], [0, 0, 0, 1]], dtype=torch.float32)
    torch.testing.assert_close(cams.viewmats[0], expected)
    uv, depth = project(cams, torch.tensor([[0.0, 0, 0], [1.0, 0, -0.5]]))
    assert depth[0].tolist() == pytest.approx([4.0, 4.0])
    assert uv[0, 0].tolist() == pytest.approx([4.0, 4.0])  # the image centre
    assert uv[0, 1, 0] > 4 and uv[0, 1, 1] > 4  # right and below


def test_rgba_is_composited_over_a_non_white_background_exactly(tmp_path):
    import numpy as np
    rgba = np.zeros((4, 4, 4), np.uint8)
    rgba[..., 0], rgba[..., 1], rgba[..., 2], rgba[..., 3] = 200, 100, 50, 51  # alpha 0.2
    rgba[0, 0, 3] = 0      # fully transparent: the background
    rgba[1, 1, 3] = 255    # opaque: the colour
    eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]
    background = (0.1, 0.7, 0.3)
    scene = read_blender(hand_made_blender_scene(tmp_path / "s", eye, rgba), background=background)
    image = scene.split("train").images.stack([0])[0].double()
    colour = torch.tensor([200, 100, 50], dtype=torch.float64) / 255
    bg = torch.tensor(background, dtype=torch.float64)
    torch.testing.assert_close(image[0, 0], bg, rtol=0, atol=1e-6)
    torch.testing.assert_close(image[1, 1], colour, rtol=0, atol=1e-6)
    torch.testing.assert_close(image[2, 2], colour * 0.2 + bg * 0.8, rtol=0, atol=1e-6)


def _edit_json(root, split, edit):
    path = root / f"transforms_{split}.json"
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize("edit,match", [
    (lambda d: d.pop("camera_angle_x"), "transforms_train.json: expected an object with 'camera_angle_x'"),
    (lambda d: d["frames"][1].pop("transform_matrix"), "transforms_train.json: frame 1 lacks 'file_path'"),
    (lambda d: d["frames"][0].update(transform_matrix=[[1, 0, "x", 0]] * 4),
     "transforms_train.json: a transform_matrix is not a 4x4 list of numbers"),
    (lambda d: [f.update(transform_matrix=[[1, 0, 0]] * 3) for f in d["frames"]],
     r"transforms_train.json: transform_matrix must be 4x4, got \[3, 3\]"),
])
def test_every_blender_json_error_names_the_file_and_the_reason(tmp_path, small_scene, edit, match):
    bad = _copy(small_scene, tmp_path / "s")
    _edit_json(bad, "train", edit)
    with pytest.raises(DataError, match=match):
        read_blender(bad)


def test_image_errors_name_the_file(tmp_path, small_scene):
    from pipeline.data.images import ImageStore, image_size, read_image
    with pytest.raises(DataError, match="nope.png: image file not found"):
        read_image(tmp_path / "nope.png", None, torch.zeros(3))
    with pytest.raises(DataError, match="nope.png: image file not found"):
        image_size(tmp_path / "nope.png")
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not a png")
    with pytest.raises(DataError, match="broken.png: cannot read image"):
        read_image(broken, None, torch.zeros(3))
    with pytest.raises(DataError, match="broken.png: cannot read image"):
        image_size(broken)
    from PIL import Image
    Image.new("RGB", (20, 10)).save(tmp_path / "small.png")
    store = ImageStore([tmp_path / "small.png"], (32, 32), torch.zeros(3), source_size=(32, 32))
    with pytest.raises(DataError, match=r"small.png: image is 20x10, the scene's images are 32x32"):
        store[0]


def test_load_scene_errors_name_the_folder(tmp_path):
    from pipeline.data.load import load_scene
    with pytest.raises(DataError, match="nope: no such folder"):
        load_scene(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="empty: not a scene folder of any known format: blender"):
        load_scene(tmp_path / "empty")


def test_generating_the_scene_reports_every_view_and_the_cli_prints_tenths(tmp_path, capsys):
    from pipeline.cli.data import main as data_main
    from pipeline.data.synthetic import generate
    heard = []
    generate(tmp_path / "a", size=8, n_train=3, n_test=2, progress=lambda *a: heard.append(a))
    assert heard == [("train", 1, 3), ("train", 2, 3), ("train", 3, 3), ("test", 1, 2), ("test", 2, 2)]
    assert data_main(["generate", str(tmp_path / "b"), "--size", "8"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "train: 10/100 views" and err[-1] == "test: 200/200 views" and len(err) == 20


def rays_at_the_whole_scene(count: int, seed: int):
    """Rays from random points on the camera sphere (and a few close ones) to random points
    of a box larger than the scene: every primitive, its edges and the group boxes' walls get hit."""
    gen = torch.Generator().manual_seed(seed)
    origin = torch.nn.functional.normalize(torch.randn(count, 3, generator=gen), dim=1)
    origin = origin * torch.where(torch.rand(count, generator=gen) < 0.2, 1.6, RADIUS)[:, None]
    target = (torch.rand(count, 3, generator=gen) * 2 - 1) * torch.tensor([1.2, 1.2, 1.1])
    return origin, torch.nn.functional.normalize(target - origin, dim=1)


def test_the_culled_ray_caster_is_the_reference_ray_by_ray():
    """The fast intersector (group boxes, surfaces copied from the nearest primitive) against the
    one that intersects every primitive with every ray: identical, not close."""
    from pipeline.data.synthetic import _intersect, _intersect_reference
    o, d = rays_at_the_whole_scene(60_000, 0)
    fast, slow = _intersect(o, d), _intersect_reference(o, d)
    hit = torch.isfinite(slow.t)
    assert 0.3 < hit.float().mean() < 0.95
    assert torch.equal(torch.isfinite(fast.t), hit) and torch.equal(fast.t[hit], slow.t[hit])
    for name in ("normal", "uv", "tex"):
        assert torch.equal(getattr(fast, name)[hit], getattr(slow, name)[hit]), name
    assert len(set(slow.tex[hit].tolist())) == 13  # every texture, so every kind of primitive, was hit


def test_views_rendered_by_a_worker_pool_are_the_same_files(tmp_path):
    one = generate(tmp_path / "one", seed=5, size=24, n_train=7, n_test=4, workers=1)
    pool = generate(tmp_path / "pool", seed=5, size=24, n_train=7, n_test=4, workers=2)
    names = sorted(p.relative_to(one) for p in one.rglob("*") if p.is_file())
    assert names == sorted(p.relative_to(pool) for p in pool.rglob("*") if p.is_file()) and len(names) == 14
    for name in names:
        assert (one / name).read_bytes() == (pool / name).read_bytes(), name
    with pytest.raises(ValueError, match="workers must be at least 1"):
        generate(tmp_path / "bad", size=8, n_train=1, n_test=1, workers=0)


def test_two_processes_generating_one_scene_at_once_leave_it_whole(tmp_path):
    """Two sweeps started together share the generated scene's folder: both generate, the scene
    ends complete and loadable, and no half-written copy stays beside it."""
    import subprocess
    import sys
    code = ("import sys; from pipeline.data.synthetic import generate; "
            "generate(sys.argv[1], seed=3, size=24, n_train=12, n_test=6, workers=1)")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "scene")]) for _ in range(3)]
    assert [p.wait(timeout=300) for p in procs] == [0, 0, 0]
    scene = load_scene(tmp_path / "scene")
    assert len(scene.split("train").cameras) == 12 and len(scene.split("test").cameras) == 6
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]


def test_generating_over_a_different_scene_replaces_it(tmp_path):
    generate(tmp_path / "scene", seed=3, size=24, n_train=6, n_test=4)
    generate(tmp_path / "scene", seed=4, size=24, n_train=8, n_test=4)
    assert len(load_scene(tmp_path / "scene").split("train").cameras) == 8
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


def test_a_scene_appears_only_when_whole(tmp_path):
    """No reader can see a half-written scene: while views are being written the folder is not
    there; generating the same scene again keeps the one there (not rewritten)."""
    seen = []
    generate(tmp_path / "scene", seed=3, size=24, n_train=6, n_test=4, workers=1,
             progress=lambda split, done, total: seen.append((tmp_path / "scene").exists()))
    assert seen and not any(seen)
    stamp = (tmp_path / "scene" / "scene.json").stat().st_mtime_ns
    generate(tmp_path / "scene", seed=3, size=24, n_train=6, n_test=4, workers=1)
    assert (tmp_path / "scene" / "scene.json").stat().st_mtime_ns == stamp
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]
