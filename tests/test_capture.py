"""Your own capture: lens distortion undistorted on load, nerfstudio's transforms.json, masks in
training and evaluation, video frames by sharpness, the reader registry, and structure-from-motion
of the generated scene's renders with its poses recovered."""

import json
import math
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from pipeline.cameras import Cameras
from pipeline.data.alignment import matched, pose_errors, umeyama
from pipeline.data.capture import CaptureError, capture_scene
from pipeline.data.colmap import read_colmap
from pipeline.data.images import DataError
from pipeline.data.load import load_scene
from pipeline.data.nerfstudio import read_nerfstudio
from pipeline.data.video import choose_sharp, sharp_frames, sharpness
from pipeline.eval.metrics import psnr_value, ssim_value


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("GOPRE_CACHE", str(tmp_path / "cache"))


# -- distortion ----------------------------------------------------------------------------------
W, H, F, CX, CY = 200, 150, 150.0, 100.0, 75.0
K1, K2, P1, P2 = -0.25, 0.05, 0.004, -0.003


def distort(x, y):
    """OpenCV's model on normalised coordinates (written here from its definition)."""
    r2 = x * x + y * y
    radial = 1 + K1 * r2 + K2 * r2 * r2
    return (x * radial + 2 * P1 * x * y + P2 * (r2 + 2 * x * x),
            y * radial + P1 * (r2 + 2 * y * y) + 2 * P2 * x * y)


def points_grid():
    return [(x, y, 4.0) for x in np.linspace(-1.6, 1.6, 7) for y in np.linspace(-1.2, 1.2, 5)]


def blob_image(centres, size=(W, H), sigma=1.2):
    """Gaussian dots at continuous pixel positions (pixel i's centre at i + 0.5)."""
    u = np.arange(size[0]) + 0.5
    v = np.arange(size[1]) + 0.5
    img = np.zeros((size[1], size[0]))
    for cu, cv in centres:
        img += np.exp(-((u[None, :] - cu) ** 2 + (v[:, None] - cv) ** 2) / (2 * sigma ** 2))
    return (np.clip(img, 0, 1) * 255).round().astype(np.uint8)


