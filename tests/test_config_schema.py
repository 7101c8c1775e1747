"""The config schema: every declared key's bad values (below, above, wrong type, null) are one
config error naming the key and the value, before any job is built; the declarations agree with
conf/, with their own defaults, and with the documentation generated from them."""

import copy
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pipeline.acquisition import REGISTRY
from pipeline.active.uncertainty import UncertaintyConfig
from pipeline.bounds import BOOL, FLOAT, INT, STR, Bound, bounded, declared, violations
from pipeline.cli.run import CONF_DIR
from pipeline.data.protocols import ProtocolConfig
from pipeline.data.synthetic import GeneratedScene, generate
from pipeline.experiment.episode_settings import ConfigError
from pipeline.experiment.build import expand_jobs
from pipeline.experiment.schema import (EXECUTORS, SPLAT_FIELDS, JobSection, Sweep, TrackingSection,
                                        field_bound, schema_markdown)
from pipeline.fit.config import FitConfig

ROOT = Path(__file__).resolve().parent.parent


def base_config(executor: str = "local"):
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose("config", ["experiment=debug", f"executor={executor}", "tracking=none",
                                  "output_dir=/tmp/gopre-schema-test"])


def cases():
    """(executor kind, dotted key, bad value) for every declared key of every section."""
    out = []
    sections = [("", Sweep), ("job.", JobSection), ("splat.fit.", FitConfig), ("protocol.", ProtocolConfig),
                ("uncertainty.", UncertaintyConfig), ("tracking.", TrackingSection),
                ("dataset.generated.generate.", GeneratedScene)]
    for prefix, cls in sections:
        out += [("local", prefix + key, bad) for key, bound, _ in declared(cls) for bad in bound.bad_values()]
    for kind, cls in EXECUTORS.items():
        out += [(kind, "executor." + key, bad) for key, bound, _ in declared(cls) for bad in bound.bad_values()]
    for name, cls in REGISTRY.items():
        out += [("local", f"method.{name}.options.{key}", bad)
                for key, bound, _ in declared(cls) for bad in bound.bad_values()]
    for key, (cls, field_name) in SPLAT_FIELDS.items():
        # null means "the preset's value" for every splat key
        out += [("local", f"splat.{key}", bad) for bad in field_bound(cls, field_name).bad_values() if bad is not None]
    return out


CASES = cases()
BASES = {}


def test_the_table_covers_every_section_and_every_way_to_be_wrong():
    keys = {key for _, key, _ in CASES}
    for expected in ("splat.fit.sh_degree", "splat.fit.lr.means_init", "splat.fit.densify.interval",
                     "splat.fit.init_points", "splat.fit.init_opacity", "splat.fit.ssim_weight",
                     "splat.curve_test_views", "splat.views_per_round", "method.gopre.options.lam",
                     "method.gopre.options.tau", "job.device", "job.retries", "uncertainty.train_views",
                     "uncertainty.iterations", "executor.gpus_per_job", "executor.num_cpus", "executor.max_retries",
                     "dataset.generated.generate.size", "tracking.uri", "name", "method.cover.options.bins"):
        assert expected in keys, expected
    assert len(CASES) > 250


@pytest.mark.parametrize("executor,key,bad", CASES, ids=[f"{k}={b!r}" for _, k, b in CASES])
def test_a_bad_declared_value_is_one_config_error_naming_key_and_value(executor, key, bad):
    if executor not in BASES:
        BASES[executor] = base_config(executor)
    cfg = copy.deepcopy(BASES[executor])
    if key.startswith("method."):
        name = key.split(".")[1]
        OmegaConf.update(cfg, f"method.{name}", {"strategy": name, "options": {}}, force_add=True)
    OmegaConf.update(cfg, key, bad, force_add=True)
    with pytest.raises(ConfigError) as err:
        expand_jobs(cfg)
    message = str(err.value)
    assert f"{key}: {bad!r} is not " in message, message


