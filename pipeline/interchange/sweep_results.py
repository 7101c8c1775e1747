"""A sweep's output folder, read: what the reports, the viewer, the tracking replay and ``gopre-eval
--sweep`` take from a sweep, so none of them spells a path or parses a job's file by hand (Ray Tune's
``ResultGrid`` is the model). Torch-free: the records frame, each job's configuration as plain data,
its episode as the typed ``EpisodeResult`` (without the model), its portable ``result.json``, its
model file and its round images.

    results = SweepResults("outputs/table2_goal")
    for row in results.finished().itertuples():
        episode = results.episode(row.config_hash)   # EpisodeResult, or None when absent
"""

from __future__ import annotations

import json
from functools import cached_property
from pathlib import Path

import pandas as pd

from pipeline.interchange.layout import JobFolder, SweepFolder
from pipeline.interchange.results import EpisodeResult


class SweepResults:
    def __init__(self, folder: str | Path):
        self.folder = SweepFolder(Path(folder))

    @property
    def path(self) -> Path:
        return self.folder.path

    @cached_property
    def records(self) -> pd.DataFrame:
        """``records.parquet`` as written (an empty frame before the first finished job)."""
        path = self.folder.records_file
        return pd.read_parquet(path) if path.exists() else pd.DataFrame()

    def finished(self) -> pd.DataFrame:
        """The final rows of the finished jobs."""
        frame = self.records
        if frame.empty or "kind" not in frame:
            return frame
        return frame[(frame["kind"] == "final") & (frame["status"] == "FINISHED")]

    def job_configs(self) -> list[dict]:
        """Each job as the sweep's last launch described it (``jobs.json``, plain data)."""
        if not self.folder.jobs_file.exists():
            raise ValueError(f"{self.path}: no jobs.json (not a sweep folder)")
        return json.loads(self.folder.jobs_file.read_text())

    def job(self, config_hash: str) -> JobFolder:
        return self.folder.job(config_hash)

    def episode_data(self, config_hash: str) -> dict | None:
        """A finished episode's internal record (``EpisodeResult.to_dict``) as plain data; None when
        the job has not finished."""
        path = self.job(config_hash).result_file
        return json.loads(path.read_text()) if path.is_file() else None

    def episode(self, config_hash: str) -> EpisodeResult | None:
        """A finished episode, typed (without its model: ``model_file`` holds it)."""
        data = self.episode_data(config_hash)
        return None if data is None else EpisodeResult.from_dict(data)

    def result_document(self, config_hash: str) -> dict | None:
        """The portable ``result.json`` (``pipeline.interchange``'s schema) of a finished episode."""
        path = self.job(config_hash).benchmark_result
        return json.loads(path.read_text()) if path.is_file() else None

    def model_file(self, config_hash: str) -> Path:
        return self.job(config_hash).model_file

    def round_images(self, config_hash: str) -> dict[int, dict[str, Path]]:
        """views -> image key -> PNG of every round whose images the job kept."""
        return self.job(config_hash).saved_round_images()
