"""``pipeline-eval``: an outside PLY scored on a scene's test views with the episodes' metrics."""

import json
import math

import pytest

from pipeline.data.load import load_scene
from pipeline.data.synthetic import generate
from pipeline.cli.eval import main
from pipeline.eval.model import evaluate_model
from pipeline.splat import ply, render
from pipeline.splat.scenes import random_scene


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene") / "generated"
    generate(out, seed=0, size=32, n_train=8, n_test=5)
    return out


def test_each_test_views_psnr_is_the_render_against_the_photo(scene_dir, tmp_path):
    model = ply.save(random_scene(300, seed=3, sh_degree=1, extent=0.8), tmp_path / "m.ply")
    result = evaluate_model(model, scene_dir, lpips=False)
    scene = load_scene(scene_dir)
    test = scene.split("test")
    assert result["test_views"] == len(test) == 5 and result["width"] == 32
    g = ply.load(model)
    for row in result["per_view"]:
        pred = render(g, test.cameras[[row["id"]]], scene.background).rgb[0].clamp(0, 1)
        mse = float((pred.double() - test.images[row["id"]].double()).square().mean())
        assert row["psnr"] == pytest.approx(-10 * math.log10(mse), rel=1e-9)
    assert result["psnr"] == pytest.approx(sum(r["psnr"] for r in result["per_view"]) / 5)
    assert result["lpips"] is None and result["lpips_status"] == "LPIPS not requested"


def test_the_goal_protocol_scores_only_the_sector_and_the_width_rescales(scene_dir, tmp_path):
    model = ply.save(random_scene(100, seed=1, sh_degree=0), tmp_path / "m.ply")
    goal = evaluate_model(model, scene_dir, protocol="goal", width=16, lpips=False)
    assert 0 < goal["test_views"] < 5 and goal["width"] == 16


def test_the_command_writes_json_and_names_a_bad_file(scene_dir, tmp_path, capsys):
    model = ply.save(random_scene(100, seed=1, sh_degree=0), tmp_path / "m.ply")
    assert main([str(model), str(scene_dir), "--no-lpips", "--out", str(tmp_path / "o" / "m.json")]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads((tmp_path / "o" / "m.json").read_text())
    (tmp_path / "bad.ply").write_bytes(b"nope")
    assert main([str(tmp_path / "bad.ply"), str(scene_dir)]) == 1
    assert "bad.ply: not a PLY file" in capsys.readouterr().err
    assert main([str(model), str(tmp_path / "nowhere")]) == 1
    assert "nowhere: no such folder" in capsys.readouterr().err


def test_a_real_capture_is_scored_on_every_eighth_view(tmp_path):
    from pathlib import Path
    bonsai = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "colmap" / "bonsai"
    if not bonsai.exists():
        pytest.skip(f"the staged bonsai capture is not at {bonsai}")
    model = ply.save(random_scene(200, seed=0, sh_degree=0, extent=2.0), tmp_path / "m.ply")
    result = evaluate_model(model, bonsai, width=32, lpips=False)
    views = len(load_scene(bonsai, width=32).split(result["test_split"]).cameras)
    assert result["test_views"] == math.ceil(views / 8) == len({r["id"] for r in result["per_view"]})
    assert all(r["id"] % 8 == 0 for r in result["per_view"])


def test_our_own_splat_output_is_scored_and_exported(scene_dir, tmp_path, capsys):
    """gopre-export --format splat wrote a file that gopre-eval and gopre-export could not read
    ('ascii' codec can't decode): it is read as what it holds."""
    from pipeline.cli.export import main as export_main
    g = random_scene(300, seed=3, sh_degree=0, extent=0.8)
    model = ply.save(g, tmp_path / "m.ply")
    assert export_main([str(model), "--format", "splat", "--out", str(tmp_path / "m.splat")]) == 0
    capsys.readouterr()
    assert main([str(tmp_path / "m.splat"), str(scene_dir), "--no-lpips"]) == 0
    from_splat = json.loads(capsys.readouterr().out)
    exact = evaluate_model(model, scene_dir, lpips=False)
    assert from_splat["num_gaussians"] == 300 and abs(from_splat["psnr"] - exact["psnr"]) < 0.5
    assert export_main([str(tmp_path / "m.splat"), "--format", "ply", "--out", str(tmp_path / "back.ply")]) == 0
    assert len(ply.load(tmp_path / "back.ply")) == 300
