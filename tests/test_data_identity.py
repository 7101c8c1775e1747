"""A scene's data identity: the fingerprint of the files its reader takes, in every job's hash, its
records, result.json and benchmark definitions; a relaunch over changed data re-runs those jobs,
says which scene changed and moves the old records aside; a node with another copy refuses."""

import json
import shutil

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir
from PIL import Image

import pipeline.data.fingerprint as fp
from pipeline.data.fingerprint import FileDigests, scene_fingerprint, source_files
from pipeline.data.synthetic import generate
from tests.conftest import shared_scene


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    return generate(tmp_path_factory.mktemp("scenes") / "mine", seed=3, size=32, n_train=12, n_test=6)


def _copy(scene, tmp_path, name="copy"):
    target = tmp_path / name
    shutil.copytree(scene, target)
    return target


def _touch_pixel(path):
    image = Image.open(path)
    image.load()
    pixels = image.load()
    first = pixels[0, 0]
    pixels[0, 0] = tuple((c + 1) % 256 for c in first) if isinstance(first, tuple) else (first + 1) % 256
    image.save(path)


def test_the_same_bytes_elsewhere_are_the_same_data_and_any_change_is_other_data(small_scene, tmp_path):
    digests = FileDigests(tmp_path / "cache.json")
    here = scene_fingerprint(small_scene, digests=digests)
    moved = scene_fingerprint(_copy(small_scene, tmp_path), digests=digests)
    assert moved.digest == here.digest and here.files == 1 + 12 + 1 + 6  # two transforms files, 18 images
    changed = _copy(small_scene, tmp_path, "changed")
    _touch_pixel(changed / "test" / "r_3.png")
    assert scene_fingerprint(changed, digests=digests).digest != here.digest
    renamed = _copy(small_scene, tmp_path, "renamed")  # the same bytes under other frame names
    for split in ("train",):
        meta = json.loads((renamed / f"transforms_{split}.json").read_text())
        meta["frames"][0], meta["frames"][1] = meta["frames"][1], meta["frames"][0]  # two poses swap images
        (renamed / f"transforms_{split}.json").write_text(json.dumps(meta))
    assert scene_fingerprint(renamed, digests=digests).digest != here.digest


def test_a_file_the_reader_does_not_take_is_not_the_scenes_data(small_scene, tmp_path):
    copy = _copy(small_scene, tmp_path)
    before = scene_fingerprint(copy).digest
    (copy / "notes.txt").write_text("a file beside the scene")
    (copy / "train" / "unused.png").write_bytes((copy / "train" / "r_0.png").read_bytes())
    assert scene_fingerprint(copy).digest == before


def test_the_digest_is_the_file_list_by_hand(small_scene):
    import hashlib
    lines = sorted(f"{p.resolve().relative_to(small_scene.resolve()).as_posix()}\t"
                   f"{hashlib.sha256(p.read_bytes()).hexdigest()}" for p in source_files(small_scene))
    expected = hashlib.sha256(("\n".join(lines) + "\n").encode()).hexdigest()
    assert scene_fingerprint(small_scene).digest == expected


def test_file_digests_are_cached_by_path_size_and_mtime(small_scene, tmp_path, monkeypatch):
    copy, cache = _copy(small_scene, tmp_path), tmp_path / "cache.json"
    reads = []
    real = fp.file_sha256
    monkeypatch.setattr(fp, "file_sha256", lambda path: reads.append(path) or real(path))
    first = scene_fingerprint(copy, digests=FileDigests(cache))
    FileDigests(cache)  # nothing written yet by a caller that passes its own digests: save is theirs
    scene_fingerprint(copy)  # a launch's own cache (GOPRE_CACHE)
    monkeypatch.setenv("GOPRE_CACHE", str(tmp_path / "gopre-cache"))
    reads.clear()
    scene_fingerprint(copy)
    assert len(reads) == first.files  # a new cache reads every file once
    reads.clear()
    assert scene_fingerprint(copy).digest == first.digest and reads == []  # then none
    _touch_pixel(copy / "test" / "r_0.png")
    reads.clear()
    assert scene_fingerprint(copy).digest != first.digest
    assert [p.name for p in reads] == ["r_0.png"]  # only the changed file is read again
    meta = copy / "transforms_test.json"  # the same size, other bytes, a later time: read again
    text = meta.read_text()
    swapped = text.replace("0", "#").replace("1", "0").replace("#", "1")
    assert len(swapped) == len(text) and swapped != text
    before = scene_fingerprint(copy).digest
    meta.write_text(swapped)
    import os
    os.utime(meta, ns=(meta.stat().st_atime_ns, meta.stat().st_mtime_ns + 10_000_000))
    reads.clear()
    assert scene_fingerprint(copy).digest != before and [p.name for p in reads] == ["transforms_test.json"]


