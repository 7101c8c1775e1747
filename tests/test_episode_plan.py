"""The episode plan (``pipeline.active.plan``): made once per job and shared by the episode, its
``result.json`` and the round messages; the pre-flight check makes each distinct plan once; the
outline known before the scene is read is the read scene's; the viewer's plan is the job's."""

import json

import pytest
from hydra import compose, initialize_config_dir

from pipeline.active import plan as plan_module
from pipeline.active.config import cpu_episode, tiny_episode
from pipeline.active.plan import EpisodeOutline, EpisodePlan, uniform_subset
from pipeline.cli.run import CONF_DIR
from pipeline.data.load import load_scene
from pipeline.data.protocols import ProtocolConfig, build_protocol
from pipeline.data.readers import traits_of
from pipeline.experiment.sweep import run_sweep

TINY = ["experiment=debug", "splat=tiny", "splat.iterations=40", "dataset.generated.generate.size=32",
        "dataset.generated.generate.n_train=16", "dataset.generated.generate.n_test=8",
        "protocol.initial_views=2", "protocol.budget=4", "protocol.probes=2", "executor=local", "tracking=none"]


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    from pipeline.data.synthetic import generate
    return generate(tmp_path_factory.mktemp("gen") / "scene", seed=0, size=32, n_train=14, n_test=8)


def counted_protocols(monkeypatch) -> list[str]:
    """Every protocol built through the plan, by scene (build_protocol still does the work)."""
    calls: list[str] = []

    def counting(scene, cfg):
        calls.append(str(scene.root))
        return build_protocol(scene, cfg)
    monkeypatch.setattr(plan_module, "build_protocol", counting)
    return calls


def test_a_sweep_builds_each_jobs_views_once_and_the_pre_flight_each_distinct_plan_once(tmp_path, monkeypatch):
    calls = counted_protocols(monkeypatch)
    out = tmp_path / "sweep"
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", [*TINY, "method=[random,coverage]", "seeds=[0,1]", f"output_dir={out}"])
    assert run_sweep(cfg).finished == 4
    # one plan for the pre-flight (the four jobs share it: only strategy and seed differ), one per job
    assert len(calls) == 1 + 4, calls
    for path in out.glob("jobs/*/artifacts/benchmark/result.json"):
        doc = json.loads(path.read_text())
        assert len(doc["rounds"]) == 2 + 1  # 2 -> 3 -> 4 views, then the final evaluation


def test_the_pre_flight_makes_a_plan_per_distinct_episode_setting(tmp_path, monkeypatch):
    from pipeline.experiment.build import expand_jobs
    from pipeline.experiment.preflight import prepare_scenes, protocol_errors
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", [*TINY, "method=[random,coverage]", "seeds=[0,1]",
                                 "+sweep.splat.curve_test_views=[2,4]", f"output_dir={tmp_path / 'p'}"])
    jobs = expand_jobs(cfg)
    assert len(jobs) == 8 and {j.episode.curve_test_views for j in jobs} == {2, 4}
    scenes, errors = prepare_scenes(jobs)
    assert errors == []
    calls = counted_protocols(monkeypatch)
    assert protocol_errors(jobs, scenes, decode=False) == []
    assert len(calls) == 2  # two curves, two plans; methods and seeds share them


def test_the_outline_before_reading_is_the_read_scenes_for_every_protocol(scene_dir):
    scene = load_scene(scene_dir, width=32)
    for protocol in (ProtocolConfig(), ProtocolConfig(kind="sparse"), ProtocolConfig(initial_views=3, budget=7)):
        for policy in ("reset_opacity", "reload"):
            cfg = cpu_episode(protocol=protocol, post_selection=policy)
            plan, before = EpisodePlan.of(scene, cfg), EpisodeOutline.before_reading(traits_of(scene.format), cfg)
            assert (before.schedule, before.fit) == (plan.schedule, plan.fit)
            assert plan.evaluations == len(plan.schedule.round_views) + 1
            assert plan.schedule.round_views[0] == len(plan.views.initial_ids)


def test_the_plans_curve_views_picks_and_probes_follow_their_rules(scene_dir):
    scene = load_scene(scene_dir, width=32)
    cfg = tiny_episode(protocol=ProtocolConfig(initial_views=2, budget=7, probes=3), views_per_round=2,
                       curve_test_views=3)
    plan = EpisodePlan.of(scene, cfg)
    test = plan.views.test_ids
    assert len(test) > 3 and len(set(plan.curve_ids)) == 3 and set(plan.curve_ids) <= set(test)
    assert plan.curve_ids[0] == test[0] and plan.curve_ids[-1] == test[-1]
    # 2 -> 4 -> 6 -> 7: the last round asks for the one view the budget leaves
    assert plan.schedule.round_views == (2, 4, 6)
    assert [plan.picks(k, cfg.views_per_round) for k in range(3)] == [2, 2, 1]
    assert plan.probes(0, 1) == plan.probes(0, 1) != plan.probes(1, 1)
    assert set(plan.probes(0, 0)) <= set(plan.views.probe_ids) and len(plan.probes(0, 0)) == 3
    with pytest.raises(AttributeError):
        plan.extent = 1.0  # frozen: the one plan cannot drift between its users


def test_uniform_subset_spreads_evenly_and_keeps_the_ends():
    assert uniform_subset(list(range(10)), 3) == [0, 4, 9]  # 4.5 rounds to even
    assert uniform_subset([5, 7, 9], None) == [5, 7, 9] == uniform_subset([5, 7, 9], 8)
    picked = uniform_subset(list(range(100)), 10)
    assert picked[0] == 0 and picked[-1] == 99 and len(set(picked)) == 10
