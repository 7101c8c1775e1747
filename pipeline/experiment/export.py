"""``pipeline-export``: a run's trained model as a standard 3DGS file (gsplat's exporter).

    pipeline-export outputs/demo/jobs/<config hash>                  # -> model.ply beside it
    pipeline-export outputs/demo/jobs/<hash>/checkpoint/episode.pt --format splat --out m.splat
    pipeline-export RUN_ID --mlflow-uri sqlite:///outputs/demo/mlflow.db --format ply_compressed

SOURCE: a job folder (its final model, ``artifacts/model.ply``, else its last round checkpoint),
an episode checkpoint (``episode.pt``: the model of its last round, at that round's SH degree), a
3DGS ``.ply``, or an MLflow run id (its ``model.ply`` artifact) with ``--mlflow-uri``.
Exit status 0, or 1 with one line naming the source and the reason.
"""

from __future__ import annotations

import argparse
import sys
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


def default_out(source: str, fmt: str, mlflow: bool) -> Path:
    base = Path(f"model-{source}") if mlflow else Path(source)
    if base.is_dir():
        base = base / "model"
    else:
        base = base.with_suffix("") if base.suffix in (".pt", ".ply") else base
        base = base.parent / f"{base.name}-export"
    return base.parent / (base.name + ply.SUFFIX[fmt])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="pipeline-export", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", help="job folder, episode.pt, .ply, or an MLflow run id")
    parser.add_argument("--format", default="ply", choices=ply.FORMATS)
    parser.add_argument("--out", type=Path, default=None, help="output file (default: beside the source)")
    parser.add_argument("--mlflow-uri", default=None, help="read SOURCE as a run id from this tracking URI")
    args = parser.parse_args(argv)
    try:
        model = read_model(args.source, args.mlflow_uri)
        out = args.out or default_out(args.source, args.format, bool(args.mlflow_uri))
        data = ply.export_bytes(model, args.format)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(data)
        kept = ply.written_count(data, args.format)
    except ValueError as err:
        print(f"pipeline-export: error: {err}", file=sys.stderr)
        return 1
    dropped = f" ({len(model) - kept} of the model's {len(model)} dropped)" if kept != len(model) else ""
    print(f"{out}: {kept} Gaussians{dropped}, SH degree {model.sh_degree}, format {args.format}, "
          f"{len(data) / 2 ** 20:.2f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
