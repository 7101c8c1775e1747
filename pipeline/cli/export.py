"""``gopre-export``: a run's trained model as a standard 3DGS file (gsplat's exporter).

    gopre-export outputs/demo/jobs/<config hash>                  # -> model.ply beside it
    gopre-export outputs/demo/jobs/<hash>/checkpoint/episode.pt --format splat --out m.splat
    gopre-export RUN_ID --mlflow-uri sqlite:///outputs/demo/mlflow.db --format ply_compressed

SOURCE: a job folder (its final model, ``artifacts/model.ply``, else its last round checkpoint),
an episode checkpoint (``episode.pt``: the model of its last round, at that round's SH degree), a
3DGS ``.ply``, or an MLflow run id (its ``model.ply`` artifact) with ``--mlflow-uri``.
Exit status 0, or 1 with one line naming the source and the reason.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.cli import alias_note, command_name, unwritable
from pipeline.experiment.export import read_model
from pipeline.splat import ply


def default_out(source: str, fmt: str, mlflow: bool) -> Path:
    base = Path(f"model-{source}") if mlflow else Path(source)
    if base.is_dir():
        base = base / "model"
    else:
        base = base.with_suffix("") if base.suffix in (".pt", ".ply", ".splat", ".spz") else base
        base = base.parent / f"{base.name}-export"
    return base.parent / (base.name + ply.SUFFIX[fmt])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog=command_name("export"), description=__doc__,
                                     epilog=alias_note("export"),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", help="job folder, episode.pt, a .ply / .spz / .splat model, or an MLflow run id")
    parser.add_argument("--format", default="ply", choices=ply.FORMATS)
    parser.add_argument("--out", type=Path, default=None, help="output file (default: beside the source)")
    parser.add_argument("--mlflow-uri", default=None, help="read SOURCE as a run id from this tracking URI")
    args = parser.parse_args(argv)
    try:
        out = args.out or default_out(args.source, args.format, bool(args.mlflow_uri))
        problem = unwritable(out, "--out")
        if problem:
            raise ValueError(problem)
        model = read_model(args.source, args.mlflow_uri)
        data = ply.export_bytes(model, args.format)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(data)
        kept = ply.written_count(data, args.format)
    except ValueError as err:
        print(f"{command_name('export')}: error: {err}", file=sys.stderr)
        return 1
    dropped = f" ({len(model) - kept} of the model's {len(model)} dropped)" if kept != len(model) else ""
    print(f"{out}: {kept} Gaussians{dropped}, SH degree {model.sh_degree}, format {args.format}, "
          f"{len(data) / 2 ** 20:.2f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
