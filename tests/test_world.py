"""pipeline/world (issue 28): the pose space, the search and the capture simulators.

Oracles: the manifolds' own azimuth rule (data/manifolds.py) for where a pose's camera sits, the
pinhole projection of the centre for where it looks, the stored dataset images (as the reader
reads them) for the generated world, hand-planted optima for the search."""

import math

import numpy as np
import pytest
import torch

from pipeline.cameras import Cameras
from pipeline.data.load import load_scene
from pipeline.data.manifolds import SectorManifold
from pipeline.data.synthetic import CAMERA_ANGLE_X, generate
from pipeline.world import (GeneratedWorld, LookAtShell, SearchBudget, TwinWorld, pose_coordinates,
                            search_poses, train_twin)

UP = (0.0, 0.0, 1.0)
K = ((50.0, 0.0, 32.0), (0.0, 50.0, 32.0), (0.0, 0.0, 1.0))


def shell(**changes) -> LookAtShell:
    base = dict(centre=(0.1, -0.2, 0.3), up=UP, azimuth_start_deg=0.0, azimuth_span_deg=360.0,
                elevation_deg=(5.0, 70.0), radius=(3.0, 5.0), K=K, width=64, height=64, scene_radius=1.5)
    return LookAtShell(**{**base, **changes})


def test_a_poses_camera_sits_at_its_coordinates_and_looks_at_the_centre():
    space = shell()
    poses = space.sample(40, torch.Generator().manual_seed(0))
    cams = space.cameras(poses)
    az, el, r = pose_coordinates(cams, torch.tensor(space.centre), torch.tensor(UP))
    turn = (az - poses[:, 0] + 180) % 360 - 180
    assert turn.abs().max() < 1e-3 and (el - poses[:, 1]).abs().max() < 1e-3
    assert (r - poses[:, 2]).abs().max() < 1e-4
    assert torch.equal(space.poses_of(cams), torch.stack([az, el, r], 1))  # the shell's own inverse
    centre = torch.tensor([*space.centre, 1.0], dtype=torch.float64)
    in_camera = cams.viewmats.double() @ centre  # [B, 4]
    pixel = (torch.tensor(K, dtype=torch.float64) @ in_camera[:, :3].T).T
    assert (in_camera[:, 2] > 0).all()  # in front
    assert torch.allclose(pixel[:, :2] / pixel[:, 2:], torch.tensor([32.0, 32.0], dtype=torch.float64), atol=1e-3)
    # up is up in the image: the world up direction maps to the camera's -y
    assert (cams.viewmats[:, 1, :3].double() @ torch.tensor(UP, dtype=torch.float64) < 0).all()


