"""Which way is up: the cameras' mean up, the points' dominant plane and the camera centres'
smallest axis, checked on scenes built by hand (a ring of cameras over a table, held upright and
held sideways), the choice a dataset entry or a capture makes, and the warning when they disagree."""

import json
import math

import pytest
import torch

from pipeline.cameras import Cameras, intrinsics_from_fov, look_at
from pipeline.data.orientation import (DISAGREE_DEG, angle_deg, camera_up, orientation, parse_up, pca_up,
                                       plane_up)

TRUE_UP = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64), dim=0)


def _frame(up):
    """An orthonormal basis (e1, e2) of the plane orthogonal to ``up``."""
    a = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    e1 = torch.nn.functional.normalize(a - (a @ up) * up, dim=0)
    return e1, torch.linalg.cross(up, e1)


def ring(count=24, sideways=False, up=TRUE_UP, arc_deg=360.0):
    """Cameras on a circle 0.6 above a table (the plane through the origin orthogonal to ``up``),
    looking at the origin; ``sideways``: each rolled 90 degrees about its optical axis (a phone held
    sideways, no orientation tag); ``arc_deg``: the part of the circle walked."""
    e1, e2 = _frame(up)
    angles = torch.arange(count, dtype=torch.float64) * math.radians(arc_deg) / count
    eyes = 2.0 * (torch.cos(angles)[:, None] * e1 + torch.sin(angles)[:, None] * e2) + 0.6 * up
    viewmats = look_at(eyes, torch.zeros_like(eyes), up)
    if sideways:  # roll about the camera's own z axis: image x becomes the old -y
        roll = torch.tensor([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        viewmats[:, :3, :] = roll @ viewmats[:, :3, :]
    return Cameras(viewmats.float(), intrinsics_from_fov(1.0, 64, 48, count), 64, 48)


def table_points(up=TRUE_UP, count=3000, seed=0):
    """Most points on the table plane, the rest an object above it."""
    gen = torch.Generator().manual_seed(seed)
    e1, e2 = _frame(up)
    flat = torch.rand(count, 2, generator=gen, dtype=torch.float64) * 4 - 2
    table = flat[:, :1] * e1 + flat[:, 1:] * e2 + 0.002 * torch.randn(count, 1, generator=gen, dtype=torch.float64) * up
    blob = torch.randn(count // 2, 3, generator=gen, dtype=torch.float64) * 0.2 + 0.4 * up
    return torch.cat([table, blob]).float()


def test_upright_cameras_over_a_table_agree_on_up():
    cams, points = ring(), table_points()
    assert angle_deg(camera_up(cams), TRUE_UP) < 0.01
    normal, inliers = plane_up(points, cams)
    assert angle_deg(normal, TRUE_UP) < 0.5 and inliers == pytest.approx(2 / 3, abs=0.02)
    assert angle_deg(pca_up(cams, points), TRUE_UP) < 0.01
    found = orientation(cams, points)
    assert found.method == "cameras" and found.warning() is None and max(found.angles_deg.values()) < 0.5


def test_a_sideways_phone_is_caught_and_the_plane_or_pca_set_it_right():
    """The issue's capture: cameras' up 90 degrees off, the table's normal right; warned."""
    cams, points = ring(sideways=True, arc_deg=200), table_points()  # a walk around the table's near side
    assert angle_deg(camera_up(cams), TRUE_UP) == pytest.approx(90.0, abs=0.5)
    found = orientation(cams, points)
    assert found.method == "cameras" and found.angles_deg["plane"] > DISAGREE_DEG
    assert "up axis (cameras) disagrees" in found.warning() and "plane 90 deg away, pca 90 deg away" in found.warning()
    for method in ("plane", "pca"):
        chosen = orientation(cams, points, method)
        assert chosen.method == method and angle_deg(torch.tensor(chosen.up, dtype=torch.float64), TRUE_UP) < 0.5
        assert chosen.warning() is None  # chosen on purpose: recorded, not warned about
    one_off = orientation(cams, None, None)  # no points, no plane: pca alone still disagrees
    assert one_off.warning() is not None


def test_the_normal_points_towards_the_cameras_whatever_its_sign_from_ransac():
    cams, points = ring(), table_points()
    flipped = orientation(cams, points, "plane").up
    assert float(torch.tensor(flipped, dtype=torch.float64) @ TRUE_UP) > 0.99
    below = ring(up=-TRUE_UP)  # the same ring seen upside down: the cameras are below the table now
    assert float(plane_up(table_points(up=-TRUE_UP), below)[0] @ TRUE_UP) < -0.99


def test_one_estimate_that_fails_alone_is_no_warning():
    """alexander: a wall outweighs the floor, so the plane is 105 degrees off while the cameras and
    pca agree; only an axis far from every other estimate is warned about."""
    from pipeline.data.orientation import Orientation
    assert Orientation([0, 0, 1], "cameras", {}, {"cameras": 0.0, "plane": 104.7, "pca": 20.5}).warning() is None
    assert Orientation([0, 0, 1], "cameras", {}, {"cameras": 0.0, "plane": 148.2, "pca": 105.6}).warning()
    assert Orientation([0, 0, 1], "cameras", {}, {"cameras": 0.0, "pca": 31.0}).warning()


def test_whichever_sign_a_fit_returns_the_normal_is_turned_towards_the_cameras():
    from pipeline.data.orientation import _towards_cameras
    cams, points = ring(), table_points()
    for normal in (TRUE_UP, -TRUE_UP):
        assert float(_towards_cameras(normal, cams, points) @ TRUE_UP) == pytest.approx(1.0)
        assert float(_towards_cameras(normal, cams, None) @ TRUE_UP) == pytest.approx(1.0)  # by the cameras' up
    below = ring(up=-TRUE_UP)  # cameras under the table: its normal points down, towards them
    assert float(_towards_cameras(TRUE_UP, below, table_points(up=-TRUE_UP)) @ TRUE_UP) == pytest.approx(-1.0)


def test_an_explicit_vector_and_bad_values():
    cams = ring()
    given = orientation(cams, None, [0, 0, 2])
    assert given.method == "given" and given.up == [0.0, 0.0, 1.0] and "plane" not in given.estimates
    assert parse_up("0,0,1") == [0.0, 0.0, 1.0] and parse_up("pca") == "pca" and parse_up(None) is None
    for bad in ("sideways", [0, 0, 0], [1, 2], "1,x,3"):
        with pytest.raises(ValueError, match="up:"):
            parse_up(bad)
    with pytest.raises(ValueError, match="up: 'plane' cannot be estimated here \\(no points\\)"):
        orientation(cams, None, "plane")


def test_the_protocol_takes_its_sector_about_the_chosen_axis(tmp_path):
    """A sideways capture with up=plane has the goal views of the same capture held upright; about
    the cameras' own (tilted) axis its sector holds other views."""
    from pipeline.data.protocols import ProtocolConfig, build_protocol
    from pipeline.data.scene import Scene, Split

    def scene(cams):
        store = type("Store", (), {"paths": [], "__len__": lambda self: 64})()
        return Scene("ring", "colmap", tmp_path, {"all": Split(cams, store, [str(i) for i in range(64)])},
                     torch.zeros(3), points=table_points())

    def goal_views(views):
        return set(views.probe_ids) | set(views.test_ids)
    upright = build_protocol(scene(ring(64, arc_deg=300)), ProtocolConfig(kind="goal"))
    sideways = scene(ring(64, sideways=True, arc_deg=300))
    plane = build_protocol(sideways, ProtocolConfig(kind="goal", up="plane"))
    default = build_protocol(sideways, ProtocolConfig(kind="goal"))
    assert angle_deg(torch.tensor(plane.up, dtype=torch.float64), TRUE_UP) < 0.5
    assert angle_deg(torch.tensor(default.up, dtype=torch.float64), TRUE_UP) > 80
    assert len(goal_views(plane) ^ goal_views(upright)) <= 1 and len(goal_views(upright)) > 10
    assert len(goal_views(default) ^ goal_views(upright)) > 5


def test_a_dataset_entry_sets_up_and_only_then_enters_the_hash(tmp_path):
    from hydra import compose, initialize_config_dir

    from pipeline.cli.run import CONF_DIR
    from pipeline.experiment.build import expand_jobs
    base = ["splat=tiny", "dataset=[generated]", "executor=local", "tracking=none", "method=[random]",
            f"output_dir={tmp_path}"]
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        plain = expand_jobs(compose("config", base))[0]
        chosen = expand_jobs(compose("config", [*base, "+dataset.generated.up=pca"]))[0]
    assert "up" not in plain.protocol and chosen.protocol["up"] == "pca"
    assert chosen.episode.protocol.up == "pca" and chosen.config_hash != plain.config_hash


def test_a_captures_up_choice_is_read_with_the_scene(tmp_path):
    from pipeline.data.colmap import read_colmap
    from tests.test_data_colmap_protocols import write_text_model
    root = write_text_model(tmp_path / "s", "1 PINHOLE 80 60 50 50 40 30")
    assert "up" not in read_colmap(root).info
    (root / "capture.json").write_text(json.dumps({"orientation": {"choice": [0, 1, 0]}}))
    assert read_colmap(root).info["up"] == [0.0, 1.0, 0.0]
    (root / "capture.json").write_text(json.dumps({"orientation": {"choice": "upside"}}))
    with pytest.raises(Exception, match=r"capture.json: orientation.choice: up: expected one of"):
        read_colmap(root)
