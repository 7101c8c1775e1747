"""What a strategy returns is checked where the pick is made: exactly the count asked for, no taken
view, no duplicate, only candidates, no NaN score. The rules by hand on small asks, then through
real plugins (dotted paths) in a real sweep: each misbehaving job fails with one line naming the
strategy, the round and the ids, on its first attempt, and no such row enters a table."""

import json
import math
import textwrap

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from pipeline.acquisition.validation import RoundAsk, SelectionError, check_selection, selection_problem
from tests.conftest import SMALL_GENERATED

ASK = RoundAsk("mine", 2, 2, candidate_ids=(3, 5, 8, 13), taken_ids=(0, 1))
SCORES = {3: 0.1, 5: 0.2, 8: math.inf, 13: -1.0}  # an infinite score is a rank (COVER's +inf), not a fault


def test_a_selection_that_follows_every_rule_is_taken():
    assert selection_problem(ASK, [8, 3], SCORES) is None
    assert selection_problem(ASK, [np.int64(8), 3], {**SCORES, 3: np.float32(0.5)}) is None  # numpy numbers are numbers
    check_selection(ASK, [5, 13], {})  # a strategy need not score every candidate


@pytest.mark.parametrize("chosen, scores, message", [
    ([3, 5, 8], SCORES, r"returned 3 pick\(s\) \[3, 5, 8\], asked for 2"),
    ([3], SCORES, r"returned 1 pick\(s\) \[3\], asked for 2"),
    ([1, 3], SCORES, r"picked view\(s\) \[1\] already taken"),
    ([5, 5], SCORES, r"picked view\(s\) \[5\] more than once in \[5, 5\]"),
    ([3, 99], SCORES, r"picked view\(s\) \[99\] outside this round's 4 candidates"),
    ([3, 5], {**SCORES, 8: float("nan")}, r"scored view\(s\) \[8\] NaN"),
    ([3, 5], {**SCORES, 99: 1.0}, r"scored view\(s\) \[99\] that are not candidates"),
    ([3, None], SCORES, r"picked \[None\], which are not view ids"),
    ([3.0, 5], SCORES, r"picked \[3.0\], which are not view ids"),
])
def test_each_broken_rule_is_one_line_naming_strategy_round_and_ids(chosen, scores, message):
    with pytest.raises(SelectionError, match=r"^strategy 'mine', round 2 \(2 views taken\): " + message) as err:
        check_selection(ASK, chosen, scores)
    assert "\n" not in str(err.value)


def test_the_count_rule_holds_when_the_pool_runs_out():
    """The round asks for fewer when fewer remain: exactly that many, no more."""
    short = RoundAsk("mine", 5, 1, candidate_ids=(7,), taken_ids=(0, 1, 2))
    assert selection_problem(short, [7], {7: 0.0}) is None
    assert "asked for 1" in selection_problem(short, [], {})


BAD_STRATEGIES = """
    import math
    from pipeline.api import Selection

    class _Bad:
        def select(self, ctx, count=1):
            ids, taken = list(ctx.candidate_ids), list(ctx.taken_ids or [])
            chosen, scores = self.pick(ids, taken, count)
            return Selection(chosen, scores, 0.0, 0.0, 0.0)

    class TooMany(_Bad):
        name = "too_many"
        def pick(self, ids, taken, count):
            return ids[:count + 2], {i: 0.0 for i in ids}

    class Retaken(_Bad):
        name = "retaken"
        def pick(self, ids, taken, count):
            return [taken[0]], {i: 0.0 for i in ids}

    class Twice(_Bad):
        name = "twice"
        def pick(self, ids, taken, count):
            return [ids[0], ids[0]], {i: 0.0 for i in ids}

    class Outside(_Bad):
        name = "outside"
        def pick(self, ids, taken, count):
            return [10000], {i: 0.0 for i in ids}

    class NaNScores(_Bad):
        name = "nan_scores"
        def pick(self, ids, taken, count):
            return ids[:count], {i: math.nan for i in ids}
"""
CASES = {"too_many": ("TooMany", r"returned 3 pick\(s\) \[\d+, \d+, \d+\], asked for 1"),
         "retaken": ("Retaken", r"picked view\(s\) \[\d+\] already taken"),
         "twice": ("Twice", r"picked view\(s\) \[\d+\] more than once"),
         "outside": ("Outside", r"picked view\(s\) \[10000\] outside this round's \d+ candidates"),
         "nan_scores": ("NaNScores", r"scored view\(s\) \[\d+, \d+, .*\] NaN")}


@pytest.fixture(scope="module")
def misbehaving_sweep(tmp_path_factory):
    """One tiny sweep of five plugin methods that each break one rule (and random, which follows them)."""
    import sys

    from pipeline.cli.run import CONF_DIR
    from pipeline.experiment.records import RecordsFile
    from pipeline.experiment.sweep import run_sweep
    root = tmp_path_factory.mktemp("bad")
    (root / "bad_select.py").write_text(textwrap.dedent(BAD_STRATEGIES))
    (root / "conf" / "method").mkdir(parents=True)
    for key, (cls, _) in CASES.items():
        (root / "conf" / "method" / f"{key}.yaml").write_text(f"{key}:\n  strategy: bad_select:{cls}\n")
    sys.path.insert(0, str(root))
    try:
        with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
            cfg = compose("config", ["splat=tiny", "dataset=[generated]", *SMALL_GENERATED, "protocol.initial_views=2",
                                     "protocol.budget=4", "protocol.probes=3", "executor=local", "tracking=none",
                                     "job.retries=2", f"output_dir={root / 'out'}", f"hydra.searchpath=[file://{root}/conf]",
                                     f"method=[random,{','.join(CASES)}]"])
        summary = run_sweep(cfg)
    finally:
        sys.path.remove(str(root))
    return summary, RecordsFile(root / "out").frame


@pytest.mark.slow
def test_every_misbehaving_plugin_fails_its_job_once_naming_strategy_round_and_ids(misbehaving_sweep):
    summary, frame = misbehaving_sweep
    finals = frame[frame["kind"] == "final"].set_index("method")
    assert summary.failed == len(CASES) and summary.finished == 1
    assert finals.loc["random", "status"] == "FINISHED"
    for key, (cls, message) in CASES.items():
        row = finals.loc[key]
        assert row["status"] == "FAILED", key
        assert int(row["attempts"]) == 1, f"{key}: a strategy's fault is deterministic, never retried"
        last = row["error"].strip().splitlines()[-1]
        assert last.startswith(f"pipeline.acquisition.validation.SelectionError: strategy 'bad_select:{cls}', round 0 ")
        assert __import__("re").search(message, last), last


@pytest.mark.slow
def test_no_misbehaving_row_enters_a_table(misbehaving_sweep):
    from pipeline.report.rows import finished
    _, frame = misbehaving_sweep
    assert set(finished(frame, "final")["method"]) == {"random"}
    assert json.loads(frame[(frame["method"] == "random") & (frame["kind"] == "final")]["selected"].iloc[0])