def distorted_scene(root, model_line):
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(model_line + "\n")
    (sparse / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")  # the camera at the origin
    (sparse / "points3D.txt").write_text("")
    (root / "images").mkdir()
    centres = []
    for X, Y, Z in points_grid():
        xd, yd = distort(X / Z, Y / Z)
        centres.append((F * xd + CX, F * yd + CY))
    Image.fromarray(np.stack([blob_image(centres)] * 3, -1)).save(root / "images" / "a.png")
    return root


def centroid(img, u, v, r=4):
    """Intensity centroid of the window around (u, v) (continuous pixel coordinates)."""
    iu, iv = int(u), int(v)
    win = img[max(iv - r, 0):iv + r + 1, max(iu - r, 0):iu + r + 1]
    ys, xs = np.mgrid[max(iv - r, 0):iv + r + 1, max(iu - r, 0):iu + r + 1]
    return float((win * (xs + 0.5)).sum() / win.sum()), float((win * (ys + 0.5)).sum() / win.sum())


def test_a_distorted_model_is_undistorted_on_load(tmp_path):
    root = distorted_scene(tmp_path / "scene", f"1 OPENCV {W} {H} {F} {F} {CX} {CY} {K1} {K2} {P1} {P2}")
    before = sorted(p.name for p in root.rglob("*"))
    scene = read_colmap(root)
    assert sorted(p.name for p in root.rglob("*")) == before  # nothing written into the user's folder
    assert scene.info["undistorted"].startswith(str(tmp_path / "cache"))
    cams = scene.split("all").cameras
    k = cams.Ks[0].double()
    img = scene.split("all").images[0].mean(-1).numpy()
    errors = []
    for X, Y, Z in points_grid():  # each dot lands where the undistorted pinhole camera puts it
        u, v = float(k[0, 0] * X / Z + k[0, 2]), float(k[1, 1] * Y / Z + k[1, 2])
        if 6 < u < cams.width - 6 and 6 < v < cams.height - 6:
            cu, cv = centroid(img, u, v)
            errors.append(math.hypot(cu - u, cv - v))
    assert len(errors) >= 20 and max(errors) < 0.6, errors
    again = read_colmap(root)  # the cached copy, not a second undistortion
    assert again.info["undistorted"] == scene.info["undistorted"]


def test_ignoring_the_distortion_misplaces_the_dots(tmp_path):
    """The witness: read as if undistorted, the same dots miss their pinhole positions by pixels."""
    root = distorted_scene(tmp_path / "scene", f"1 OPENCV {W} {H} {F} {F} {CX} {CY} {K1} {K2} {P1} {P2}")
    scene = read_colmap(root, allow_distortion=True)
    img = scene.split("all").images[0].mean(-1).numpy()
    X, Y, Z = 1.6, 1.2, 4.0
    cu, cv = centroid(img, F * X / Z + CX, F * Y / Z + CY, r=3)
    assert math.hypot(cu - (F * X / Z + CX), cv - (F * Y / Z + CY)) > 2.0


@pytest.mark.parametrize("line", ["1 SIMPLE_RADIAL 200 150 150 100 75 -0.2", "1 RADIAL 200 150 150 100 75 -0.2 0.03"])
def test_radial_models_are_undistorted_too(tmp_path, line):
    root = tmp_path / "s"
    distorted_scene(root, line)
    scene = read_colmap(root)
    assert "undistorted" in scene.info and scene.split("all").cameras.Ks[0, 0, 0] > 0


# -- nerfstudio's transforms.json --------------------------------------------------------------------

def nerfstudio_from_blender(blender_root, out, **extra):
    """A transforms.json written from a Blender-layout scene's train split (same poses and images)."""
    meta = json.loads((blender_root / "transforms_train.json").read_text())
    first = Image.open(blender_root / (meta["frames"][0]["file_path"] + ".png"))
    w, h = first.size
    f = 0.5 * w / math.tan(0.5 * meta["camera_angle_x"])
    out.mkdir(parents=True)
    frames = []
    for frame in meta["frames"]:
        name = frame["file_path"].split("/")[-1] + ".png"
        shutil.copy(blender_root / (frame["file_path"] + ".png"), out / name)
        frames.append({"file_path": name, "transform_matrix": frame["transform_matrix"]})
    (out / "transforms.json").write_text(json.dumps({"camera_model": "OPENCV", "fl_x": f, "fl_y": f,
                                                      "cx": w / 2, "cy": h / 2, "w": w, "h": h,
                                                      "frames": frames, **extra}))
    return out


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    from pipeline.data.synthetic import generate
    return generate(tmp_path_factory.mktemp("gen") / "scene", seed=0, size=48, n_train=16, n_test=4)


def test_transforms_json_round_trip(generated, tmp_path):
    root = nerfstudio_from_blender(generated, tmp_path / "ns", applied_transform=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]])
    ns = load_scene(root)
    blender = load_scene(generated).split("train")
    assert ns.format == "nerfstudio" and ns.traits.split == "llff"
    names = ns.split("all").names
    order = [blender.names.index(n[:-4]) for n in names]
    torch.testing.assert_close(ns.split("all").cameras.viewmats, blender.cameras.viewmats[order])
    torch.testing.assert_close(ns.split("all").cameras.Ks, blender.cameras.Ks[order], rtol=1e-5, atol=1e-4)
    assert ns.split("all").images.paths[0].name == blender.images.paths[order[0]].name
    assert ns.split("all").images[0].shape == blender.images[order[0]].shape


def test_transforms_json_with_distortion_is_undistorted(generated, tmp_path):
    root = nerfstudio_from_blender(generated, tmp_path / "ns", k1=-0.1, k2=0.0, p1=0.0, p2=0.0)
    scene = load_scene(root)
    assert scene.format == "nerfstudio" and "undistorted" in scene.info
    assert scene.split("all").names[0].endswith(".png") and len(scene.split("all")) == 16


@pytest.mark.parametrize("extra, message", [
    ({"camera_model": "OPENCV_FISHEYE"}, r"camera_model OPENCV_FISHEYE is not supported"),
    ({"k3": 0.01}, r"has k3/k4 distortion"),
    ({"fl_x": None}, r"frame 0 .* has no 'fl_x'"),
])
def test_transforms_json_refusals(generated, tmp_path, extra, message):
    root = nerfstudio_from_blender(generated, tmp_path / "ns")
    meta = json.loads((root / "transforms.json").read_text())
    meta.update(extra)
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=message):
        read_nerfstudio(root)


def test_masks_are_read_per_split_and_refused_when_missing(generated, tmp_path):
    root = nerfstudio_from_blender(generated, tmp_path / "ns")
    meta = json.loads((root / "transforms.json").read_text())
    (root / "masks").mkdir()
    for frame in meta["frames"][:-1]:
        Image.new("L", (48, 48), 255).save(root / "masks" / frame["file_path"])
        frame["mask_path"] = "masks/" + frame["file_path"]
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"1 frame\(s\) have no mask_path"):
        load_scene(root, masks=True)
    assert load_scene(root).masks is None  # without the switch nothing changes


