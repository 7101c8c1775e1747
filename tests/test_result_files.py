"""result.json and benchmark definitions: every finished episode writes a result that validates
against the package's JSON Schema (checked with jsonschema), whose views equal the preset's
benchmark definition; a result written without the pipeline's selection code is accepted in the
report beside the sweep's rows; a changed split or ground-truth hash is refused naming the field."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import jsonschema
import pytest
from hydra import compose, initialize_config_dir

from pipeline.cli.data import write_benchmark
from pipeline.cli.report import main as report_main
from pipeline.cli.run import CONF_DIR
from pipeline.experiment.sweep import run_sweep
from pipeline.interchange.documents import DocumentError, _validator, schema
from pipeline.interchange.hashes import file_sha256, pixels_sha256
from pipeline.report.external import external_rows

ROOT = Path(__file__).resolve().parents[1]
GOAL = ["splat=tiny", "splat.iterations=60", "dataset=[generated]", "dataset.generated.generate.size=32",
        "dataset.generated.generate.n_train=24", "dataset.generated.generate.n_test=12",
        "protocol.initial_views=2", "protocol.budget=4", "protocol.probes=2"]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("interchange") / "sweep"
    overrides = ["experiment=table2_goal", "method=[gopre,random]", *GOAL, "executor=local", "tracking=none",
                 f"output_dir={out}", "seeds=[0,1]"]
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides)
    assert run_sweep(cfg).finished == 4
    bench = out.parent / "bench.json"
    write_benchmark("table2_goal", overrides[1:], bench)
    return out, bench


def results(out: Path) -> list[Path]:
    return sorted(out.glob("jobs/*/artifacts/benchmark/result.json"))


def test_every_episode_writes_a_result_valid_under_the_schema(sweep):
    out, bench = sweep
    files = results(out)
    assert len(files) == 4
    for path in files:
        doc = json.loads(path.read_text())
        jsonschema.validate(doc, schema("result"))  # the package's schema, by jsonschema itself
        assert doc["benchmark"]["protocol"] == "goal" and doc["method"]["name"] in ("gopre", "random")
        scene = Path(doc["config"]["scene_path"])
        for view, name in doc["views"]["test_image_files"].items():  # hashes of the files themselves
            assert doc["views"]["test_image_sha256"][view] == file_sha256(scene / name)
        taken = doc["views"]["initial_ids"] + [i for r in doc["rounds"] for i in r["selected"]]
        assert len(taken) == doc["views"]["budget"] == doc["final"]["num_views"]
        assert sorted(p["test_id"] for p in doc["final"]["per_image"]) == sorted(doc["views"]["test_ids"])


def test_every_episode_records_its_final_models_pixel_uncertainty(sweep, tmp_path):
    """unc_* columns from the job's rendered test views, and their table in the report."""
    import math

    from pipeline.experiment.records import RecordsFile
    out, _ = sweep
    finals = RecordsFile(out).frame.query("kind == 'final'")
    for column in ("unc_ause_mae_max", "unc_ause_mae_start", "unc_ause_rmse_max", "unc_ause_dssim_start",
                   "unc_nll", "unc_auce", "unc_pearson", "unc_spearman"):
        assert finals[column].map(math.isfinite).all(), column
    assert (finals["unc_views"] >= 1).all() and finals["unc_pearson"].between(-1, 1).all()
    assert finals["unc_auce"].between(0, 1).all()
    assert report_main([str(out), "--out", str(tmp_path / "r"), "--no-images"]) == 0
    table = (tmp_path / "r" / "table.md").read_text()
    assert "pixel-level uncertainty of the final model" in table and "AUSE MAE (start-norm.)" in table
    assert (finals["path_length"] > 0).all() and "Camera path (pool diameters)" in table
    assert finals["depth_abs_rel"].between(0, 1).all() and (finals["depth_pixels"] > 0).all()  # the generated scene
    assert "Depth abs rel" in table
    assert (tmp_path / "r" / "figures" / "pixel_sparsification.png").exists()  # Fig. 7 extended


def test_the_sweep_uses_exactly_the_benchmark_definition(sweep):
    out, bench = sweep
    definition = json.loads(bench.read_text())
    assert not list(_validator("benchmark").iter_errors(definition))
    entries = {(e["benchmark"]["scene"], e["benchmark"]["seed"]): e for e in definition["entries"]}
    draws = set()
    assert len(entries) == 2  # one per (scene, seed): the methods share it
    for path in results(out):
        doc = json.loads(path.read_text())
        entry = entries[(doc["benchmark"]["scene"], doc["benchmark"]["seed"])]
        assert doc["views"] == entry["views"]
        picked = [r for r in doc["rounds"] if r["selected"]]
        assert [r["probes"] for r in picked] == [r["probes"] for r in entry["rounds"]]
        draws.add(json.dumps([r["probes"] for r in picked]))
        assert [r["num_views"] for r in picked] == [r["num_views"] for r in entry["rounds"]]
    assert len(draws) > 1  # the probes differ between seeds and rounds: the comparison can fail


