"""Each job is resolved once: ``Job.episode`` is built when the sweep expands (a bad value fails
there) and every later reader shares that one EpisodeConfig."""

from hydra import compose, initialize_config_dir

import pipeline.experiment.build as build
import pipeline.experiment.episode_settings as episode_settings
from pipeline.cli.run import CONF_DIR
from pipeline.experiment.spec import Job

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
    assert "_episode" not in plain and build.config_hash(plain) == job.config_hash
    again = Job.from_dict(plain)  # a job that travelled (Ray) resolves again, to an equal config
    assert again.episode == job.episode and again.episode is not job.episode