def test_a_config_with_many_bad_values_names_every_one():
    cfg = base_config()
    for key, value in (("splat.fit.sh_degree", 7), ("job.retries", 10**6), ("seeds", [0]),
                       ("method.gopre.options.tau", "abc")):
        OmegaConf.update(cfg, key, value, force_add=True)
    with pytest.raises(ConfigError, match="3 bad values, nothing was started") as err:
        expand_jobs(cfg)
    for line in ("splat.fit.sh_degree: 7 is not an integer in [0, 3]", "job.retries: 1000000 is not an integer in [0, 100]",
                 "method.gopre.options.tau: 'abc' is not a number >= 0"):
        assert line in str(err.value)


@pytest.mark.parametrize("override,match", [
    ("seeds=[0,0]", r"seeds: \[0, 0\] lists a seed twice"),
    ("splat.views_per_round=3", r"views_per_round: 3 is more than the picks the budget leaves"),
    ("protocol.initial_views=4", r"protocol.initial_views: 4 leaves no pick within budget=4"),
    ("protocol.probes=2.5", r"protocol.probes: 2.5 is not a count >= 1 or a fraction in \(0, 1\)"),
])
def test_relations_between_values_are_config_errors_too(override, match):
    cfg = base_config()
    key, value = override.split("=")
    OmegaConf.update(cfg, key, yaml.safe_load(value), force_add=True)
    with pytest.raises(ConfigError, match=match):
        expand_jobs(cfg)


def test_every_declared_default_is_allowed_and_every_bad_value_refused():
    classes = [Sweep, JobSection, FitConfig, ProtocolConfig, UncertaintyConfig, TrackingSection, GeneratedScene,
               *EXECUTORS.values(), *REGISTRY.values()]
    for cls in classes:
        for key, bound, default in declared(cls):
            assert bound.problem(default) is None, f"{cls.__name__}.{key}: default {default!r} breaks its own bound"
            for bad in bound.bad_values():
                assert bound.problem(bad) is not None, f"{cls.__name__}.{key}: {bad!r} passes"


def test_a_bound_says_what_it_allows_and_checks_it_by_hand():
    degree = Bound(INT, ge=0, le=3)
    assert degree.describe() == "an integer in [0, 3]"
    assert [degree.problem(v) for v in (0, 3, -1, 4, 2.0, True, "2", None)] == [
        None, None, "out of range", "out of range", "wrong type", "wrong type", "wrong type", "may not be null"]
    rate = Bound(FLOAT, gt=0, nullable=True)
    assert rate.describe() == "a number > 0, or null"
    assert [rate.problem(v) for v in (1e-9, 3, 0, None, math.inf, math.nan)] == [
        None, None, "out of range", None, "not finite", "not finite"]
    assert Bound(FLOAT, gt=0, lt=1).describe() == "a number in (0, 1)"
    assert Bound(STR, choices=("cpu", "cuda")).problem("tpu") == "not allowed"
    assert Bound(BOOL).problem(1) == "wrong type"
    assert Bound(STR, pattern=r"[a-z]+").problem("a/b") == "malformed"
    assert Bound(STR).problem("  ") == "empty"


def test_violations_walk_nested_groups_and_leave_unknown_keys_to_their_own_check():
    assert violations(FitConfig, {"lr": {"means_init": -1}, "densify": {"interval": 0}, "unknown": 3}, "splat.fit.") == [
        "splat.fit.lr.means_init: -1 is not a number > 0", "splat.fit.densify.interval: 0 is not an integer >= 1"]
    with pytest.raises(ValueError, match=r"^sh_degree: 7 is not an integer in \[0, 3\]$"):
        FitConfig(sh_degree=7)  # a typed config refuses it wherever it is built


def run_plan(tmp_path, *overrides):
    return subprocess.run([sys.executable, "-m", "pipeline.cli.run", "experiment=debug", "executor=local",
                           "tracking=none", f"output_dir={tmp_path / 'sweep'}", "plan=true", *overrides],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)


def test_plan_warns_about_values_far_above_anything_measured(tmp_path):
    proc = run_plan(tmp_path, "splat.iterations=1000000000", "splat.fit.init_points=20000000")
    assert proc.returncode == 0, proc.stderr
    assert "warning: splat.iterations=1000000000 is far above anything measured (usually <= 300000)" in proc.stdout
    assert "warning: splat.fit.init_points=20000000 is far above anything measured (usually <= 10000000)" in proc.stdout
    assert "warning" not in run_plan(tmp_path).stdout