def test_render_hash_convention():
    import numpy as np
    pixels = np.zeros((2, 3, 3))
    pixels[0, 0] = [1.0, 0.5, 2.0]  # clipped and rounded: 255, 128, 255
    expected = np.zeros((2, 3, 3), dtype=np.uint8)
    expected[0, 0] = [255, 128, 255]
    import hashlib
    assert pixels_sha256(pixels) == hashlib.sha256(expected.tobytes()).hexdigest()


@pytest.fixture(scope="module")
def external(sweep, tmp_path_factory):
    """A result.json from examples/external_result.py, which imports nothing of the pipeline."""
    out, bench = sweep
    script = ROOT / "examples" / "external_result.py"
    assert "pipeline" not in "".join(line for line in script.read_text().splitlines()
                                     if line.startswith(("import", "from")))
    scene = Path(json.loads(results(out)[0].read_text())["config"]["scene_path"])
    target = tmp_path_factory.mktemp("external") / "result.json"
    subprocess.run([sys.executable, str(script), str(bench), str(scene), "--scene", "generated", "--seed", "0",
                    "--out", str(target)], check=True, capture_output=True)
    return target


def test_an_outside_result_is_accepted_beside_the_sweep(sweep, external, tmp_path, capsys):
    out, bench = sweep
    assert report_main([str(out), "--results", str(external), "--out", str(tmp_path / "r")]) == 0
    table = (tmp_path / "r" / "table.md").read_text()
    assert "| mean_colour |" in table and "| gopre |" in table
    paired = [line for line in table.splitlines() if line.startswith("| mean_colour | 1 |")]
    assert paired, "the outside method's paired comparison against gopre"
    # against the published definition alone, without the sweep
    assert report_main(["--results", str(external), "--benchmark", str(bench), "--out", str(tmp_path / "b")]) == 0


def changed(external: Path, tmp_path: Path, edit) -> Path:
    doc = json.loads(external.read_text())
    edit(doc)
    path = tmp_path / "changed.json"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["views"].update(test_ids=d["views"]["test_ids"][1:]), r"views.test_ids is \["),
    (lambda d: d["views"]["test_image_sha256"].update({next(iter(d["views"]["test_image_sha256"])): "0" * 64}),
     r"views.test_image_sha256 differs from .* for test view\(s\) \[.*\]: not the same ground-truth images"),
    (lambda d: d["views"].update(initial_ids=[1, 2]), r"views.initial_ids is \[1, 2\]"),
    (lambda d: d["benchmark"].update(seed=7), r"no benchmark definition for generated/generated goal seed 7"),
    (lambda d: d["rounds"][0]["selected"].append(10_000), r"rounds select view\(s\) \[10000\] outside"),
    (lambda d: d["rounds"][0]["selected"].append(next(i for i in d["views"]["pool_ids"] if i not in {
        *d["views"]["initial_ids"], *(j for r in d["rounds"] for j in r["selected"])})),
     r"5 views taken, over the benchmark's budget of 4"),
    (lambda d: d["final"].pop("per_image"), r"not a valid result file .*final: 'per_image' is a required property"),
])
def test_a_result_that_does_not_match_is_refused_naming_the_field(sweep, external, tmp_path, edit, message):
    out, bench = sweep
    path = changed(external, tmp_path, edit)
    with pytest.raises(DocumentError, match=message) as err:
        external_rows([str(path)], [str(bench)], [], set())
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


def _duplicate_pick(d):
    picked = next(r for r in d["rounds"] if r["selected"])
    later = next(r for r in d["rounds"][d["rounds"].index(picked) + 1:] if r["selected"])
    later["selected"][0] = picked["selected"][0]


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["final"].update(psnr=40.0),
     r"final.psnr is 40.0, the mean of final.per_image's psnr is \d+\.\d{4} \(tolerance 0.01 dB\)"),
    (lambda d: d["final"].update(ssim=0.99) if d["final"].get("ssim") is not None else d["final"].update(
        ssim=0.99, per_image=[{**p, "ssim": 0.5} for p in d["final"]["per_image"]]),
     r"final.ssim is 0.99, the mean of final.per_image's ssim is"),
    (lambda d: d["final"].update(num_views=d["final"]["num_views"] + 1), r"final.num_views is \d+, the rounds took \d+ views"),
    (lambda d: d["views"].update(image_width=d["views"]["image_width"] * 2),
     r"views.image_width is \d+, .* has \d+: scored at another resolution"),
    (_duplicate_pick, r"rounds\[\d+\].selected takes view\(s\) \[\d+\] already taken or twice"),
    (lambda d: d["rounds"][1].update(num_views=d["rounds"][1]["num_views"] + 1),
     r"rounds\[1\].num_views is \d+, but \d+ views were taken by then"),
])
def test_a_result_that_contradicts_itself_is_refused_naming_the_field(sweep, external, tmp_path, edit, message):
    """The headline must be what the per-image values say, and the rounds what they took."""
    _, bench = sweep
    path = changed(external, tmp_path, edit)
    with pytest.raises(DocumentError, match=message) as err:
        external_rows([str(path)], [str(bench)], [], set())
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


