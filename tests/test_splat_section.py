"""conf/splat/*.yaml shows every hyperparameter of its preset, and jobs keep their hashes.

The presets are defined once (pipeline/active/config.py); the YAML lists them value for value and
is what a run applies, so the two must agree. A job carries only what differs from its preset
(experiment/splat_section.job_form): the form every finished sweep was hashed in."""

from dataclasses import asdict

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pipeline.active.config import episode_preset
from pipeline.cli.run import CONF_DIR
from pipeline.experiment.episode_settings import ConfigError, episode_config
from pipeline.experiment.build import expand_jobs
from pipeline.experiment.splat_section import FROM_PRESET, job_form

SPLAT_DIR = CONF_DIR / "splat"


def composed(overrides):
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides)


def splat_of(name: str) -> dict:
    return OmegaConf.to_container(composed([f"splat={name}"]).splat, resolve=True)


def _leaves(tree: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in tree.items():
        out.update(_leaves(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
    return out


@pytest.mark.parametrize("name", ["cpu", "paper", "tiny"])
def test_a_preset_yaml_lists_every_value_of_its_preset(name):
    """Each fit hyperparameter (but the four set elsewhere) and each top-level value, equal to the
    preset's: editing one side without the other fails here, naming the key."""
    section, preset = splat_of(name), episode_preset(name)
    shown = _leaves(section["fit"])
    expected = {k: v for k, v in _leaves(asdict(preset.fit)).items()
                if k not in ("iterations", "image_width", "seed", "densify.max_gaussians")}
    assert set(shown) == set(expected), set(shown) ^ set(expected)
    for key, value in expected.items():
        assert shown[key] == value and type(shown[key]) is type(value), key
    assert (section["iterations"], section["image_width"], section["max_gaussians"]) == (
        preset.fit.iterations, preset.fit.image_width, preset.fit.densify.max_gaussians)
    assert (section["epochs_per_view"], section["curve_test_views"], section["lpips"]) == (
        preset.epochs_per_view, preset.curve_test_views, preset.lpips)
    assert section["post_selection"] == preset.post_selection
    assert section["views_per_round"] == preset.views_per_round
    assert section["pool_keep_fraction"] == preset.pool_keep_fraction


@pytest.mark.parametrize("name", ["cpu", "paper", "tiny", "demo"])
def test_a_job_carries_what_differs_from_the_preset_in_the_form_it_always_had(name):
    form = job_form(splat_of(name))
    assert "fit" not in form  # the listed recipe is the preset's: nothing differs
    if name != "demo":
        assert all(form[key] is None for key in FROM_PRESET)
    else:  # the demo scale: the cpu preset with five values changed, written as they always were
        assert {k: form[k] for k in FROM_PRESET} == {"iterations": 800, "image_width": 48, "max_gaussians": 4000,
                                                      "epochs_per_view": 15, "curve_test_views": 20}


def test_a_changed_fit_value_is_kept_as_written_an_unknown_one_is_named():
    section = splat_of("cpu")
    section["fit"]["densify"]["grad_threshold"] = 3e-4
    section["fit"]["lr"]["sh0"] = episode_preset("cpu").fit.lr.sh0  # unchanged: dropped
    section["image_width"] = 100
    form = job_form(section)
    assert form["fit"] == {"densify": {"grad_threshold": 3e-4}} and form["image_width"] == 100
    section["fit"]["lr"]["mean_init"] = 1.0
    with pytest.raises(ValueError, match=r"fit\.lr\.mean_init: unknown"):
        job_form(section)
    with pytest.raises(ConfigError, match=r"splat\.fit\.densify\.gradthreshold: unknown"):
        expand_jobs(composed(["experiment=debug", "+splat.fit.densify.gradthreshold=1"]))


def test_the_presets_jobs_keep_the_hashes_their_finished_sweeps_were_written_under():
    """Pinned before conf/splat/ listed the real values (when the presets held nulls): the demo's
    four jobs and the epochs ablation, whose axis value 25 equals the cpu preset's (an axis is
    applied as written, after the section is reduced). Their data identity (the generated scene's
    options and generator, in the hash since 2026-12-07) is left out: what is pinned is the section."""
    from pipeline.experiment.spec import without_data_identity
    demo = [without_data_identity(j) for j in expand_jobs(composed(["experiment=demo"]))]
    assert demo == ["cfe8eca91141b222", "1662c459c535d4ce", "6aa9ef01d12a778f", "be3815958f649f8f"]
    ablation = expand_jobs(composed(["experiment=science_ablation", "ablation=epochs", "dataset=[generated]"]))
    assert [(j.setting, without_data_identity(j)) for j in ablation[:2]] == [
        ("splat.epochs_per_view=25", "47e82f26e83b882d"), ("splat.epochs_per_view=100", "d407611cf95319a7")]


def test_a_fit_value_is_a_sweep_axis():
    jobs = expand_jobs(composed(["experiment=debug", "method=[gopre]", "+sweep.splat.fit.ssim_weight=[0.1,0.3]",
                                 "+sweep.splat.fit.densify.grad_threshold=[2e-4]"]))
    assert [episode_config(j).fit.ssim_weight for j in jobs] == [0.1, 0.3]
    assert all(episode_config(j).fit.densify.grad_threshold == 2e-4 for j in jobs)
    assert len({j.config_hash for j in jobs}) == 2
    assert jobs[0].setting == "splat.fit.densify.grad_threshold=0.0002, splat.fit.ssim_weight=0.1"


def test_every_splat_yaml_composes_to_a_known_preset():
    for path in sorted(SPLAT_DIR.glob("*.yaml")):
        section = splat_of(path.stem)
        episode_preset(section["preset"])  # raises on an unknown preset
        job_form(section)


def test_the_published_study_keeps_every_hash_it_was_run_under():
    """reports/science/{generated,lego,bonsai}/runs.csv are the study as it ran (108 episodes, each
    scene from one code version, with its data identity): each of its jobs, expanded by today's code,
    has the hash it finished under, so a relaunch into the same folders knows them as the same jobs."""
    import csv

    from pipeline.cli.run import CONF_DIR as conf
    published = {}
    for scene in ("generated", "lego", "bonsai"):
        for r in csv.DictReader(open(conf.parent / "reports" / "science" / scene / "runs.csv")):
            published[(r["method"], r["scene"], int(r["seed"]), r["setting"])] = r["config_hash"]
    expanded = expand_jobs(composed(["experiment=science"]))
    jobs = {(j.method, j.scene, j.seed, j.setting): j.config_hash for j in expanded}
    assert len(published) == 108 and set(published) <= set(jobs)
    assert {key: jobs[key] for key in published} == published
