"""pipeline-view: what it draws (against hand geometry), what it loads (the run's own records),
the goal it scores (the run's own scores reproduced), and the viewer in a real headless Chromium."""

import json
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import free_port
from pipeline.cameras import Cameras, intrinsics_from_fov, look_at
from pipeline.data.manifolds import SectorManifold
from pipeline.splat import Gaussians
from pipeline.view.geometry import (camera_poses, lower_is_better, rotmat_to_wxyz, score_ranks,
                                    sector_outline, splat_arrays, vertical_fov)

ROOT = Path(__file__).resolve().parents[1]


def rotate(wxyz: np.ndarray, v: np.ndarray) -> np.ndarray:
    """v rotated by the unit quaternion (w, x, y, z): v + 2w (q x v) + 2 q x (q x v)."""
    w, q = wxyz[0], wxyz[1:]
    return v + 2 * w * np.cross(q, v) + 2 * np.cross(q, np.cross(q, v))


def ring_cameras(count=8, radius=3.0, height=1.0, size=32) -> Cameras:
    angles = torch.arange(count, dtype=torch.float64) * 2 * math.pi / count
    eyes = torch.stack([radius * angles.cos(), radius * angles.sin(), torch.full_like(angles, height)], 1)
    vm = look_at(eyes, torch.zeros_like(eyes), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    return Cameras(vm, intrinsics_from_fov(0.8, size, size, count, torch.float64), size, size)


# -- geometry against hand values -------------------------------------------------------------
def test_rotmat_to_wxyz_on_known_rotations_and_every_pivot():
    half = math.sqrt(0.5)
    z90 = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    assert np.allclose(rotmat_to_wxyz(z90[None])[0], [half, 0, 0, half])
    x180 = np.diag([1.0, -1, -1])  # trace -1: the x pivot
    assert np.allclose(np.abs(rotmat_to_wxyz(x180[None])[0]), [0, 1, 0, 0])
    gen = np.random.default_rng(0)
    for _ in range(50):  # random rotations, some near 180 degrees (every pivot branch)
        q = gen.normal(size=4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        got = rotmat_to_wxyz(rot[None])[0]
        assert np.allclose(got, q * np.sign(q[0]), atol=1e-12)


def test_a_frustum_sits_at_the_camera_and_looks_at_its_target():
    eyes = torch.tensor([[3.0, -1.0, 2.0], [-2.0, 0.5, -1.0]], dtype=torch.float64)
    targets = torch.tensor([[0.2, 0.1, -0.3], [1.0, 2.0, 0.0]], dtype=torch.float64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    cams = Cameras(look_at(eyes, targets, up), intrinsics_from_fov(1.0, 40, 30, 2, torch.float64), 40, 30)
    positions, wxyz = camera_poses(cams)
    assert np.allclose(positions, eyes.numpy())
    for i in range(2):
        forward = (targets[i] - eyes[i]) / (targets[i] - eyes[i]).norm()
        assert np.allclose(rotate(wxyz[i], np.array([0, 0, 1.0])), forward.numpy())  # OpenCV +z forward
        image_up = rotate(wxyz[i], np.array([0, -1.0, 0]))  # -y is up in the image
        assert image_up @ up.numpy() > 0 and abs(image_up @ forward.numpy()) < 1e-12


def test_vertical_field_of_view():
    ks = torch.tensor([[[20.0, 0, 20], [0, 15.0, 15], [0, 0, 1]]])
    cams = Cameras(torch.eye(4)[None], ks, 40, 30)
    assert vertical_fov(cams) == pytest.approx(2 * math.atan(1.0))  # half height 15 = fy


def test_splat_arrays_have_world_covariances_dc_colours_and_opacities():
    half = math.sqrt(0.5)
    g = Gaussians(means=torch.tensor([[1.0, 2.0, 3.0]]), log_scales=torch.tensor([[1.0, 2.0, 3.0]]).log(),
                  quats=torch.tensor([[half, 0, 0, half]]), logit_opacities=torch.tensor([0.0]),
                  sh0=torch.tensor([[[1.0, 0.0, -3.0]]]), shN=torch.zeros(1, 3, 3))
    out = splat_arrays(g)
    # 90 degrees about z swaps the x and y axes: scales (1, 2, 3) -> variances (4, 1, 9)
    assert np.allclose(out["covariances"][0], np.diag([4.0, 1.0, 9.0]), atol=1e-5)
    assert np.allclose(out["rgbs"][0], [0.5 + 0.28209479177387814, 0.5, 0.0])
    assert np.allclose(out["opacities"], [[0.5]]) and np.allclose(out["centers"], [[1, 2, 3]])


@pytest.mark.parametrize("clockwise", [True, False])
def test_the_drawn_sector_covers_exactly_the_manifold(clockwise):
    cams = ring_cameras()
    manifold = SectorManifold(50.0, 120.0, clockwise).resolve(cams)
    manifold.up = [0.0, 0.0, 1.0]
    segments = sector_outline(manifold, cams, points=25)
    arc = np.concatenate([segments[:24, 0], segments[23:24, 1]])  # the 25 arc points in order
    assert np.allclose(np.linalg.norm(arc[:, :2], axis=1), 3.0) and np.allclose(arc[:, 2], 1.0)
    azimuths = np.degrees(np.arctan2(arc[:, 1], arc[:, 0])) % 360
    ends = sorted([azimuths[0], azimuths[-1]])
    assert np.allclose(ends, sorted([50.0, (50.0 - 120.0) % 360 if clockwise else 170.0]))
    probe_angles = np.radians(azimuths[1:-1])  # inside: the manifold holds cameras there
    eyes = torch.tensor(np.stack([3 * np.cos(probe_angles), 3 * np.sin(probe_angles), np.ones_like(probe_angles)], 1))
    probes = Cameras(look_at(eyes, torch.zeros_like(eyes), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)),
                     intrinsics_from_fov(0.8, 8, 8, len(eyes), torch.float64), 8, 8)
    assert bool(manifold.contains(probes).all())
    opposite = torch.tensor([[3 * math.cos(math.radians(a)), 3 * math.sin(math.radians(a)), 1.0]
                             for a in ((50 + 120 if clockwise else 50 - 120) % 360 + 0.0,)], dtype=torch.float64)
    outside = Cameras(look_at(opposite, torch.zeros_like(opposite), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)),
                      intrinsics_from_fov(0.8, 8, 8, 1, torch.float64), 8, 8)
    assert not bool(manifold.contains(outside).any())


def test_score_standing_follows_the_strategy_direction():
    scores = {3: 5.0, 7: 1.0, 9: 3.0, 11: 3.0}
    assert lower_is_better(scores, [7]) and not lower_is_better(scores, [3])
    assert score_ranks(scores, True) == {7: 1.0, 9: 0.5, 11: 0.5, 3: 0.0}
    assert score_ranks(scores, False) == {3: 1.0, 9: 0.5, 11: 0.5, 7: 0.0}


# -- a tiny run, loaded ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """experiment=debug (gopre and random, 2 selection rounds) with the round models kept."""
    out = tmp_path_factory.mktemp("view") / "debug"
    subprocess.run([str(Path(sys.executable).parent / "pipeline-run"), "experiment=debug",
                    f"output_dir={out}", "job.round_models=true"], cwd=ROOT, check=True,
                   capture_output=True, timeout=600)
    jobs = {j["method"]: Path(j["execution"]["job_dir"]) for j in json.loads((out / "jobs.json").read_text())}
    return jobs


def test_a_round_model_and_its_records_reproduce_the_pick_the_run_made(tiny_run):
    """The viewer's round state is the episode at that pick: the gopre strategy on it, with the
    round's own probes as the goal, gives back the recorded scores and pick."""
    from pipeline.view.goal import score_goal
    from pipeline.view.run import load_run
    run = load_run(str(tiny_run["gopre"]))
    assert len(run.rounds) == 2 and set(run.round_models) == {0, 1}
    for index in range(2):
        state = run.round_state(index)
        assert state.taken == run.initial + run.selected[:index] and not state.model_is_final
        goal = score_goal(run, state, {"kind": "poses", "view_ids": state.probes}, len(state.probes))
        assert goal.probes == sorted(state.probes)
        assert goal.best == state.picked[0]
        assert goal.scores.keys() == state.scores.keys()
        for view, value in state.scores.items():
            assert goal.scores[view] == pytest.approx(value, rel=1e-6), view


def test_a_drawn_sector_probes_inside_it_and_moves_the_scores(tiny_run):
    from pipeline.view.goal import goal_members, score_goal
    from pipeline.view.run import load_run
    run = load_run(str(tiny_run["random"]))  # another method's run: scored with GO-PRE's defaults
    state = run.round_state(1)
    a = score_goal(run, state, {"kind": "sector", "start_deg": 0.0, "width_deg": 120.0, "clockwise": True}, 3)
    b = score_goal(run, state, {"kind": "sector", "start_deg": 180.0, "width_deg": 120.0, "clockwise": True}, 3)
    inside_a = goal_members(run, a.manifold)
    assert set(a.probes) <= set(inside_a) and len(a.probes) == min(3, len(inside_a))
    assert not set(b.probes) & set(inside_a) - set(goal_members(run, b.manifold))
    assert a.scores.keys() == b.scores.keys() and not set(a.scores) & set(state.taken)
    assert a.best == min(a.scores, key=a.scores.get)
    assert a.scores != b.scores


def test_a_run_without_round_models_shows_the_final_model(tiny_run, tmp_path):
    from pipeline.view.run import load_run
    sweep = tmp_path / "sweep"
    shutil.copytree(tiny_run["gopre"].parent.parent, sweep)
    folder = sweep / "jobs" / tiny_run["gopre"].name
    shutil.rmtree(folder / "rounds")
    run = load_run(str(folder))
    state = run.round_state(0)
    assert state.model_is_final and torch.equal(state.model.means, run.final_model.means)
    (folder / "artifacts" / "model.ply").unlink()  # a run older than the exporter: the checkpoint's model
    older = load_run(str(folder))
    assert torch.equal(older.final_model.means, run.final_model.means)
    assert torch.equal(older.final_model.shN, run.final_model.shN)


def test_bad_sources_name_what_is_missing(tiny_run, tmp_path, capsys):
    from pipeline.cli.view import main
    assert main([str(tmp_path / "nope")]) == 1
    assert "nope: no such job folder" in capsys.readouterr().err
    (tmp_path / "jobs" / "abc").mkdir(parents=True)
    assert main([str(tmp_path / "jobs" / "abc")]) == 1
    assert "jobs.json beside it" in capsys.readouterr().err
    (tmp_path / "jobs.json").write_text("[]")
    assert main([str(tmp_path / "jobs" / "abc")]) == 1
    assert "no job with config hash 'abc'" in capsys.readouterr().err


# -- the viewer, in process and in a browser ----------------------------------------------------
@pytest.fixture
def viewer(tiny_run):
    from pipeline.cli.view import start
    server, viewer = start(str(tiny_run["gopre"]), port=free_port())
    yield server, viewer
    server.stop()


def test_the_viewer_draws_every_camera_by_role_and_scores_a_goal(viewer):
    from pipeline.view.geometry import ROLE_COLOURS
    from pipeline.view.goal import score_goal
    from pipeline.view.server import CameraKey
    server, v = viewer
    run = v.run
    pool = sorted(set(run.views.pool_ids) | set(run.initial))
    assert {k for k in v.frustums if k.split == "pool"} == {CameraKey("pool", i) for i in pool}
    assert sum(k.split == "test" for k in v.frustums) == len(run.views.test_ids)
    assert v.state.index == 1
    colour = {i: tuple(v.frustums[CameraKey("pool", i)].color) for i in pool}
    assert all(colour[i] == ROLE_COLOURS["initial"] for i in run.initial)
    assert colour[run.selected[0]] == ROLE_COLOURS["selected"]
    assert colour[run.selected[1]] == ROLE_COLOURS["picked"]
    v.show_round(0)
    assert tuple(v.frustums[CameraKey("pool", run.selected[0])].color) == ROLE_COLOURS["picked"]
    v.goal_start.value, v.goal_width.value = 90.0, 150.0
    goal = v.score()
    expected = score_goal(run, run.round_state(0), v.goal_manifold(), int(v.goal_probes.value))
    assert goal.scores == expected.scores and goal.best == expected.best
    assert tuple(v.frustums[CameraKey("pool", goal.best)].color) == ROLE_COLOURS["picked"]
    assert f"Next best view: pool {goal.best}" in v.goal_text.content
    v.goal_kind.value, v.goal_views.value = "picked cameras", "1, x"
    assert v.score() is None and "must be integers" in v.goal_text.content
    v.show_camera(CameraKey("test", run.views.test_ids[0]))
    assert v.image_render.image is not None and "test" in v.camera_text.content


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
BROWSER_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--enable-unsafe-swiftshader"]


def browser_page(playwright):
    browser = playwright.chromium.launch(executable_path=CHROMIUM, headless=True, args=BROWSER_ARGS)
    return browser, browser.new_page(viewport={"width": 1200, "height": 800})


def canvas(page) -> np.ndarray:
    import io
    from PIL import Image
    return np.asarray(Image.open(io.BytesIO(page.locator("canvas").first.screenshot())).convert("RGB"), dtype=int)


def inked(page) -> float:
    """Share of the 3D canvas that is not the white background."""
    return float((np.abs(canvas(page) - 255).sum(-1) > 30).mean())


def wait_for_ink(page, test, seconds: float = 20) -> float:
    deadline, ink = time.time() + seconds, inked(page)
    while time.time() < deadline and not test(ink):
        time.sleep(0.5)
        ink = inked(page)
    return ink


@pytest.mark.e2e
@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium on this machine: `make e2e` installs it")
def test_the_viewer_in_a_headless_browser(viewer, tmp_path):
    playwright_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed (dev extra)")
    server, v = viewer
    run = v.run
    with playwright_api.sync_playwright() as p:
        browser, page = browser_page(p)
        try:
            page.goto(f"http://127.0.0.1:{server.get_port()}/")
            page.wait_for_selector("canvas", timeout=60_000)
            page.wait_for_function("document.body.innerText.includes('selected (pick order)')", timeout=60_000)
            ink = wait_for_ink(page, lambda share: share >= 0.005, seconds=60)
            page.screenshot(path=str(tmp_path / "viewer.png"))
            assert ink >= 0.005, f"blank canvas: {ink:.4f} of it drawn"
            parts = {"cameras": list(v.frustums.values()) + list(v.labels.values()), "splat": [v.splat]}
            for name, handles in parts.items():  # each part is on the picture: hiding it clears ink
                for handle in handles:
                    handle.visible = False
                without = wait_for_ink(page, lambda share: share <= ink - 0.002)
                assert without <= ink - 0.002, f"the {name} drew nothing ({without:.4f} vs {ink:.4f})"
                for handle in handles:
                    handle.visible = True
                wait_for_ink(page, lambda share: share >= ink - 0.001)
            text = page.inner_text("body")
            assert f"initial: {', '.join(map(str, run.initial))}" in text
            assert f"selected (pick order): {run.selected[0]}" in text
            assert f"test views: {len(run.views.test_ids)}" in text

            view = run.views.test_ids[-1]  # a camera chosen in the GUI shows its images
            page.get_by_label("Camera view", exact=True).click()
            page.get_by_role("option", name=f"test {view}", exact=True).click()
            shown = f"test {view} ({run.test.names[view]})"
            page.wait_for_function(f"document.body.innerText.includes({json.dumps(shown)})", timeout=60_000)
            assert page.locator("img").count() >= 3

            def score_with_start(angle: str) -> str:
                """Type the start angle, press Score, wait for the viewer and then the page."""
                start = page.get_by_label("Start angle (deg)")
                start.fill(angle)
                start.press("Enter")
                page.get_by_role("button", name="Score next view").click()
                deadline = time.time() + 60
                while time.time() < deadline and (v.goal is None or v.goal.manifold["start_deg"] != float(angle)):
                    time.sleep(0.2)
                assert v.goal is not None and v.goal.manifold["start_deg"] == float(angle), "the GUI did not score"
                shown = f"Next best view: pool {v.goal.best} (GO-PRE score {v.goal.scores[v.goal.best]:.6g}"
                page.wait_for_function(f"document.body.innerText.includes({json.dumps(shown)})", timeout=60_000)
                return page.inner_text("body")

            first = score_with_start("0")
            first_scores = dict(v.goal.scores)
            second = score_with_start("180")
            assert v.goal.manifold["start_deg"] == 180.0 and v.goal.scores != first_scores
            def table(body):
                return body[body.index("Next best view"):body.index("Camera")]
            assert table(first) != table(second)
        finally:
            browser.close()


# -- what users touch (issue 29): each row of the viewer's state table --------------------------
def test_a_round_change_clears_the_goal_and_re_renders_the_shown_camera(viewer):
    from pipeline.view.server import CameraKey
    server, v = viewer
    run = v.run
    v.show_round(1)
    v.goal_start.value, v.goal_width.value = 90.0, 150.0
    goal = v.score()
    assert goal is not None and v.goal_sector is not None and "Next best view" in v.goal_text.content
    key = CameraKey("test", run.views.test_ids[0])
    v.show_camera(key)
    before = np.array(v.image_render.image)
    v.show_round(0)
    assert v.goal is None and v.goal_sector is None  # the red sector is gone with the scores
    assert "Next best view" not in v.goal_text.content and "Round changed to 0" in v.goal_text.content
    assert v.shown == key and "round 0's model" in v.camera_text.content
    if not run.round_state(0).model_is_final:  # each round's own model: the panel changed with it
        assert not np.array_equal(np.asarray(before), np.asarray(v.image_render.image))


def test_the_camera_dropdown_follows_the_shown_camera_and_inspecting_never_edits_the_goal(viewer):
    from pipeline.view.server import CameraKey
    server, v = viewer
    view = v.run.views.pool_ids[-1]
    v.goal_kind.value, v.goal_views.value = "picked cameras", ""
    v.show_camera(CameraKey("pool", view))  # e.g. a click on its frustum
    assert v.camera_choice.value == f"pool {view}" and v.shown == CameraKey("pool", view)
    assert v.goal_views.value == ""          # looking at a camera is not adding it
    v.add_shown_to_goal()
    v.add_shown_to_goal()                     # twice: still once
    assert v.goal_views.value == str(view)
    v.show_camera(CameraKey("test", v.run.views.test_ids[0]))
    v.add_shown_to_goal()
    assert v.goal_views.value == str(view) and "test views cannot" in v.goal_text.content


def test_candidate_colours_cannot_be_confused_with_any_role_and_there_is_a_legend(viewer):
    from pipeline.view.geometry import ROLE_COLOURS, standing_colour
    from pipeline.view.server import LEGEND
    ramp = np.array([standing_colour(x) for x in np.linspace(0, 1, 21)], dtype=float)
    for role in ("initial", "selected", "picked", "probe", "test"):
        nearest = np.linalg.norm(ramp - np.array(ROLE_COLOURS[role], dtype=float), axis=1).min()
        assert nearest > 60, (role, nearest)
    assert standing_colour(0.0) != standing_colour(1.0)
    for word in ("blue", "green", "red", "purple", "grey", "dark teal", "bright cyan", "orange"):
        assert word in LEGEND


def test_a_sweep_folder_lists_its_jobs_and_a_moved_scene_is_found_with_data_root(tiny_run, tmp_path, capsys):
    import shutil
    from pipeline.cli.view import main
    from pipeline.view.run import load_run
    job_dir = tiny_run["gopre"]
    sweep = job_dir.parent.parent
    assert main([str(sweep)]) == 1
    err = capsys.readouterr().err
    assert "is a sweep folder" in err and "gopre / " in err and job_dir.name in err
    # the sweep copied elsewhere, its scene moved: found by --data-root, named when missing
    copy = tmp_path / "copied"
    shutil.copytree(sweep, copy, ignore=shutil.ignore_patterns("mlflow.db", "mlartifacts"))
    run = load_run(str(job_dir))
    scene = Path(run.job.scene_path).resolve()
    moved = tmp_path / "data" / scene.name
    shutil.copytree(scene, moved)
    jobs = json.loads((copy / "jobs.json").read_text())
    for j in jobs:
        j["scene_path"] = "/nowhere/" + scene.name
    (copy / "jobs.json").write_text(json.dumps(jobs))
    (copy / "jobs" / job_dir.name / "artifacts" / "result.json").write_text(json.dumps(
        {**json.loads((job_dir / "artifacts" / "result.json").read_text()), "scene": "/nowhere/x"}))
    with pytest.raises(ValueError, match="--data-root"):
        load_run(str(copy / "jobs" / job_dir.name))
    assert load_run(str(copy / "jobs" / job_dir.name), data_root=str(tmp_path / "data")).scene is not None
    assert load_run(str(copy / "jobs" / job_dir.name), scene=str(moved)).selected == run.selected


@pytest.mark.e2e
@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium on this machine: `make e2e` installs it")
def test_each_browser_tab_has_its_own_goal(tiny_run):
    """pipeline-view serves one viewer per tab: a goal scored in one tab is not in a second one."""
    playwright_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed (dev extra)")
    from pipeline.cli.view import start
    server, viewers = start(str(tiny_run["gopre"]), port=free_port(), per_client=True)
    try:
        with playwright_api.sync_playwright() as p:
            browser, first = browser_page(p)
            try:
                url = f"http://127.0.0.1:{server.get_port()}/"
                first.goto(url)
                first.wait_for_function("document.body.innerText.includes('Score next view')", timeout=60_000)
                first.get_by_role("button", name="Score next view").click()
                first.wait_for_function("document.body.innerText.includes('Next best view: pool')", timeout=60_000)
                second = browser.new_page(viewport={"width": 1200, "height": 800})
                second.goto(url)
                second.wait_for_function("document.body.innerText.includes('Score next view')", timeout=60_000)
                deadline = time.time() + 30  # the page may show the panel before the server registers its viewer
                while len(viewers) < 2 and time.time() < deadline:
                    time.sleep(0.1)
                assert len(viewers) == 2
                body = second.inner_text("body")
                assert "Next best view: pool" not in body and "Draw a goal" in body
                assert "Next best view: pool" in first.inner_text("body")  # the first tab kept its own
            finally:
                browser.close()
    finally:
        server.stop()


@pytest.mark.e2e
@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium on this machine: `make e2e` installs it")
def test_the_viewers_state_rows_in_a_browser(tiny_run):
    """Issue 29's viewer rows, driven in Chromium: a round change (the slider, by keyboard) clears
    the scored goal on the page; a camera shown from the scene (what a frustum click does) moves
    the dropdown; choosing a camera in 'picked cameras' mode does not add it to the goal, the Add
    button does; the colour legend is on the page."""
    playwright_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed (dev extra)")
    from pipeline.cli.view import start
    from pipeline.view.server import CameraKey

    def until(condition, what: str, seconds: float = 60) -> None:
        deadline = time.time() + seconds
        while time.time() < deadline and not condition():
            time.sleep(0.2)
        assert condition(), what

    server, v = start(str(tiny_run["gopre"]), port=free_port())
    try:
        with playwright_api.sync_playwright() as p:
            browser, page = browser_page(p)
            try:
                page.goto(f"http://127.0.0.1:{server.get_port()}/")
                page.wait_for_function("document.body.innerText.includes('Score next view')", timeout=60_000)
                body = page.inner_text("body")
                for word in ("Colours", "dark teal", "bright cyan", "purple"):
                    assert word in body, word
                # a round change clears the goal's result on the page
                page.get_by_role("button", name="Score next view").click()
                page.wait_for_function("document.body.innerText.includes('Next best view: pool')", timeout=60_000)
                assert v.state.index > 0
                slider = page.get_by_role("slider").first
                slider.focus()
                slider.press("Home")
                page.wait_for_function("document.body.innerText.includes('Round changed to 0')", timeout=60_000)
                assert v.state.index == 0 and v.goal is None
                assert "Next best view: pool" not in page.inner_text("body")
                # a camera shown from the scene moves the dropdown
                view = v.run.views.pool_ids[-1]
                v.show_camera(CameraKey("pool", view))
                choice = page.get_by_label("Camera view", exact=True)
                until(lambda: choice.input_value() == f"pool {view}", "the dropdown did not follow")
                # inspecting in 'picked cameras' mode leaves the goal alone; Add adds
                page.get_by_label("Goal", exact=True).click()
                page.get_by_role("option", name="picked cameras", exact=True).click()
                until(lambda: v.goal_kind.value == "picked cameras", "the goal kind did not change")
                other = v.run.views.pool_ids[0]
                choice.click()
                page.get_by_role("option", name=f"pool {other}", exact=True).click()
                until(lambda: v.shown == CameraKey("pool", other), "the chosen camera was not shown")
                # viser's text input is not linked to its label: the input in the label's row
                picked = page.locator("xpath=//label[text()='Picked views']/ancestor::div"
                                      "[contains(@class, 'mantine-Flex-root')][1]//input")
                assert v.goal_views.value == "" and picked.input_value() == ""
                page.get_by_role("button", name="Add the shown camera to the picked views").click()
                until(lambda: picked.input_value() == str(other), "Add did not add")
            finally:
                browser.close()
    finally:
        server.stop()


# -- an episode off the pool (issue 28) -------------------------------------------------------------
@pytest.fixture(scope="module")
def off_pool_run(tmp_path_factory):
    """experiment=debug with gopre_search (the generated world), the round models kept."""
    out = tmp_path_factory.mktemp("view_world") / "debug"
    subprocess.run([str(Path(sys.executable).parent / "gopre-run"), "experiment=debug", "method=[gopre_search]",
                    "executor=local", "tracking=none", f"output_dir={out}", "job.round_models=true"],
                   cwd=ROOT, check=True, capture_output=True, timeout=600)
    return Path(json.loads((out / "jobs.json").read_text())[0]["execution"]["job_dir"])


def test_the_viewer_shows_views_captured_off_the_pool_and_the_searched_landscape(off_pool_run):
    import torch

    from pipeline.cli.view import start
    from pipeline.view.server import CameraKey
    server, v = start(str(off_pool_run), port=free_port())
    try:
        run = v.run
        captured = [view for view in run.selected if run.is_captured(view)]
        assert captured and run.captured is not None and len(run.captured) == len(captured)
        keys = [CameraKey("captured", view - run.first_captured) for view in captured]
        assert all(key in v.frustums for key in keys)
        for index in range(len(run.rounds)):  # a captured view appears in the round that picks it
            v.show_round(index)
            taken_or_picked = set(v.state.taken) | set(v.state.picked)
            for view, key in zip(captured, keys):
                assert v.frustums[key].visible == (view in taken_or_picked), (index, view)
            search = run.rounds[index]["search"]
            assert v.landscape is not None and len(search["evaluated"]) == search["evaluations"]
        v.show_camera(keys[0])  # its panel: the captured image, a render, a variance map
        assert "captured off the pool" in v.camera_text.content and "azimuth" in v.camera_text.content
        truth = np.asarray(v.image_truth.image)
        expected = np.asarray(run.captured.images[0].clamp(0, 1).mul(255).round().byte())
        assert truth.shape[0] % expected.shape[0] == 0 and (truth[::truth.shape[0] // expected.shape[0],
                                                                 ::truth.shape[0] // expected.shape[0]] == expected).all()
        assert torch.equal(run.cameras_of([captured[0]]).viewmats, run.captured.cameras.viewmats[:1])
        goal = v.score()  # a goal scored with captured views among the taken ones
        assert goal is not None and goal.best in run.views.pool_ids
        assert "captured off the pool" in v.camera_list.content
    finally:
        server.stop()


def test_the_report_of_a_real_off_pool_sweep_has_its_search_section(off_pool_run, tmp_path):
    from pipeline.report.report import make_report
    sweep = off_pool_run.parent.parent
    report = make_report(sweep, tmp_path / "report")
    text = (tmp_path / "report" / "search.md").read_text()
    line = next(r for r in text.splitlines() if r.startswith("| generated |") and "gopre_search" in r)
    assert line.split("|")[5].strip() == "2"  # the debug episode's two selection rounds
    assert "search_landscape_0.png" in report["figures"]
    result = json.loads((off_pool_run / "artifacts" / "result.json").read_text())
    drawn = report["figures"]["search_landscape_0.png"]
    assert len(drawn) == sum(1 for r in result["rounds"] if r.get("search"))
