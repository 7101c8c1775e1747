"""The on-disk layout of a sweep and of its jobs, written once (every reader and writer goes
through these two records instead of spelling the paths).

    <output_dir>/                       SweepFolder
      jobs.json  records.parquet  sweep_config.json  summary.json  sweep.log  mlflow.db
      jobs/<config hash>/               JobFolder
        log.txt
        checkpoint/episode.pt           the episode after its last finished round
        rounds/round_NN.ply             each round's model (job.round_models=true)
        artifacts/result.json           the episode's internal record (EpisodeResult.to_dict)
        artifacts/benchmark/result.json the portable result (pipeline.interchange's schema)
        artifacts/model.ply  artifacts/renders/ ...
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from pipeline.active.checkpoint import CHECKPOINT
from pipeline.experiment.spec import Job


@dataclass(frozen=True)
class JobFolder:
    path: Path

    @property
    def hash(self) -> str:
        return self.path.name

    @property
    def log_file(self) -> Path:
        return self.path / "log.txt"

    @property
    def checkpoint_dir(self) -> Path:
        return self.path / "checkpoint"

    @property
    def checkpoint_file(self) -> Path:
        return self.checkpoint_dir / CHECKPOINT

    @property
    def artifacts(self) -> Path:
        return self.path / "artifacts"

    @property
    def result_file(self) -> Path:
        return self.artifacts / "result.json"

    @property
    def benchmark_result(self) -> Path:
        """The portable ``result.json`` (``pipeline.interchange``'s schema)."""
        return self.artifacts / BENCHMARK_RESULT

    @property
    def model_file(self) -> Path:
        return self.artifacts / MODEL

    def round_model(self, index: int) -> Path:
        return self.path / "rounds" / f"round_{index:02d}.ply"


@dataclass(frozen=True)
class SweepFolder:
    path: Path

    @property
    def jobs_file(self) -> Path:
        return self.path / "jobs.json"

    @property
    def records_file(self) -> Path:
        return self.path / "records.parquet"

    @property
    def config_file(self) -> Path:
        return self.path / "sweep_config.json"

    @property
    def summary_file(self) -> Path:
        return self.path / "summary.json"

    def read_jobs(self) -> list[Job]:
        """The sweep's jobs, as its last launch wrote them."""
        return [Job.from_dict(j) for j in json.loads(self.jobs_file.read_text())]

    def write_jobs(self, jobs: list[Job]) -> None:
        self.jobs_file.write_text(json.dumps([j.to_dict() for j in jobs], indent=1))

    def job(self, config_hash: str) -> JobFolder:
        return JobFolder(self.path / "jobs" / config_hash)

    @staticmethod
    def of_job(folder: Path) -> "SweepFolder":
        """The sweep a job folder ``<output_dir>/jobs/<hash>`` belongs to."""
        return SweepFolder(Path(folder).parent.parent)


BENCHMARK_RESULT = "benchmark/result.json"  # the portable result (an artifact, also in MLflow)
MODEL = "model.ply"  # the final model, INRIA 3DGS PLY (an artifact, also in MLflow)