def test_colmap_sources_are_the_model_and_the_image_folder_and_masks_only_when_read():
    bonsai = shared_scene("colmap", "bonsai")
    files = source_files(bonsai)
    assert sorted(p.name for p in files if p.parent.name == "0") == ["cameras.bin", "images.bin", "points3D.bin"]
    assert sum(p.parent.name == "images" for p in files) == 292


def test_the_fingerprint_enters_the_hash_the_records_and_the_result_file(small_scene, tmp_path):
    from pipeline.experiment.spec import config_hash, without_data_identity
    from pipeline.experiment.build import expand_jobs
    copy = _copy(small_scene, tmp_path, "mine")
    jobs = expand_jobs(_cfg(tmp_path, copy))
    (job,) = jobs
    assert job.data_fingerprint == scene_fingerprint(copy).short and len(job.data_fingerprint) == 16
    assert job.config_hash == config_hash(job.to_dict()) != without_data_identity(job)
    _touch_pixel(copy / "train" / "r_5.png")
    (again,) = expand_jobs(_cfg(tmp_path, copy))
    assert again.data_fingerprint != job.data_fingerprint and again.config_hash != job.config_hash
    assert without_data_identity(again) == without_data_identity(job)  # the same job, other data


def _cfg(tmp_path, scene, *extra):
    from pipeline.cli.run import CONF_DIR
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose("config", ["splat=tiny", "dataset=[blender]", f"dataset.blender.root={scene.parent}",
                                  f"dataset.blender.scenes=[{scene.name}]", "protocol.initial_views=2",
                                  "protocol.budget=3", "protocol.probes=2", "executor=local", "tracking=none",
                                  "method=[random]", "seeds=[0]", f"output_dir={tmp_path / 'out'}", *extra])


def test_a_relaunch_over_changed_data_reruns_says_which_scene_and_keeps_the_old_records(small_scene, tmp_path, capsys):
    from pipeline.experiment.data_changes import SUPERSEDED
    from pipeline.experiment.records import RecordsFile
    from pipeline.experiment.sweep import run_sweep
    copy = _copy(small_scene, tmp_path, "mine")
    first = run_sweep(_cfg(tmp_path, copy))
    assert first.finished == 1
    frame = RecordsFile(tmp_path / "out").frame
    old_hash, old_fp = frame["config_hash"].iloc[0], frame["data_fingerprint"].iloc[0]
    result = json.loads((tmp_path / "out" / "jobs" / old_hash / "artifacts" / "benchmark" / "result.json").read_text())
    assert result["views"]["data_fingerprint"] == old_fp
    assert run_sweep(_cfg(tmp_path, copy)).skipped == 1  # unchanged data: finished
    capsys.readouterr()

    _touch_pixel(copy / "test" / "r_2.png")
    second = run_sweep(_cfg(tmp_path, copy))
    out = capsys.readouterr().out
    assert second.skipped == 0 and second.finished == 1
    assert (f"data changed: dataset.blender scene 'mine' is now {scene_fingerprint(copy).short} (was {old_fp}): "
            f"its 1 finished job(s) re-run; their old records moved to {SUPERSEDED}") in out
    records = RecordsFile(tmp_path / "out").frame
    assert set(records["data_fingerprint"]) == {scene_fingerprint(copy).short}  # one identity per scene
    superseded = pd.read_parquet(tmp_path / "out" / SUPERSEDED)
    assert set(superseded["config_hash"]) == {old_hash} and set(superseded["data_fingerprint"]) == {old_fp}
    assert (tmp_path / "out" / "jobs" / old_hash).is_dir()  # nothing deleted


