"""A capture that checks itself: loop-closing matching above the exhaustive limit, the geometry
check that flags a folded model (bonsai's old one) and passes the re-staged one, the up axis of a
capture taken with the phone sideways, a truncated photo named in one line."""

import json
import math
import shutil
from pathlib import Path

import pytest
import torch
from PIL import Image

from pipeline.data import capture as cap
from pipeline.data.capture import CaptureError, loop_pairs, photo_files
from tests.conftest import SHARED_DATA


def test_loop_pairs_are_the_walk_neighbours_and_the_skeleton_by_brute_force():
    names = [f"DSCF{5565 + i}.JPG" for i in range(292)]
    expected = {(names[i], names[j]) for i in range(292) for j in range(i + 1, 292)
                if j - i <= 10 or (i % 5 == 0 and j % 5 == 0)}
    pairs = loop_pairs(list(reversed(names)))  # name order, whatever order they come in
    assert len(pairs) == len(set(pairs)) == len(expected) == 4461  # the bonsai re-staging's count
    assert set(pairs) == expected
    small = loop_pairs(["a", "b", "c"], neighbours=1, skeleton_every=2)
    assert small == [("a", "b"), ("a", "c"), ("b", "c")]


def test_above_the_exhaustive_limit_the_loop_pairs_are_matched(tmp_path, monkeypatch):
    """The matcher the capture runs, with pycolmap's stages recorded instead of run."""
    import pycolmap
    calls = {}
    monkeypatch.setattr(pycolmap, "extract_features", lambda *a, **k: None)
    monkeypatch.setattr(pycolmap, "match_exhaustive", lambda *a, **k: calls.setdefault("exhaustive", True))

    def imported(db, pairing_options=None, **k):
        calls["pairs"] = Path(pairing_options.match_list_path).read_text().splitlines()
    monkeypatch.setattr(pycolmap, "match_image_pairs", imported)
    monkeypatch.setattr(pycolmap, "incremental_mapping", lambda *a, **k: {})
    names = [f"p{i:03d}.jpg" for i in range(30)]
    with pytest.raises(CaptureError, match="registered no model"):
        cap.reconstruct(tmp_path, names, "loop", lambda line: None, {})
    assert "exhaustive" not in calls and calls["pairs"] == [f"{a} {b}" for a, b in loop_pairs(names)]
    assert cap.pair_count(names, "loop") == len(loop_pairs(names))
    assert cap.pair_count(names, "exhaustive") == 435


def test_the_matcher_is_chosen_by_the_number_of_photos(tmp_path, monkeypatch):
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(9):
        Image.new("RGB", (64, 48), (k * 20, 40, 90)).save(photos / f"p{k}.jpg")
    _, matcher, _ = cap.prepare_inputs(photos, tmp_path / "w1", 64, 10, lambda line: None)
    assert matcher == "exhaustive"
    monkeypatch.setattr(cap, "EXHAUSTIVE_UP_TO", 8)
    _, matcher, _ = cap.prepare_inputs(photos, tmp_path / "w2", 64, 10, lambda line: None)
    assert matcher == "loop"


