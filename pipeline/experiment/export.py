"""Reading a model back: from an episode checkpoint (the model of its last round, at that round's
SH degree), a job folder (its final ``artifacts/model.ply``, else its checkpoint), a 3DGS file, or
an MLflow run's ``model.ply`` artifact. The ``gopre-export`` command is ``pipeline.cli.export``."""

from __future__ import annotations

import tempfile
from pathlib import Path

import torch

from pipeline.experiment.layout import MODEL, JobFolder
from pipeline.splat import Gaussians, ply


def from_checkpoint(path: Path) -> Gaussians:
    try:
        state = torch.load(path, weights_only=False, map_location="cpu")
        trainer = state["trainer"]
    except Exception as err:
        raise ValueError(f"{path}: not a readable episode checkpoint ({type(err).__name__}: {err})") from None
    g = Gaussians(**trainer["params"]).detach()
    degree = trainer.get("active_sh_degree")  # absent in checkpoints older than the exporter
    return g.at_sh_degree(degree) if degree is not None else g


def from_mlflow(uri: str, run_id: str) -> Gaussians:
    from mlflow import MlflowClient  # the tracking edge
    with tempfile.TemporaryDirectory() as tmp:
        try:
            local = MlflowClient(tracking_uri=uri).download_artifacts(run_id, MODEL, tmp)
        except Exception as err:
            raise ValueError(f"MLflow run {run_id} at {uri}: no {MODEL} artifact ({type(err).__name__}: {err})") from None
        return ply.load(local)


def read_model(source: str, mlflow_uri: str | None = None) -> Gaussians:
    if mlflow_uri:
        return from_mlflow(mlflow_uri, source)
    path = Path(source)
    if path.is_dir():
        job = JobFolder(path)
        for candidate in (job.model_file, path / MODEL):
            if candidate.exists():
                return ply.load(candidate)
        if job.checkpoint_file.exists():
            return from_checkpoint(job.checkpoint_file)
        raise ValueError(f"{path}: a folder without artifacts/{MODEL} or checkpoint/episode.pt (pass a "
                         "job folder outputs/<sweep>/jobs/<config hash>)")
    if not path.exists():
        raise ValueError(f"{path}: no such file or folder (or pass --mlflow-uri for a run id)")
    if path.suffix == ".pt":
        return from_checkpoint(path)
    return ply.load(path)