def test_unknown_folder_names_every_format(tmp_path):
    with pytest.raises(DataError, match=r"not a scene folder of any known format: blender \(transforms_train.json\), "
                                        r"nerfstudio \(transforms.json\), colmap \(sparse/\)"):
        load_scene(tmp_path)


# -- masks in evaluation and training ------------------------------------------------------------

def test_masked_metrics_by_hand():
    gt = torch.zeros(4, 4, 3)
    pred = gt.clone()
    pred[:, 2:] = 0.5  # wrong only in the right half
    mask = torch.zeros(4, 4)
    mask[:, :2] = 1
    assert psnr_value(pred, gt, mask) == math.inf  # the masked-in half is exact
    mask[0, 2] = 1  # one wrong pixel among 9: mse = 0.25 / 9
    assert psnr_value(pred, gt, mask) == pytest.approx(-10 * math.log10(0.25 / 9))
    assert psnr_value(pred, gt) == pytest.approx(-10 * math.log10(0.125))
    assert ssim_value(gt, gt, mask) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="no pixel of this view is masked in"):
        psnr_value(pred, gt, torch.zeros(4, 4))


def test_masked_training_step_fused_equals_autograd_and_ignores_masked_pixels():
    from pipeline.fit.fused_step import fused_step_gradients
    from pipeline.fit.losses import masked_pair, photometric_loss
    from pipeline.splat import RenderSettings
    from pipeline.splat.training_view import training_view_generic
    from tests.test_plugins import look_along
    from pipeline.splat.gaussians import Gaussians
    gen = torch.Generator().manual_seed(3)
    n = 30
    params = dict(means=(torch.rand(n, 3, generator=gen) - 0.5).double() * torch.tensor([1.6, 1.2, 0.4]).double(),
                  log_scales=torch.full((n, 3), -2.5, dtype=torch.float64),
                  quats=torch.randn(n, 4, generator=gen).double(), logit_opacities=torch.zeros(n, dtype=torch.float64),
                  sh0=torch.rand(n, 1, 3, generator=gen).double(), shN=torch.zeros(n, 0, 3, dtype=torch.float64))
    cam = look_along([[0, 0, 1]])
    cam = Cameras(cam.viewmats.double(), cam.Ks.double(), 16, 16)
    cam.viewmats[0, 2, 3] = 3.0
    target = torch.rand(16, 16, 3, generator=gen).double()
    mask = torch.zeros(16, 16, dtype=torch.float64)
    mask[:, :8] = 1
    bg = torch.zeros(3, dtype=torch.float64)
    settings = RenderSettings(backend="compiled")
    fused = fused_step_gradients(params, cam, bg, 0, settings, target, 0.2, mask)
    leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    out = training_view_generic(Gaussians.unchecked(**leaves), cam, bg, 0, RenderSettings(backend="tiles"))
    loss = photometric_loss(*masked_pair(out.image, target, mask), 0.2)
    loss.backward()
    assert fused.loss == pytest.approx(float(loss.detach()), rel=1e-9)
    for k in params:
        torch.testing.assert_close(fused.grads[k], leaves[k].grad, rtol=1e-7, atol=1e-10)
    # the target's masked-out half does not matter at all
    other = target.clone()
    other[:, 8:] = 1 - other[:, 8:]
    again = fused_step_gradients(params, cam, bg, 0, settings, other, 0.2, mask)
    assert again.loss == fused.loss and all(torch.equal(again.grads[k], fused.grads[k]) for k in params)


# -- video ----------------------------------------------------------------------------------------

def test_sharp_frames_are_chosen_one_per_stretch(tmp_path):
    av = pytest.importorskip("av")
    rng = np.random.default_rng(0)
    sharp = (rng.random((64, 64, 3)) * 255).astype(np.uint8)
    blurred = np.full_like(sharp, 128)
    frames = [sharp if k % 3 == 1 else blurred for k in range(12)]  # the sharp one is the middle of each three
    assert choose_sharp([sharpness(f) for f in frames], 4) == [1, 4, 7, 10]
    path = tmp_path / "walk.mp4"
    with av.open(str(path), "w") as out:
        stream = out.add_stream("mpeg4", rate=10)
        stream.width, stream.height, stream.pix_fmt = 64, 64, "yuv420p"
        stream.bit_rate = 4_000_000
        for f in frames:
            out.mux(stream.encode(av.VideoFrame.from_ndarray(f, format="rgb24")))
        out.mux(stream.encode())
    kept = sharp_frames(path, 4)
    assert len(kept) == 4 and all(sharpness(k) > 10 * sharpness(blurred) + 1 for k in kept)
    with pytest.raises(DataError, match="cannot open the video"):
        (tmp_path / "bad.mp4").write_bytes(b"not a video")
        sharp_frames(tmp_path / "bad.mp4", 4)


