"""The typed job outcome: one FAILED constructor, plain data across Ray and back unchanged."""

import pickle
from dataclasses import replace

import pytest

from pipeline.experiment.outcome import FAILED, FINISHED, TRACEBACK_ARTIFACT, JobOutcome


def test_an_outcome_survives_plain_data_and_pickling_unchanged():
    outcome = JobOutcome(FINISHED, 2, ["Traceback: first attempt"], {"final": {"psnr": 21.5}},
                         {"model.ply": b"ply\n"}, 12.5)
    data = outcome.to_dict()
    assert all(type(v) in (str, int, float, list, dict) for v in data.values())
    again = JobOutcome.from_dict(pickle.loads(pickle.dumps(data)))
    assert again == outcome and again.finished and again.final == {"psnr": 21.5}
    assert again.traceback == "Traceback: first attempt"


def test_failed_keeps_every_traceback_and_the_last_as_an_artifact():
    outcome = JobOutcome.failed(3, ["one", "two", "three"])
    assert outcome.status == FAILED and not outcome.finished and outcome.attempts == 3
    assert outcome.errors == ["one", "two", "three"] and outcome.traceback == "three"
    assert outcome.artifacts == {TRACEBACK_ARTIFACT: b"three"}
    assert outcome.result is None and outcome.final == {} and outcome.seconds is None


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
    from pipeline.active.episode import RoundRecord
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