def test_a_truncated_photo_is_named_in_one_line(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(9):
        Image.new("RGB", (200, 150), (k * 20, 40, 90)).save(photos / f"p{k}.jpg", quality=95)
    whole = (photos / "p4.jpg").read_bytes()
    (photos / "p4.jpg").write_bytes(whole[:len(whole) // 2])  # cut short, as a failed copy leaves it
    with pytest.raises(CaptureError) as err:
        photo_files(photos)
    assert "\n" not in str(err.value) and "1 unreadable image file(s): p4.jpg (" in str(err.value)
    assert "truncated" in str(err.value)


@pytest.fixture(scope="module")
def staged_bonsai():
    from pipeline.data.geometry_check import model_poses
    scene = SHARED_DATA / "colmap" / "bonsai"
    if not (scene / "images").is_dir():
        pytest.skip(f"{scene}: the shared data is not staged here")
    return model_poses(scene)


class _Lazy:
    """Witnesses made as they are first asked for, kept for the next test."""

    def __init__(self, made):
        self.made, self.kept = made, []

    def __iter__(self):
        k = 0
        while True:
            if k == len(self.kept):
                try:
                    self.kept.append(next(self.made))
                except StopIteration:
                    return
            yield self.kept[k]
            k += 1


@pytest.fixture(scope="module")
def bonsai_witnesses(staged_bonsai, tmp_path_factory):
    from pipeline.data.geometry_check import witnesses
    return _Lazy(witnesses(staged_bonsai, 5, tmp_path_factory.mktemp("geometry"), lambda line: None))


@pytest.mark.slow
def test_the_geometry_check_passes_the_restaged_bonsai_and_flags_the_folded_one(staged_bonsai, bonsai_witnesses):
    """Witnesses of the same 292 photos (every 5th, exhaustive), asked until one agrees with the
    re-staged model; the folded model against the witness that agreed. Measured (4 runs): the
    re-staged model 0.4-0.6 % of the cameras' diameter and 0.2-0.5 degrees, the folded one 14-21 %."""
    from pipeline.data.geometry_check import FOLD_CENTRE, MIN_COVER, model_poses, verdict
    folded = model_poses(SHARED_DATA / "regressions" / "bonsai_folded", SHARED_DATA / "colmap" / "bonsai" / "images")
    assert folded.names == staged_bonsai.names
    good = verdict(staged_bonsai, bonsai_witnesses, 5)
    assert good.verdict == "consistent" and good.median_centre_error < FOLD_CENTRE / 2, good.line()
    assert good.registered >= MIN_COVER * good.subset
    agreed = bonsai_witnesses.kept[len(good.witnesses) - 1]
    bad = verdict(folded, [agreed], 5)
    assert bad.verdict == "folded or drifted" and bad.median_centre_error > 2 * FOLD_CENTRE, bad.line()


def test_the_check_measures_what_a_planted_fold_does(staged_bonsai):
    """Without SfM: the model's own cameras as the 'subset' agree exactly; the same cameras with the
    far half of the walk rotated about the up axis (a fold made by hand) are flagged."""
    from pipeline.data.geometry_check import ModelPoses, compare
    staged = staged_bonsai
    every = staged.names[::5]
    own = ModelPoses(every, staged.viewmats[::5].clone(), [])
    exact = compare(staged, own, len(every), 5)
    assert exact.verdict == "consistent" and exact.median_centre_error < 1e-4 and exact.max_rotation_error_deg < 0.05
    bent = own.viewmats.clone()
    half = slice(len(every) // 2, None)
    axis = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    angle = torch.tensor(1.2, dtype=torch.float64)
    k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=torch.float64)
    turn = torch.eye(3, dtype=torch.float64) + torch.sin(angle) * k + (1 - torch.cos(angle)) * k @ k
    c2w = torch.linalg.inv(bent[half])
    c2w[:, :3, :] = turn @ c2w[:, :3, :]
    bent[half] = torch.linalg.inv(c2w)
    assert compare(staged, ModelPoses(every, bent, []), len(every), 5).verdict == "folded or drifted"


def test_the_verdict_asks_witnesses_until_one_agrees_and_quotes_the_closest(staged_bonsai):
    """Witnesses made by hand from the model's own cameras: exact, folded (the far half turned
    about the up axis by ``angle``), too few registered. No SfM."""
    from pipeline.data.geometry_check import MIN_COVER, ModelPoses, verdict
    staged = staged_bonsai
    every = staged.names[::5]
    size = len(every)

    def bent(angle):
        viewmats = staged.viewmats[::5].clone()
        half = slice(size // 2, None)
        c, s = math.cos(angle), math.sin(angle)
        turn = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64)
        c2w = torch.linalg.inv(viewmats[half])
        c2w[:, :3, :] = turn @ c2w[:, :3, :]
        viewmats[half] = torch.linalg.inv(c2w)
        return (0, ModelPoses(every, viewmats, []), size)
    exact = (1, ModelPoses(every, staged.viewmats[::5].clone(), []), size)
    keep = int(MIN_COVER * size) - 1
    tiny = (2, ModelPoses(every[:keep], staged.viewmats[::5][:keep].clone(), []), size)
    first_agrees = verdict(staged, iter([exact, bent(1.2)]), 5)
    assert first_agrees.verdict == "consistent" and len(first_agrees.witnesses) == 1
    second_agrees = verdict(staged, [bent(1.2), tiny, exact], 5)
    assert second_agrees.verdict == "consistent" and second_agrees.first == 1
    assert [w["verdict"] for w in second_agrees.witnesses] == ["folded or drifted", "inconclusive", "consistent"]
    none_agree = verdict(staged, [bent(1.2), tiny, bent(0.6)], 5)
    assert none_agree.verdict == "folded or drifted" and none_agree.folded
    closest = min(w["median_centre_error"] for w in none_agree.witnesses if w["verdict"] != "inconclusive")
    assert none_agree.median_centre_error == closest and closest > 0.05
    unheard = verdict(staged, [tiny], 5)
    assert unheard.verdict == "inconclusive" and not unheard.folded and unheard.median_centre_error is None
    assert "inconclusive" in unheard.line() and json.loads(json.dumps(unheard.to_dict()))["verdict"] == "inconclusive"


def test_relative_rotation_errors_ignore_a_global_turn_and_find_the_turned_camera(staged_bonsai):
    from pipeline.cameras import Cameras
    from pipeline.data.alignment import relative_rotation_errors
    views = staged_bonsai.viewmats[::20].clone()
    c, s = math.cos(0.7), math.sin(0.7)
    turn = torch.eye(4, dtype=torch.float64)
    turn[:3, :3] = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
    turned_world = views @ turn  # world->camera after the world is turned: a global rotation
    ks = torch.eye(3).expand(len(views), 3, 3).clone()
    assert relative_rotation_errors(Cameras(views.float(), ks, 1, 1), Cameras(turned_world.float(), ks, 1, 1)).max() < 0.05
    one = views.clone()
    ten = math.radians(10)
    one[3, :3, :3] = torch.tensor([[1, 0, 0], [0, math.cos(ten), -math.sin(ten)], [0, math.sin(ten), math.cos(ten)]],
                                  dtype=torch.float64) @ one[3, :3, :3]
    errors = relative_rotation_errors(Cameras(views.float(), ks, 1, 1), Cameras(one.float(), ks, 1, 1))
    assert abs(float(errors[3]) - 10) < 0.05 and float(errors.median()) < 0.05


@pytest.fixture(scope="module")
def sideways_alexander(tmp_path_factory):
    """alexander's photos turned 90 degrees clockwise without an orientation tag, captured at 400 px."""
    photos = SHARED_DATA / "photos" / "alexander" / "images"
    if not photos.is_dir():
        pytest.skip(f"{photos}: the shared data is not staged here")
    root = tmp_path_factory.mktemp("sideways")
    (root / "images").mkdir()
    for path in sorted(photos.glob("*.JPG")):
        with Image.open(path) as im:
            im.transpose(Image.ROTATE_270).save(root / "images" / path.name, quality=92)
    summary = cap.capture_scene(root / "images", root / "scene", max_size=400)
    return root, summary


@pytest.mark.slow
def test_a_sideways_capture_is_warned_about_and_pca_sets_it_right(sideways_alexander):
    """The truth is the photos' own up, now the cameras' +x axis (turned clockwise). Measured: the
    cameras' axis 105 degrees off, the plane 100 (a wall dominates the points), pca 17."""
    from pipeline.data.geometry_check import colmap_poses
    from pipeline.data.orientation import angle_deg
    root, summary = sideways_alexander
    found = json.loads((root / "scene" / "capture.json").read_text())["orientation"]
    assert found["method"] == "cameras" and found["choice"] is None and "disagrees" in found["warning"]
    truth = colmap_poses(root / "scene").viewmats[:, 0, :3].mean(0)
    off = {m: angle_deg(torch.tensor(v, dtype=torch.float64), truth / truth.norm()) for m, v in found["estimates"].items()}
    assert off["cameras"] > 60 and off["pca"] < 30, off


@pytest.mark.slow
def test_capture_up_is_kept_and_read_with_the_scene(sideways_alexander, tmp_path):
    from pipeline.data.colmap import read_colmap
    root, _ = sideways_alexander
    scene = tmp_path / "scene"
    shutil.copytree(root / "scene", scene)
    doc = json.loads((scene / "capture.json").read_text())
    from pipeline.data.capture import orient
    doc["orientation"] = orient(scene, "pca", lambda line: None)
    (scene / "capture.json").write_text(json.dumps(doc))
    assert doc["orientation"]["choice"] == "pca" and doc["orientation"]["warning"] is None
    assert read_colmap(scene).info["up"] == "pca"


class _FakeModel:
    def __init__(self, names):
        self.names = names

    def reg_image_ids(self):
        return list(range(len(self.names)))

    def image(self, i):
        return type("Image", (), {"name": self.names[i]})()

    def write(self, folder):
        (Path(folder) / "cameras.bin").write_bytes(b"")

    def num_points3D(self):
        return 1000

    def compute_mean_reprojection_error(self):
        return 0.5


@pytest.mark.parametrize("verdict, matchers", [("folded or drifted", ["loop", "exhaustive"]), ("consistent", ["loop"])])
def test_a_loop_matched_model_that_fails_the_check_is_matched_again_exhaustively(tmp_path, monkeypatch, verdict, matchers):
    """The stages recorded instead of run: the second attempt happens only after a failed check,
    and capture.json keeps the first attempt's figures."""
    from pipeline.data import geometry_check
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(12):
        Image.new("RGB", (64, 48), (k * 20, 40, 90)).save(photos / f"p{k:02d}.jpg")
    monkeypatch.setattr(cap, "EXHAUSTIVE_UP_TO", 10)
    called = []

    def reconstruct(work, names, matcher, say, seconds):
        called.append(matcher)
        assert not (work / "kept").exists()  # a second attempt starts from a clean work folder
        return _FakeModel(names), []

    def undistort(work, model_dir, out, has_masks):
        (out / "sparse" / "0").mkdir(parents=True)
        (out / "images").mkdir()

    def check(out, say=None, work=None):
        return geometry_check.GeometryCheck(12, 3, 5, 3, 0.2, 0.3, 9.0, 12.0, verdict)
    monkeypatch.setattr(cap, "reconstruct", reconstruct)
    monkeypatch.setattr(cap, "undistort", undistort)
    monkeypatch.setattr(geometry_check, "check_geometry", check)
    monkeypatch.setattr(cap, "orient", lambda out, up, say: {"choice": up})
    summary = cap.capture_scene(photos, tmp_path / "scene")
    assert called == matchers
    written = json.loads((tmp_path / "scene" / "capture.json").read_text())
    if len(matchers) == 2:
        assert written["matcher"] == "exhaustive" and written["pairs"] == 66 and written["geometry"] is None
        assert written["first_try"]["matcher"] == "loop" and written["first_try"]["geometry"]["verdict"] == verdict
    else:
        assert written["matcher"] == "loop" and written["first_try"] is None and summary.geometry["verdict"] == verdict
    with pytest.raises(CaptureError, match="--matcher: 'vocab' is not one of"):
        cap.capture_scene(photos, tmp_path / "other", matcher="vocab")