def test_a_training_width_above_the_images_is_refused_before_reading_them(tmp_path):
    generate(tmp_path / "scenes" / "generated-32px-14-8-seed0" / "generated", seed=0, size=32, n_train=14, n_test=8)
    proc = run_plan(tmp_path, "splat.image_width=100000")  # used to be read, upsampled, and killed for memory
    assert proc.returncode == 2
    assert "training width 100000 px is wider than the images (32 px)" in proc.stderr


def section_defaults(cls) -> dict:
    return {key: default for key, _, default in declared(cls)}


def test_the_declared_defaults_are_the_ones_in_conf():
    config = yaml.safe_load((CONF_DIR / "config.yaml").read_text())
    assert {k: config["job"][k] for k in section_defaults(JobSection)} == section_defaults(JobSection)
    assert {k: config[k] for k in section_defaults(Sweep)} == section_defaults(Sweep)
    for kind, cls in EXECUTORS.items():
        conf = yaml.safe_load((CONF_DIR / "executor" / f"{kind}.yaml").read_text())
        assert {k: conf.get(k) for k in section_defaults(cls)} == section_defaults(cls), kind
    for kind in ("mlflow", "none"):
        conf = yaml.safe_load((CONF_DIR / "tracking" / f"{kind}.yaml").read_text())
        assert conf["uri"] is None and TrackingSection().uri is None
    unc = section_defaults(UncertaintyConfig)
    assert {k: config["uncertainty"][k] for k in config["uncertainty"] if k in unc} == \
        {k: unc[k] for k in config["uncertainty"] if k in unc}
    generate = yaml.safe_load((CONF_DIR / "dataset" / "generated.yaml").read_text())["generated"]["generate"]
    assert generate == section_defaults(GeneratedScene)


def test_the_committed_schema_document_is_the_declarations():
    """conf/SCHEMA.md is ``python -m pipeline.experiment.schema``'s output: regenerate it when a
    declaration changes."""
    assert (CONF_DIR / "SCHEMA.md").read_text() == schema_markdown()
    proc = subprocess.run([sys.executable, "-m", "pipeline.experiment.schema"], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)
    assert proc.returncode == 0 and proc.stdout == schema_markdown()


def test_bounded_gives_each_instance_its_own_mutable_default():
    from dataclasses import dataclass

    @dataclass
    class Holder:
        items: list = bounded([1], INT)
    a, b = Holder(), Holder()
    a.items.append(2)
    assert b.items == [1]


# the values a new user tried (issue 47), written out: each is one line naming key and value
TRIED = [
    ("local", "splat.fit.lr.means_init=-1", "splat.fit.lr.means_init: -1 is not a number > 0"),
    ("local", "splat.fit.sh_degree=7", "splat.fit.sh_degree: 7 is not an integer in [0, 3]"),
    ("local", "splat.fit.sh_degree=-1", "splat.fit.sh_degree: -1 is not an integer in [0, 3]"),
    ("local", "splat.fit.densify.interval=0", "splat.fit.densify.interval: 0 is not an integer >= 1"),
    ("local", "splat.fit.init_points=0", "splat.fit.init_points: 0 is not an integer >= 1"),
    ("local", "splat.fit.init_opacity=1.5", "splat.fit.init_opacity: 1.5 is not a number in (0, 1)"),
    ("local", "splat.curve_test_views=0", "splat.curve_test_views: 0 is not an integer >= 1"),
    ("local", "splat.curve_test_views=-3", "splat.curve_test_views: -3 is not an integer >= 1"),
    ("local", "method.gopre.options.lam=-1", "method.gopre.options.lam: -1 is not a number > 0"),
    ("local", "method.gopre.options.tau=abc", "method.gopre.options.tau: 'abc' is not a number >= 0"),
    ("local", "job.device=tpu", "job.device: 'tpu' is not one of cpu, cuda"),
    ("local", "uncertainty.train_views=0", "uncertainty.train_views: 0 is not an integer >= 1"),
    ("local", "uncertainty.iterations=-1", "uncertainty.iterations: -1 is not an integer >= 1"),
    ("ray", "executor.gpus_per_job=-1", "executor.gpus_per_job: -1 is not a number >= 0"),
    ("local", "dataset.generated.generate.size=0", "dataset.generated.generate.size: 0 is not an integer in [8, 4096]"),
    ("local", "dataset.generated.generate.size=-8", "dataset.generated.generate.size: -8 is not an integer in [8, 4096]"),
    ("local", "tracking.uri=bogus://x", "tracking.uri: 'bogus://x' is not a non-empty string"),
    ("local", "splat.fit.ssim_weight=2", "splat.fit.ssim_weight: 2 is not a number in [0, 1]"),
    ("local", "splat.fit.ssim_weight=-1", "splat.fit.ssim_weight: -1 is not a number in [0, 1]"),
    ("local", "seeds=[0,0]", "seeds: [0, 0] lists a seed twice"),
    ("local", "name=", "name: '' is not a non-empty string"),
    ("local", "splat.views_per_round=100", "splat.views_per_round: 100 is more than the picks the budget leaves"),
    ("local", "job.retries=1000000", "job.retries: 1000000 is not an integer in [0, 100]"),
    ("ray", "executor.num_cpus=0", "executor.num_cpus: 0 is not an integer >= 1, or null"),
    ("ray", "executor.max_retries=-1", "executor.max_retries: -1 is not an integer in [0, 100]"),
]


