"""The records' columns come from the typed records' fields (``record_columns``): the records file,
what MLflow is sent and what the read-back rebuilds agree column for column. The MLflow side here is
what the tracker logs, served back by a stand-in client (the real server round trip is in
test_experiment.py)."""

import math
from dataclasses import dataclass, field
from types import SimpleNamespace

import pytest

from pipeline.interchange.results import EpisodeResult, FinalMetrics, RoundRecord, recorded
from pipeline.experiment.record_columns import (FINAL_COLUMNS, ROUND_COLUMNS, ROUND_METRICS, columns_of,
                                                final_tags)
from pipeline.experiment.records import _rows_of_run, episode_rows
from pipeline.experiment.tracking import MlflowTracker


def a_round(k: int, views: int, picked: list[int], cost: float, cpu: float | None) -> RoundRecord:
    return RoundRecord(k, views, 100 * (k + 1), 20.0 + k, 0.70 + k / 100, 1000 + k, 1.5, selected=picked,
                       per_candidate_ms=cost * 3, selection_seconds=cost, peak_rss_mb=500.0 + k,
                       test_ssim_skimage=0.60 + k / 100, selection_cpu_seconds=cpu, compile_seconds=0.25 * k)


def an_episode() -> EpisodeResult:
    # a pick that cost 0.0 s (a random pick, rounded) is a measured 0, not a missing value
    rounds = [a_round(0, 2, [5], 0.0, 0.0), a_round(1, 3, [7], 2.0, None), a_round(2, 4, [], 0.0, None)]
    final = FinalMetrics(22.5, 0.81, 0.79, None, "LPIPS disabled in the config", 8, [22.5] * 8, [0.81] * 8,
                         [0.79] * 8, 1200, curve_psnr_drop=0.4, degraded=False, nonfinite_steps=2, path_length=3.5)
    return EpisodeResult("scene", "random", 0, "global", [0, 1], [5, 7], [[1], [2]], "train", "test",
                         list(range(8)), [0, 4, 7], rounds, final, 12.0)


class StandInClient:
    """What ``records_from_mlflow`` asks an MLflow client: each metric's history."""

    def __init__(self, logged: list[tuple[str, float, int]]):
        self.logged = [(k, float(v), step) for k, v, step in logged if v is not None and math.isfinite(float(v))]

    def get_metric_history(self, run_id: str, key: str):
        return [SimpleNamespace(step=step, value=v) for k, v, step in self.logged if k == key]


def through_mlflow(episode: EpisodeResult) -> list[dict]:
    outcome = SimpleNamespace(episode=episode, seconds=12.0)
    logged = MlflowTracker._metrics(SimpleNamespace(kind="episode"), outcome)
    client = StandInClient(logged)
    latest = {k: v for k, v, _ in sorted(client.logged, key=lambda m: m[2])}
    run = SimpleNamespace(data=SimpleNamespace(tags={"config_hash": "h", **final_tags(episode.final)},
                                               metrics=latest, params={}),
                          info=SimpleNamespace(run_id="r", status="FINISHED"))
    return _rows_of_run(client, run, "sweep")


def same(a, b) -> bool:
    if a is None or b is None or (isinstance(a, float) and math.isnan(a)):
        return (a is None or a != a) and (b is None or b != b)
    return a == pytest.approx(b)


def test_the_read_back_rebuilds_every_tracked_column_as_the_records_file_has_it():
    episode = an_episode()
    stored = episode_rows({"config_hash": "h"}, episode, 12.0)
    back = through_mlflow(episode)
    stored_rounds = [r for r in stored if r["kind"] == "round"]
    back_rounds = sorted((r for r in back if r["kind"] == "round"), key=lambda r: r["num_views"])
    assert [r["num_views"] for r in back_rounds] == [r["num_views"] for r in stored_rounds] == [2, 3, 4]
    tracked = [c.column for c in ROUND_METRICS]
    assert {"psnr", "ssim", "ssim_skimage", "num_gaussians", "per_candidate_ms", "selection_seconds",
            "selection_cpu_seconds"} == set(tracked)
    for a, b in zip(stored_rounds, back_rounds):
        for column in tracked:
            assert same(a[column], b[column]), (a["num_views"], column, a[column], b[column])
    final_a, final_b = stored[-1], back[-1]
    for column in [c.column for c in FINAL_COLUMNS if c.metric or c.tag] + ["per_candidate_ms", "selection_seconds",
                                                                            "selection_cpu_seconds", "wall_seconds"]:
        assert same(final_a[column], final_b[column]), (column, final_a[column], final_b[column])


def test_a_pick_cost_is_kept_on_rounds_that_picked_and_averaged_over_them():
    rows = episode_rows({}, an_episode(), 12.0)
    rounds, final = rows[:-1], rows[-1]
    assert [r["selection_seconds"] for r in rounds] == [0.0, 2.0, None]  # the last round picked nothing
    assert [r["selection_cpu_seconds"] for r in rounds] == [0.0, None, None]
    assert final["selection_seconds"] == 1.0 and final["per_candidate_ms"] == 3.0
    assert final["selection_cpu_seconds"] == 0.0  # the mean of what was measured
    assert [r["compile_seconds"] for r in rounds] == [0.0, 0.25, 0.5] and final["compile_seconds"] == 0.75
    assert final["peak_rss_mb"] == 502.0 and final["degraded"] is False and final["nonfinite_steps"] == 2


def test_a_field_marked_recorded_is_a_column_and_the_rest_are_not():
    @dataclass
    class Made:
        kept: float = field(metadata=recorded("shown", metric="logged_as"))
        flag: bool = field(default=False, metadata=recorded(tag="flag"))
        private: int = 0

    columns = {c.field: c for c in columns_of(Made)}
    assert set(columns) == {"kept", "flag"}
    assert (columns["kept"].column, columns["kept"].metric, columns["kept"].tag) == ("shown", "logged_as", "")
    assert columns["flag"].encode_tag(True) == "true" and columns["flag"].decode_tag("false") is False
    round_fields = {c.field for c in ROUND_COLUMNS}
    assert {"round", "train_seconds", "scores", "probes"}.isdisjoint(round_fields)  # not record columns
