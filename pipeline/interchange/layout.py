"""The on-disk layout of a sweep and of its jobs, written once and torch-free, so the sweep's
writers (``pipeline.experiment``), the reports, the viewer and readers of ``result.json`` spell
no path themselves. ``pipeline.experiment.layout`` adds reading and writing the jobs list.

    <output_dir>/                       SweepFolder
      jobs.json  records.parquet  sweep_config.json  summary.json  sweep.log  mlflow.db
      jobs/<config hash>/               JobFolder
        log.txt
        checkpoint/episode.pt           the episode after its last finished round
        rounds/round_NN.ply             each round's model (job.round_models=true)
        rounds/images_VVV/<key>.png     each round's images at VVV views (job.round_images > 0)
        artifacts/result.json           the episode's internal record (EpisodeResult.to_dict)
        artifacts/benchmark/result.json the portable result (this package's result schema)
        artifacts/model.ply  artifacts/renders/ ...
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

RECORDS = "records.parquet"
CHECKPOINT = "episode.pt"                      # the episode checkpoint's file name
BENCHMARK_RESULT = "benchmark/result.json"     # the portable result (an artifact, also in MLflow)
MODEL = "model.ply"                            # the final model, INRIA 3DGS PLY (an artifact, also in MLflow)


def cannot_write(path: Path, folder: bool = False) -> str | None:
    """Why ``path`` cannot be written (``folder``: a folder to fill, else a file), None when it
    can: makes the folder (or the file's folder) and writes a probe file there."""
    import os
    target = Path(path) if folder else Path(path).parent
    try:
        target.mkdir(parents=True, exist_ok=True)
        probe = target / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        return f"cannot write there ({err.strerror or err})"
    if not folder and Path(path).is_dir():
        return "is a folder, expected a file"
    return None


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
    def starts_file(self) -> Path:
        """One JSON line per start of the job (host, node, pid, time): retries, requeues, relaunches."""
        return self.path / "starts.jsonl"

    @property
    def progress_file(self) -> Path:
        """Round messages of a job run by a batch scheduler (one JSON line each), tailed by the driver."""
        return self.path / "progress.jsonl"

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

    def round_images_dir(self, views: int) -> Path:
        """The round images (renders, variance maps, the picked view) of the round at ``views`` views."""
        return self.path / "rounds" / f"images_{views:03d}"

    def saved_round_images(self) -> dict[int, dict[str, Path]]:
        """views -> image key -> PNG, every round whose images the job saved."""
        out = {}
        for folder in sorted((self.path / "rounds").glob("images_*")):
            if folder.is_dir() and folder.name[len("images_"):].isdigit():
                out[int(folder.name[len("images_"):])] = {p.stem: p for p in sorted(folder.glob("*.png"))}
        return out


@dataclass(frozen=True)
class SweepFolder:
    path: Path

    @property
    def jobs_file(self) -> Path:
        return self.path / "jobs.json"

    @property
    def records_file(self) -> Path:
        return self.path / RECORDS

    @property
    def config_file(self) -> Path:
        return self.path / "sweep_config.json"

    @property
    def summary_file(self) -> Path:
        return self.path / "summary.json"

    @property
    def jobs_dir(self) -> Path:
        return self.path / "jobs"

    def job(self, config_hash: str) -> JobFolder:
        return JobFolder(self.jobs_dir / config_hash)

    def job_folders(self) -> list[JobFolder]:
        """Every job folder on disk, by hash."""
        return [JobFolder(p) for p in sorted(self.jobs_dir.glob("*")) if p.is_dir()]

    def benchmark_results(self) -> list[Path]:
        """Every job's portable result.json on disk."""
        return [f.benchmark_result for f in self.job_folders() if f.benchmark_result.is_file()]