def test_unit_coordinates_round_trip_and_the_cube_is_the_space():
    space = shell(azimuth_start_deg=300.0, azimuth_span_deg=120.0)
    unit = torch.rand(50, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    poses = space.poses_of_unit(unit)
    assert space.contains(poses).all()
    assert torch.allclose(space.unit_of_poses(poses), unit, atol=1e-9)
    outside = torch.tensor([[200.0, 30.0, 4.0], [10.0, 80.0, 4.0], [10.0, 30.0, 6.0]], dtype=torch.float64)
    assert not space.contains(outside).any()


@pytest.mark.parametrize("start,width,clockwise", [(0.0, 120.0, True), (30.0, 90.0, False), (350.0, 60.0, False)])
def test_a_sector_restricted_shell_holds_exactly_the_sectors_poses(start, width, clockwise):
    space = shell()
    sector = SectorManifold(start, width, clockwise, up=list(UP), center=list(space.centre))
    inside = space.within_sector(sector)
    cams = inside.cameras(inside.sample(60, torch.Generator().manual_seed(2)))
    assert sector.contains(cams).all()
    rest = space.cameras(space.sample(400, torch.Generator().manual_seed(3)))
    in_sector = sector.contains(rest)
    az = pose_coordinates(rest, torch.tensor(space.centre), torch.tensor(UP))[0]
    in_shell = inside.contains(torch.stack([az, torch.full_like(az, 30.0), torch.full_like(az, 4.0)], 1))
    assert torch.equal(in_sector, in_shell)
    with pytest.raises(ValueError, match="differ"):
        space.within_sector(SectorManifold(start, width, clockwise, up=list(UP), center=[0.0, 0.0, 0.0]))


def test_the_space_a_capture_spans():
    all_round = shell()
    cams = all_round.cameras(torch.tensor([[a, 20.0 + a / 40, 4.0] for a in range(0, 360, 30)], dtype=torch.float64))
    found = LookAtShell.spanning(cams, torch.tensor(all_round.centre), torch.tensor(UP), scene_radius=1.0)
    assert (found.azimuth_start_deg, found.azimuth_span_deg) == (0.0, 360.0)
    assert found.elevation_deg == pytest.approx((20.0, 28.25), abs=1e-3)
    assert found.radius == pytest.approx((4.0, 4.0), abs=1e-4) and found.width == 64
    arc = all_round.cameras(torch.tensor([[a, 30.0, 3.0 + a / 100] for a in (330, 350, 10, 40)], dtype=torch.float64))
    found = LookAtShell.spanning(arc, torch.tensor(all_round.centre), torch.tensor(UP))
    assert found.azimuth_start_deg == pytest.approx(330.0, abs=1e-3)
    assert found.azimuth_span_deg == pytest.approx(70.0, abs=1e-3)
    assert found.radius == pytest.approx((3.1, 6.5), abs=1e-4)  # 3 + a / 100 at a = 10 and 350


@pytest.mark.parametrize("changes,match", [
    ({"elevation_deg": (40.0, 10.0)}, "elevation_deg"),
    ({"elevation_deg": (-95.0, 10.0)}, "elevation_deg"),
    ({"radius": (5.0, 3.0)}, "radius"),
    ({"radius": (1.0, 3.0)}, "inside the scene"),
    ({"azimuth_span_deg": 0.0}, "azimuth_span_deg"),
    ({"up": (0.0, 0.0, 2.0)}, "unit vector"),
])
def test_bad_bounds_are_config_errors_naming_the_bound(changes, match):
    with pytest.raises(ValueError, match=match):
        shell(**changes)


def planted(target: torch.Tensor, space: LookAtShell):
    """A score whose minimum is the camera position of ``target`` (distance of the eyes)."""
    goal = space.cameras(target[None]).centers.double()

    def score(poses):
        return (space.cameras(poses).centers.double() - goal).norm(dim=1)
    return score


def test_the_search_finds_a_planted_optimum_within_bounds_and_is_seeded():
    space = shell(azimuth_start_deg=20.0, azimuth_span_deg=140.0)
    target = torch.tensor([95.0, 40.0, 4.2], dtype=torch.float64)
    starts = space.sample(6, torch.Generator().manual_seed(4))
    state = np.random.get_state()
    result = search_poses(planted(target, space), space, starts, SearchBudget(evaluations=200), seed=7)
    assert np.array_equal(np.random.get_state()[1], state[1])  # NumPy's global generator untouched
    assert result.evaluations <= 200 and result.starts == 6
    assert space.contains(result.poses).all()
    assert result.score <= result.best_start_score
    assert (result.pose - target).abs().max() < 0.5, result.pose
    again = search_poses(planted(target, space), space, starts, SearchBudget(evaluations=200), seed=7)
    assert torch.equal(again.poses, result.poses)
    other = search_poses(planted(target, space), space, starts, SearchBudget(evaluations=200), seed=8)
    assert not torch.equal(other.poses, result.poses)


def test_the_search_crosses_the_seam_of_a_full_circle_and_keeps_to_a_budget():
    space = shell()
    target = torch.tensor([355.0, 30.0, 4.0], dtype=torch.float64)
    starts = torch.tensor([[15.0, 30.0, 4.0]], dtype=torch.float64)
    result = search_poses(planted(target, space), space, starts, SearchBudget(evaluations=150), seed=0)
    assert (result.pose[0] - 355.0 + 180) % 360 - 180 == pytest.approx(0.0, abs=1.0)
    assert result.evaluations <= 150
    one = search_poses(planted(target, space), space, starts, SearchBudget(evaluations=1), seed=0)
    assert one.evaluations == 1 and torch.equal(one.pose, starts[0])
    with pytest.raises(ValueError, match="inside the pose space"):
        search_poses(planted(target, space), space, torch.tensor([[15.0, 80.0, 4.0]]), SearchBudget(), seed=0)
    with pytest.raises(ValueError, match="evaluations"):
        SearchBudget(evaluations=0)


@pytest.fixture(scope="module")
def generated_scene(tmp_path_factory):
    return generate(tmp_path_factory.mktemp("world") / "scene", seed=0, size=24, n_train=6, n_test=2)


def test_the_generated_world_gives_back_the_stored_image_at_a_dataset_pose(generated_scene):
    scene = load_scene(generated_scene, width=16)  # resized as episodes read it
    train = scene.split("train")
    world = GeneratedWorld(stored_size=24, background=scene.background)
    captured = world.capture(train.cameras[[0, 3]])
    assert torch.equal(captured, train.images.stack([0, 3]))
    bad = Cameras(train.cameras.viewmats[:1], train.cameras.Ks[:1] * 1.2, 16, 16)
    with pytest.raises(ValueError, match="intrinsics"):
        world.capture(bad)


def test_the_generated_world_renders_a_pose_off_the_dataset(generated_scene):
    scene = load_scene(generated_scene, width=16)
    cams = scene.split("train").cameras
    centre = torch.zeros(3)
    space = LookAtShell.spanning(cams, centre, torch.tensor(UP), scene_radius=1.0)
    off = space.cameras(torch.tensor([[123.0, 33.0, 4.0]], dtype=torch.float64))
    image = GeneratedWorld(24, scene.background).capture(off)
    assert image.shape == (1, 16, 16, 3) and 0 <= float(image.min()) and float(image.max()) <= 1
    assert float((image - scene.background).abs().max()) > 0.1  # the object is in view
    assert math.isclose(off.Ks[0, 0, 0].item(), 0.5 * 16 / math.tan(0.5 * CAMERA_ANGLE_X), rel_tol=1e-5)


def test_a_twin_renders_a_training_pose_close_to_its_photo(generated_scene):
    from pipeline.active.config import tiny_episode
    from pipeline.fit.init import random_in_box
    scene = load_scene(generated_scene, width=16)
    train = scene.split("train")
    cfg = tiny_episode().fit.with_changes(iterations=300)
    lo, hi = scene.bounds()
    init = random_in_box(600, lo.float(), hi.float(), cfg.sh_degree, 0, cfg.init_opacity)
    twin = train_twin(init, train.cameras, train.images.stack(list(range(len(train.cameras)))), cfg,
                      scene.background)
    world = TwinWorld(twin, scene.background)
    shot = world.capture(train.cameras[[1]])[0]
    photo = train.images.stack([1])[0]
    mse = float((shot - photo).square().mean())
    assert -10 * math.log10(mse) > 18.0  # measured 29.2 dB (the untrained init: 8.6 dB)


# -- the episode off the pool (world=generated) ---------------------------------------------------
SEARCH = {"evaluations": 30, "pool_starts": 2, "random_starts": 2}


@pytest.fixture(scope="module")
def episode_scene(tmp_path_factory):
    return generate(tmp_path_factory.mktemp("world_ep") / "scene", seed=0, size=32, n_train=12, n_test=4)


def world_config(**changes):
    from pipeline.active.config import tiny_episode
    from pipeline.data.protocols import ProtocolConfig
    base = {"strategy": "gopre", "world": "generated", "search": SEARCH,
            "protocol": ProtocolConfig(initial_views=2, budget=4, probes=3)}
    return tiny_episode(**{**base, **changes})


@pytest.mark.parametrize("strategy", ["gopre", "fisherrf"])  # least score / greatest score
def test_an_episode_off_the_pool_captures_searched_poses_and_trains_on_them(episode_scene, tmp_path, strategy):
    from pipeline.active import run_episode
    from pipeline.active.episode import Episode
    scene = load_scene(episode_scene, width=32)
    cfg = world_config(strategy=strategy)
    sign = -1.0 if strategy == "fisherrf" else 1.0  # rec.search holds costs: fisherrf's gain negated
    world = GeneratedWorld(32, scene.background)
    checked = []

    def on_selection(ep, rec):  # the image trained on is the world's image of the recorded pose
        view = rec.selected[0]
        at = ep.taken.index(view)
        if rec.search["taken"] == "search":
            camera = ep.space.cameras(torch.tensor(rec.poses))
            assert torch.equal(ep.taken_images()[at], world.capture(camera)[0])
            assert torch.allclose(ep.taken_cameras().viewmats[at], camera.viewmats[0])
        else:  # the pool's best candidate stands: its own camera and image
            assert torch.equal(ep.taken_images()[at], ep.images(ep.pool, [view])[0])
        checked.append(view)
    result = run_episode(scene, cfg, on_selection=on_selection)
    pool_size = len(scene.split("train").cameras)
    assert checked == result.selected and len(result.selected) == 2
    searched = [r for r in result.rounds[:-1] if r.search["taken"] == "search"]
    assert searched, "no round took a searched pose (measured: the second one does)"
    assert len(result.acquired_poses) == len(searched)
    space = Episode(scene, cfg).space
    assert space.contains(torch.tensor(result.acquired_poses)).all()
    for rec in result.rounds[:-1]:
        costs = {view: sign * score for view, score in rec.scores.items()}
        best_pool = min(costs.values())
        assert len(rec.scores) == rec.candidates and rec.search["best_pool_score"] == best_pool
        assert rec.search["score"] <= rec.search["best_start_score"] and rec.search["evaluations"] <= 30
        evaluated = torch.tensor(rec.search["evaluated"], dtype=torch.float64)  # the landscape the search saw: [E, 4]
        assert evaluated.shape == (rec.search["evaluations"], 4) and space.contains(evaluated[:, :3]).all()
        assert float(evaluated[:, 3].min()) == rec.search["score"]
        if rec.search["taken"] == "search":  # a captured view, after the pool's ids
            assert rec.selected[0] >= pool_size and rec.search["score"] < best_pool and len(rec.poses) == 1
        else:  # the pool pick: the best pool score
            assert rec.selected == [min(costs, key=costs.get)] and rec.poses is None
            assert rec.search["score"] >= best_pool - 1e-9 * abs(best_pool)
    assert [r.poses[0] for r in searched] == result.acquired_poses
    assert "acquired_poses" in result.to_dict()


def test_an_interrupted_episode_off_the_pool_resumes_to_the_same_poses(episode_scene, tmp_path):
    from pipeline.active import run_episode
    scene = load_scene(episode_scene, width=32)
    cfg = world_config()
    whole = run_episode(scene, cfg)

    class Stop(Exception):
        pass

    def stop_after_first(rec):
        if rec.round == 0:
            raise Stop
    with pytest.raises(Stop):
        run_episode(scene, cfg, tmp_path / "ck", on_round=stop_after_first)
    resumed = run_episode(scene, cfg, tmp_path / "ck")
    assert resumed.acquired_poses == whole.acquired_poses and resumed.selected == whole.selected
    assert resumed.final.psnr == whole.final.psnr


def test_a_goal_episode_searches_inside_the_target_sector(episode_scene):
    from pipeline.active import run_episode
    from pipeline.active.episode import Episode
    from pipeline.data.protocols import ProtocolConfig, resolved_manifold, scene_up
    scene = load_scene(episode_scene, width=32)
    cfg = world_config(protocol=ProtocolConfig(kind="goal", initial_views=2, budget=3, probes=2))
    result = run_episode(scene, cfg)
    manifold = resolved_manifold(cfg.protocol.manifold, scene, scene_up(scene, scene.all_cameras()))
    searched = [r.poses[0] for r in result.rounds[:-1] if r.search["taken"] == "search"]
    assert searched == (result.acquired_poses or [])
    space = Episode(scene, cfg).space
    # every pose the search evaluated lies in the sector: sample the space itself
    assert manifold.contains(space.cameras(space.sample(50, torch.Generator().manual_seed(0)))).all()
    if searched:
        assert manifold.contains(space.cameras(torch.tensor(searched))).all()


def test_bad_world_settings_name_the_key(episode_scene):
    from pipeline.active.config import tiny_episode
    from pipeline.active.episode import Episode
    for changes, match in (({"world": "moon"}, "world: 'moon' is not one of dataset, generated, twin"),
                           ({"world": "twin"}, "world_model"),
                           ({"world": "generated", "search": {"budget": 3}}, r"search: unknown keys \['budget'\]"),
                           ({"search": {"evaluations": 3}}, "needs a capture simulator"),
                           ({"world": "generated", "search": {"pool_starts": 0, "random_starts": 0}}, "at least one start"),
                           ({"world": "generated", "views_per_round": 2}, "views_per_round must be 1")):
        with pytest.raises(ValueError, match=match):
            tiny_episode(**changes)
    with pytest.raises(ValueError, match="cannot score a pose"):
        Episode(load_scene(episode_scene, width=32), tiny_episode(strategy="random", world="generated"))


def test_gopre_data_twin_writes_a_twin_that_world_twin_renders(episode_scene, tmp_path, capsys):
    import json as json_module

    from pipeline.cli.data import main
    from pipeline.splat import ply
    out = tmp_path / "twin.ply"
    assert main(["twin", str(episode_scene), str(out), "--width", "16", "--iterations", "200"]) == 0
    report = json_module.loads(capsys.readouterr().out)
    assert out.exists() and report["use"] == f"world=twin world.model=ply:{out}"
    assert report["train_views"] == 12 and report["test_views"] == 4
    assert report["train_psnr"] > report["test_psnr"] - 5 and report["train_psnr"] > 15  # it fits
    scene = load_scene(episode_scene, width=16)
    shot = TwinWorld(ply.load(out), scene.background).capture(scene.split("train").cameras[[2]])[0]
    assert -10 * math.log10(float((shot - scene.split("train").images.stack([2])[0]).square().mean())) > 15
    assert main(["twin", str(episode_scene), str(out), "--width", "4"]) == 1


def test_no_search_is_the_pool_episode_and_captured_pool_picks_are_the_simulators_images(episode_scene):
    """evaluations 0: the pool episode exactly; capture_pool_picks: the same pool picks' cameras,
    their images rendered by the world (the control for a simulator's images)."""
    from pipeline.active import run_episode
    scene = load_scene(episode_scene, width=32)
    plain = run_episode(scene, world_config(world="dataset", search={}))
    unsearched = run_episode(scene, world_config(search={"evaluations": 0}))
    assert unsearched.selected == plain.selected and unsearched.final.psnr == plain.final.psnr
    assert all(r.search["taken"] == "pool" and r.search["evaluations"] == 0 for r in unsearched.rounds[:-1])
    world = GeneratedWorld(32, scene.background)
    pool_cameras = scene.split("train").cameras
    checked = []

    def on_selection(ep, rec):
        assert rec.search["taken"] == "pool_captured" and ep.acquired.is_acquired(rec.selected[0])
        pool_pick = min(rec.scores, key=rec.scores.get)  # gopre: the least score
        camera = ep.taken_cameras()[[ep.taken.index(rec.selected[0])]]
        assert torch.equal(camera.viewmats, pool_cameras[[pool_pick]].viewmats)
        assert torch.equal(ep.taken_images()[ep.taken.index(rec.selected[0])], world.capture(camera)[0])
        checked.append(pool_pick)
    captured = run_episode(scene, world_config(search={"evaluations": 0, "capture_pool_picks": True}),
                           on_selection=on_selection)
    assert len(checked) == 2 and len(captured.acquired_poses) == 2
    assert checked[0] == plain.selected[0]  # the first pick is made on the same model
    with pytest.raises(ValueError, match="capture_pool_picks must be true or false"):
        world_config(search={"capture_pool_picks": "yes"})
