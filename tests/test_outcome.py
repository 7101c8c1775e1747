"""The typed run spine: the job outcome (one FAILED constructor, plain data across Ray and back
unchanged), the round message, and the episode's records with their metrics versions."""

import json
import pickle
from dataclasses import replace

import pytest

from pipeline.interchange.results import EpisodeResult, FinalMetrics, RoundRecord
from pipeline.experiment.outcome import FAILED, FINISHED, TRACEBACK_ARTIFACT, JobOutcome


def a_round(index=0, **changes) -> RoundRecord:
    rec = RoundRecord(round=index, num_views=4 + index, iteration=100 * (index + 1), test_psnr=18.5,
                      test_ssim=0.61, num_gaussians=500, train_seconds=1.5, selected=[7 + index],
                      probes=[1, 2], scores={7 + index: -3.0, 9: -2.0}, candidates=2,
                      test_ssim_skimage=0.58)
    return replace(rec, **changes)


def an_episode() -> EpisodeResult:
    final = FinalMetrics(21.5, 0.71, 0.69, None, "LPIPS disabled in the config", 2, [21.0, 22.0],
                         [0.70, 0.72], [0.68, 0.70], 600, iterations=900, curve_psnr_drop=0.1)
    return EpisodeResult("scenes/x", "gopre", 0, "global", [0, 1, 2, 3], [7, 8], [[1, 2], [1, 2]],
                         "train", "test", [0, 1], [0], [a_round(0), a_round(1), a_round(2, selected=[])],
                         final, 12.0)


def test_an_outcome_survives_plain_data_and_pickling_unchanged():
    outcome = JobOutcome(FINISHED, 2, ["Traceback: first attempt"], an_episode().to_dict(),
                         {"model.ply": b"ply\n"}, 12.5)
    data = outcome.to_dict()
    assert all(type(v) in (str, int, float, list, dict) for v in data.values())
    again = JobOutcome.from_dict(pickle.loads(pickle.dumps(data)))
    assert again == outcome and again.finished and again.final == an_episode().final
    assert again.episode == an_episode()
    assert again.traceback == "Traceback: first attempt"


def test_an_episode_result_survives_json_unchanged():
    """result.json: JSON turns the scores' int keys into strings; from_dict turns them back."""
    episode = an_episode()
    again = EpisodeResult.from_dict(json.loads(json.dumps(episode.to_dict())))
    assert again == episode and again.rounds[0].scores == {7: -3.0, 9: -2.0}


def test_a_version_1_record_never_reads_scikit_images_ssim_as_3dgss():
    """Before metrics version 2 ``ssim`` was scikit-image's: it moves to ``ssim_skimage``."""
    data = an_episode().to_dict()
    old_final = {k: v for k, v in data["final"].items()
                 if k not in ("ssim_skimage", "per_view_ssim_skimage", "metrics_version", "ssim_source")}
    old_round = {k: v for k, v in data["rounds"][0].items() if k != "test_ssim_skimage"}
    final = FinalMetrics.from_dict(old_final)
    assert final.metrics_version == 1 and final.ssim is None and final.per_view_ssim is None
    assert final.ssim_skimage == 0.71 and final.per_view_ssim_skimage == [0.70, 0.72]
    rec = RoundRecord.from_dict(old_round)
    assert rec.test_ssim is None and rec.test_ssim_skimage == 0.61
    current = FinalMetrics.from_dict(data["final"])
    assert current.ssim == 0.71 and current.ssim_skimage == 0.69 and current.metrics_version == 2


def test_records_with_unknown_keys_are_refused():
    data = an_episode().to_dict()
    with pytest.raises(ValueError, match="FinalMetrics.*unknown keys.*'sim'"):
        FinalMetrics.from_dict({**data["final"], "sim": 1})
    with pytest.raises(ValueError, match="RoundRecord.*unknown keys"):
        RoundRecord.from_dict({**data["rounds"][0], "psnr": 1})