@pytest.mark.parametrize("executor,override,line", TRIED, ids=[o for _, o, _ in TRIED])
def test_the_values_a_new_user_tried_are_one_line_each(executor, override, line):
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", ["experiment=debug", f"executor={executor}", "tracking=none", override])
    with pytest.raises(ConfigError) as err:
        expand_jobs(cfg)
    assert line in str(err.value) and "\n" not in str(err.value), str(err.value)


def test_gopre_run_says_a_bad_value_in_one_line_and_exits_2(tmp_path):
    proc = run_plan(tmp_path, "splat.fit.sh_degree=7")
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.splitlines() == ["gopre-run: config error: splat.fit.sh_degree: 7 is not an integer in [0, 3]"]


def test_cuda_jobs_on_a_machine_without_cuda_are_refused_before_any_job():
    import torch

    from pipeline.experiment.sweep import no_device_here
    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    here = type("Here", (), {"runs_here": True})()
    elsewhere = type("Elsewhere", (), {"runs_here": False})()
    job = type("J", (), {"execution": type("E", (), {"device": "cuda"})()})()
    with pytest.raises(ConfigError, match="job.device: 'cuda', but the jobs run on this machine and it has no CUDA"):
        no_device_here(here, [job])
    no_device_here(elsewhere, [job])  # a cluster's nodes may have GPUs: their workers say so


@pytest.mark.parametrize("axis,line", [
    ("+sweep.splat.iterations=[0,100]", "splat.iterations: 0 is not an integer >= 1"),
    ("+sweep.splat.max_gaussians=[0]", "splat.max_gaussians: 0 is not an integer >= 1"),
    ("+sweep.splat.curve_test_views=[0]", "splat.curve_test_views: 0 is not an integer >= 1"),
])
def test_a_sweep_axis_value_meets_the_same_declared_bounds(axis, line):
    """An axis's values reach each job's splat section after the composed config is checked: 0
    iterations used to mean "the preset's" silently."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", ["experiment=debug", "executor=local", "tracking=none", axis])
    with pytest.raises(ConfigError, match=re.escape(line)):
        expand_jobs(cfg)


def test_more_picks_per_round_than_a_resolved_budget_leaves_is_refused_before_any_job(tmp_path):
    """Without an explicit budget the picks are known once the scene's protocol is built."""
    generate(tmp_path / "scenes" / "generated-32px-14-8-seed0" / "generated", seed=0, size=32, n_train=14, n_test=8)
    proc = run_plan(tmp_path, "protocol.budget=null", "splat.views_per_round=50")
    assert proc.returncode == 2
    assert ("splat.views_per_round: 50 is more than the 8 picks the protocol leaves on dataset.generated scene "
            "'generated' (budget 10, 2 initial views)") in proc.stderr
