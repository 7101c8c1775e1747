"""The sweep's layout (``pipeline.interchange.layout``: every path, torch-free) with what only the
experiment layer does to it: read and write the jobs list as typed ``Job`` records."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from pipeline.active.checkpoint import CHECKPOINT as _CHECKPOINT
from pipeline.experiment.spec import Job
from pipeline.interchange import layout as _layout
from pipeline.interchange.layout import BENCHMARK_RESULT, CHECKPOINT, MODEL, RECORDS, JobFolder

if CHECKPOINT != _CHECKPOINT:  # one name for the checkpoint file, whichever side spells it
    raise ImportError(f"layout's checkpoint name {CHECKPOINT!r} differs from active.checkpoint's {_CHECKPOINT!r}")


@dataclass(frozen=True)
class SweepFolder(_layout.SweepFolder):
    def read_jobs(self) -> list[Job]:
        """The sweep's jobs, as its last launch wrote them."""
        return [Job.from_dict(j) for j in json.loads(self.jobs_file.read_text())]

    def write_jobs(self, jobs: list[Job]) -> None:
        self.jobs_file.write_text(json.dumps([j.to_dict() for j in jobs], indent=1))

    @staticmethod
    def of_job(folder: Path) -> "SweepFolder":
        """The sweep a job folder ``<output_dir>/jobs/<hash>`` belongs to."""
        return SweepFolder(Path(folder).parent.parent)


__all__ = ["BENCHMARK_RESULT", "CHECKPOINT", "MODEL", "RECORDS", "JobFolder", "SweepFolder"]