def test_failed_keeps_every_traceback_and_the_last_as_an_artifact():
    outcome = JobOutcome.failed(3, ["one", "two", "three"])
    assert outcome.status == FAILED and not outcome.finished and outcome.attempts == 3
    assert outcome.errors == ["one", "two", "three"] and outcome.traceback == "three"
    assert outcome.artifacts == {TRACEBACK_ARTIFACT: b"three"}
    assert outcome.result is None and outcome.final is None and outcome.episode is None
    assert outcome.seconds is None


@pytest.mark.parametrize("make,match", [
    (lambda: JobOutcome("DONE", 1, [], {}), "FINISHED or FAILED"),
    (lambda: JobOutcome(FINISHED, 1, [], None), "needs its result"),
    (lambda: JobOutcome.failed(1, []), "at least one"),
    (lambda: JobOutcome.from_dict({"status": FAILED, "traceback": "x"}), "unknown keys"),
])
def test_malformed_outcomes_are_refused(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_a_round_message_is_light_plain_data_and_comes_back_the_same():
    from pipeline.experiment.outcome import RoundMessage
    rec = RoundRecord(round=2, num_views=6, iteration=900, test_psnr=18.5, test_ssim=0.6,
                      num_gaussians=5000, train_seconds=10.0, selected=[41], probes=[1, 2, 3],
                      scores={41: -3.0, 42: -2.5}, candidates=2, selection_seconds=2.345)
    message = RoundMessage.of(rec, rounds=17)
    assert message.record.scores == {} and message.record.probes == [] and rec.scores  # copy
    assert not message.final and message.seconds == 12.35
    assert RoundMessage.of(replace(rec, round=16), 17).final
    message.images = {"picked": b"png"}
    again = RoundMessage.from_dict(pickle.loads(pickle.dumps(message.to_dict())))
    assert again == message


def test_a_job_is_the_plain_form_the_hash_and_jobs_json_were_made_of():
    """Job.to_dict() is key for key the dict every finished sweep's jobs.json holds (and whose
    hash the config hash is): across Ray and back through JSON it comes back equal."""
    from hydra import compose, initialize_config_dir

    from pipeline.cli.run import CONF_DIR
    from pipeline.experiment.spec import config_hash
    from pipeline.experiment.build import expand_jobs
    from pipeline.experiment.spec import Execution, Job
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        job = expand_jobs(compose("config", ["experiment=debug", "method=[gopre]"]))[0]
    plain = job.to_dict()
    assert list(plain)[:3] == ["sweep", "results_revision", "kind"] and isinstance(plain["execution"], dict)
    assert config_hash(plain) == config_hash(job) == job.config_hash
    again = Job.from_dict(json.loads(json.dumps(plain)))
    assert again == job and isinstance(again.execution, Execution)
    assert job.label == f"gopre on {job.scene} (seed 0)"
    with pytest.raises(ValueError, match="unknown keys.*'threads'"):
        Job.from_dict({**plain, "threads": 2})
    with pytest.raises(ValueError, match="missing keys.*'splat'"):
        Job.from_dict({k: v for k, v in plain.items() if k != "splat"})


def test_the_rounds_a_preempted_task_never_said_are_said_from_its_result():
    """A SLURM task preempted between a round's checkpoint and its progress line resumes past that
    round: the driver says the round from the finished job's result, once, in order."""
    from pipeline.experiment.executors.slurm import unheard_rounds
    outcome = JobOutcome(FINISHED, 1, [], an_episode().to_dict())
    missing = unheard_rounds(outcome, heard={0, 2})
    assert [m.record.round for m in missing] == [1]
    assert missing[0].rounds == 3 and missing[0].record.test_psnr == 18.5 and missing[0].record.scores == {}
    assert unheard_rounds(outcome, heard={0, 1, 2}) == []
    assert unheard_rounds(JobOutcome.failed(1, ["Traceback"]), heard=set()) == []