def test_a_folder_launched_before_data_identity_reruns_and_says_it_cannot_tell(small_scene, tmp_path, capsys):
    from pipeline.experiment.build import expand_jobs
    from pipeline.experiment.spec import without_data_identity
    from pipeline.experiment.records import RecordsFile
    from pipeline.experiment.sweep import run_sweep
    copy = _copy(small_scene, tmp_path, "mine")
    run_sweep(_cfg(tmp_path, copy))
    (job,) = expand_jobs(_cfg(tmp_path, copy))
    records = RecordsFile(tmp_path / "out")  # as an older gopre wrote it: no fingerprint, the old hash
    records.frame = records.frame.drop(columns=["data_fingerprint"]).assign(config_hash=without_data_identity(job))
    records.write()
    plan = _plan(tmp_path, copy)
    assert "to run (data changed)" in plan and "not recorded (launched before data identity)" in plan
    capsys.readouterr()
    again = run_sweep(_cfg(tmp_path, copy))
    assert again.skipped == 0 and again.finished == 1
    assert "was not recorded (launched before data identity)" in capsys.readouterr().out


def _plan(tmp_path, scene) -> str:
    from pipeline.experiment.build import expand_jobs
    from pipeline.experiment.plan import plan_jobs, plan_text
    return plan_text("t", plan_jobs(expand_jobs(_cfg(tmp_path, scene)), tmp_path / "out"), 1)


def test_a_node_holding_another_copy_of_the_data_refuses_the_job(small_scene, tmp_path):
    from dataclasses import replace

    from pipeline.data.images import DataError
    from pipeline.experiment.build import expand_jobs
    from pipeline.experiment.job import check_data_identity
    copy = _copy(small_scene, tmp_path, "mine")
    (job,) = expand_jobs(_cfg(tmp_path, copy))
    check_data_identity(job)  # the same bytes: runs
    _touch_pixel(copy / "train" / "r_1.png")
    with pytest.raises(DataError, match=rf"{copy}: the scene's data on this node has fingerprint [0-9a-f]{{16}}, "
                                        rf"the driver's has {job.data_fingerprint}"):
        check_data_identity(job)
    check_data_identity(replace(job, data_fingerprint=""))  # a job made before data identity: nothing to check


def _generated_cfg(tmp_path):
    from pipeline.cli.run import CONF_DIR
    from tests.conftest import SMALL_GENERATED
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose("config", ["experiment=debug", "splat=tiny", *SMALL_GENERATED, "protocol.initial_views=2",
                                  "protocol.budget=3", "protocol.probes=2", "executor=local", "tracking=none",
                                  "method=[random]", "seeds=[0]", f"output_dir={tmp_path / 'out'}"])


def test_an_edited_generator_is_changed_data_for_the_generated_scene(tmp_path, monkeypatch, capsys):
    """The generated scene has no files to hash before it is cast: its identity is its options and its
    generator, so a relaunch after the generator changed re-runs its jobs and says so."""
    from pipeline.experiment.records import RecordsFile
    from pipeline.experiment.sweep import run_sweep
    first = run_sweep(_generated_cfg(tmp_path))
    assert first.finished == 1
    before = RecordsFile(tmp_path / "out").frame["data_fingerprint"].iloc[0]
    assert before == fp.generated_fingerprint(first_generate(tmp_path)) and before.startswith("generated-")
    assert run_sweep(_generated_cfg(tmp_path)).skipped == 1  # the same generator: finished
    capsys.readouterr()
    monkeypatch.setattr(fp, "generator_identity", lambda: "e" * 16)  # as an edit of synthetic.py would
    again = run_sweep(_generated_cfg(tmp_path))
    now = fp.generated_fingerprint(first_generate(tmp_path))
    assert again.skipped == 0 and again.finished == 1 and now != before
    assert f"data changed: dataset.generated scene 'generated' is now {now} (was {before})" in capsys.readouterr().out


def first_generate(tmp_path) -> dict:
    from pipeline.experiment.build import expand_jobs
    (job,) = expand_jobs(_generated_cfg(tmp_path))
    return job.generate