# -- the capture command --------------------------------------------------------------------------

def test_capture_refusals(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(3):
        Image.new("RGB", (32, 32), (k, k, k)).save(photos / f"p{k}.jpg")
    with pytest.raises(CaptureError, match=r"3 image\(s\); a capture needs at least 8 photos"):
        capture_scene(photos, tmp_path / "out")
    (photos / "broken.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    with pytest.raises(CaptureError, match=r"1 unreadable image file\(s\): broken.jpg"):
        capture_scene(photos, tmp_path / "out2")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    with pytest.raises(CaptureError, match="exists and is not empty"):
        capture_scene(photos, tmp_path / "full")
    assert not (tmp_path / "out").exists()  # a refused capture leaves nothing behind


def test_umeyama_recovers_a_known_similarity():
    gen = torch.Generator().manual_seed(0)
    pts = torch.randn(20, 3, generator=gen, dtype=torch.float64)
    from scipy.spatial.transform import Rotation
    rot = torch.tensor(Rotation.from_rotvec([0.3, -0.5, 0.9]).as_matrix())
    target = 2.5 * pts @ rot.T + torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    s, r, t = umeyama(pts, target)
    assert s == pytest.approx(2.5) and torch.allclose(r, rot) and torch.allclose(t, torch.tensor([1.0, -2.0, 0.5],
                                                                                                  dtype=torch.float64))


@pytest.mark.slow
def test_capture_recovers_the_generated_scenes_poses(tmp_path):
    """The generated scene rendered from known poses (400 px, 40 views), captured by the command:
    every view registers and the poses match after a similarity (measured: median centre error
    0.13% of the extent, rotation 0.1 degrees)."""
    from pipeline.data.synthetic import generate
    scene_root = generate(tmp_path / "gen", seed=0, size=400, n_train=40, n_test=2)
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(40):
        shutil.copy(scene_root / "train" / f"r_{k}.png", photos / f"r_{k}.png")
    summary = capture_scene(photos, tmp_path / "captured")
    assert summary.images == 40 and summary.registered >= 38 and summary.mean_reprojection_error_px < 1.0
    assert json.loads((tmp_path / "captured" / "capture.json").read_text())["registered"] == summary.registered
    truth, est = load_scene(scene_root, width=100).split("train"), load_scene(tmp_path / "captured", width=100).split("all")
    a, b, _ = matched(truth.names, truth.cameras, est.names, est.cameras)
    errors = pose_errors(a, b)
    assert errors.median_centre_error < 0.01 and errors.median_rotation_error_deg < 0.5, errors


def test_umeyama_never_returns_a_reflection():
    """A mirrored point set is best fitted by a reflection; a pose alignment must stay a rotation."""
    gen = torch.Generator().manual_seed(1)
    pts = torch.randn(20, 3, generator=gen, dtype=torch.float64) * torch.tensor([3.0, 2.0, 1.0], dtype=torch.float64)
    s, r, _ = umeyama(pts, pts * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    assert torch.det(r) == pytest.approx(1.0) and torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64))


def test_a_video_becomes_evenly_spread_sharp_frames_matched_sequentially(tmp_path):
    av = pytest.importorskip("av")
    from pipeline.data.capture import prepare_inputs
    rng = np.random.default_rng(1)
    path = tmp_path / "walk.mp4"
    with av.open(str(path), "w") as out:
        stream = out.add_stream("mpeg4", rate=10)
        stream.width, stream.height, stream.pix_fmt = 96, 64, "yuv420p"
        stream.bit_rate = 4_000_000
        for k in range(30):
            frame = (rng.random((64, 96, 3)) * 255).astype(np.uint8) if k % 5 == 2 else np.full((64, 96, 3), 90, np.uint8)
            out.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        out.mux(stream.encode())
    names, matcher, masks = prepare_inputs(path, tmp_path / "work", max_size=64, frames=6, say=lambda line: None)
    assert matcher == "sequential" and masks == 0 and names == [f"frame_{k:05d}.jpg" for k in range(6)]
    sizes = {Image.open(tmp_path / "work" / "images" / n).size for n in names}
    assert sizes == {(64, 43)}  # the longest side at max_size
    assert all(sharpness(np.asarray(Image.open(tmp_path / "work" / "images" / n))) > 100 for n in names)
