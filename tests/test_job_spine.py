"""Each job is resolved once: ``Job.episode`` is built when the sweep expands (a bad value fails
there) and every later reader shares that one EpisodeConfig."""

from hydra import compose, initialize_config_dir

import pipeline.experiment.build as build
import pipeline.experiment.episode_settings as episode_settings
from pipeline.cli.run import CONF_DIR
from pipeline.experiment.spec import Job, config_hash

TINY = ["experiment=debug", "splat.iterations=50"]


def test_a_job_is_resolved_once_and_its_config_shared(monkeypatch, tmp_path):
    calls = []
    original = episode_settings.episode_config
    monkeypatch.setattr(episode_settings, "episode_config", lambda job: calls.append(job.method) or original(job))
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", [*TINY, f"output_dir={tmp_path}"])
    jobs = build.expand_jobs(cfg)
    assert sorted(calls) == sorted(j.method for j in jobs)  # once each, at expansion
    first = [j.episode for j in jobs]
    assert all(j.episode is e for j, e in zip(jobs, first)) and len(calls) == len(jobs)
    assert first[0].fit.iterations == 50 and first[0].strategy == jobs[0].strategy


def test_the_resolved_config_stays_out_of_the_plain_form(tmp_path):
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", [*TINY, f"output_dir={tmp_path}"])
    job = build.expand_jobs(cfg)[0]
    plain = job.to_dict()
    assert "_episode" not in plain and config_hash(plain) == job.config_hash
    again = Job.from_dict(plain)  # a job that travelled (Ray) resolves again, to an equal config
    assert again.episode == job.episode and again.episode is not job.episode


def test_a_fit_axis_reaches_each_job_and_only_that_job(tmp_path):
    """A sweep axis over splat.fit.* on top of a fit value already changed: each job keeps its own
    value in its plain form (what travels to a worker), not the last job's."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", [*TINY, f"output_dir={tmp_path}", "method=[random]", "splat.fit.lr.sh0=0.003",
                                 "+sweep.splat.fit.lr.quats=[0.002,0.004]"])
    jobs = build.expand_jobs(cfg)
    travelled = [Job.from_dict(j.to_dict()) for j in jobs]
    assert [j.splat["fit"]["lr"]["quats"] for j in travelled] == [0.002, 0.004]
    assert [j.episode.fit.lr.quats for j in travelled] == [0.002, 0.004]
    assert all(j.episode.fit.lr.sh0 == 0.003 for j in travelled)
    assert len({j.config_hash for j in jobs}) == 2


def test_a_strategy_is_built_once_per_distinct_options(monkeypatch, tmp_path):
    import pipeline.experiment.resolution as resolution
    built = []
    original = resolution.make_strategy
    monkeypatch.setattr(resolution, "make_strategy", lambda name, **o: built.append((name, o)) or original(name, **o))
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", [*TINY, f"output_dir={tmp_path}", "seeds=[0,1,2]", "+sweep.options.tau=[0.5,1.0]",
                                 "method=[gopre]"])
    jobs = build.expand_jobs(cfg)
    assert len(jobs) == 6 and sorted(o["tau"] for _, o in built) == [0.5, 1.0]