def test_a_result_named_like_a_sweep_method_but_another_one_is_refused(sweep, external, tmp_path, capsys):
    """Named `gopre` it would merge into the sweep's reference row."""
    out, bench = sweep
    path = changed(external, tmp_path, lambda d: d["method"].update(name="gopre"))
    assert report_main([str(out), "--results", str(path), "--out", str(tmp_path / "r")]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith(f"gopre-report: error: {path}: method.name 'gopre' is a method of the "
                                              "reported sweep, but this result is another identity")
    # against the definition alone there is no sweep row to merge into: accepted under that name
    assert report_main(["--results", str(path), "--benchmark", str(bench), "--out", str(tmp_path / "b")]) == 0


@pytest.fixture(scope="module")
def with_renders(sweep, tmp_path_factory):
    """The outside result again, shipping its renders (renders/<test_id>.png beside it)."""
    out, bench = sweep
    scene = Path(json.loads(results(out)[0].read_text())["config"]["scene_path"])
    target = tmp_path_factory.mktemp("shipped") / "result.json"
    subprocess.run([sys.executable, str(ROOT / "examples" / "external_result.py"), str(bench), str(scene), "--scene",
                    "generated", "--seed", "0", "--out", str(target), "--renders"], check=True, capture_output=True)
    return target, scene


def test_shipped_renders_are_scored_against_the_episodes_ground_truth(sweep, with_renders, tmp_path):
    """The example resizes the ground truth its own way (bicubic); the report scores its renders
    against the ground truth as the episodes read it, and says so in the rows."""
    import numpy as np
    from PIL import Image

    from pipeline.cli.report import RenderScorer
    from pipeline.data.load import load_scene
    out, bench = sweep
    path, scene_path = with_renders
    doc = json.loads(path.read_text())
    rows = external_rows([str(path)], [str(bench)], [out], set(), rescore=RenderScorer([out]))
    final = rows[rows["kind"] == "final"].iloc[0]
    assert final["metrics_source"].startswith("recomputed from its ")
    test = load_scene(scene_path, width=doc["views"]["image_width"]).split(doc["views"]["test_split"])
    by_hand = []
    for item in doc["final"]["per_image"]:
        pixels = np.asarray(Image.open(path.parent / "renders" / f"{item['test_id']}.png"), dtype=np.float64) / 255
        mse = np.mean((pixels - test.images[item["test_id"]].double().numpy()) ** 2)
        by_hand.append(-10 * np.log10(mse))
    assert final["psnr"] == pytest.approx(np.mean(by_hand), abs=1e-6)  # the render as float32 pixels
    assert final["psnr"] != pytest.approx(doc["final"]["psnr"], abs=1e-6)  # the file's own convention differs
    plain = external_rows([str(path)], [str(bench)], [out], set())  # no scorer: as the file states
    assert plain[plain["kind"] == "final"].iloc[0]["psnr"] == pytest.approx(doc["final"]["psnr"])


@pytest.mark.parametrize("damage, message", [
    (lambda folder, view: __import__("PIL.Image").Image.new("RGB", (48, 48), (1, 2, 3)).save(folder / f"{view}.png"),
     r"renders/\d+.png: its pixels are not final.per_image's render_sha256 for test view \d+"),
    (lambda folder, view: (folder / f"{view}.png").unlink(), r"renders/\d+.png is missing"),
])
def test_a_render_that_is_not_what_the_file_says_is_refused(sweep, with_renders, tmp_path, damage, message):
    from pipeline.cli.report import RenderScorer
    out, bench = sweep
    path, _ = with_renders
    copy = tmp_path / "copy"
    shutil.copytree(path.parent, copy)
    view = json.loads(path.read_text())["final"]["per_image"][1]["test_id"]
    damage(copy / "renders", view)
    with pytest.raises(DocumentError, match=message) as err:
        external_rows([str(copy / "result.json")], [str(bench)], [out], set(), rescore=RenderScorer([out]))
    assert "\n" not in str(err.value)


def test_the_report_command_refuses_with_one_line(sweep, external, tmp_path, capsys):
    out, _ = sweep
    path = changed(external, tmp_path, lambda d: d["views"].update(budget=9))
    assert report_main([str(out), "--results", str(path), "--out", str(tmp_path / "r")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("gopre-report: error: ") and "views.budget is 9" in err and "\n" not in err
