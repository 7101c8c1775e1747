"""The typed job outcome: one FAILED constructor, plain data across Ray and back unchanged."""

import pickle

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
