"""Which finished jobs of a sweep folder were computed on other data than the scene holds now.

A job's hash holds its scene's data fingerprint (``pipeline.data.fingerprint``), so a relaunch over
changed data does not find the old results under the new hashes and re-runs those jobs. This module
names what changed, scene by scene: a finished record of the same job on another fingerprint (the
job's plain form with the record's fingerprint hashes to the record's hash), or one recorded before
data identity (the job's plain form without a fingerprint hashes to it). Those records are
*superseded*: moved from ``records.parquet`` to ``records_superseded.parquet`` (nothing is deleted;
``jobs/<old hash>/`` stays), so the folder's report holds one data identity per scene.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from pipeline.experiment.spec import config_hash, without_data_identity
from pipeline.experiment.spec import Job

SUPERSEDED = "records_superseded.parquet"


@dataclass
class SceneChange:
    """One scene whose finished jobs were computed on other data."""

    dataset: str
    scene: str
    now: str                                       # the fingerprint the scene has now
    before: set[str] = field(default_factory=set)  # recorded fingerprints ("" = none recorded)
    hashes: set[str] = field(default_factory=set)  # the superseded jobs' config hashes

    def line(self) -> str:
        was = ", ".join(sorted(f or "not recorded (launched before data identity)" for f in self.before))
        return (f"data changed: dataset.{self.dataset} scene {self.scene!r} is now {self.now} (was {was}): "
                f"its {len(self.hashes)} finished job(s) re-run")


def _finished(records: pd.DataFrame) -> pd.DataFrame:
    if records.empty or "config_hash" not in records:
        return records.iloc[0:0]
    return records[(records["kind"] == "final") & (records["status"] == "FINISHED")]


def data_changes(jobs: list[Job], records: pd.DataFrame) -> list[SceneChange]:
    """Per scene, the finished records that are these jobs on other data (see the module's text)."""
    finished = _finished(records)
    if finished.empty:
        return []
    fingerprints = (finished["data_fingerprint"] if "data_fingerprint" in finished
                    else pd.Series([None] * len(finished), index=finished.index))
    recorded = {h: (f if isinstance(f, str) else "") for h, f in zip(finished["config_hash"], fingerprints)}
    current = {j.config_hash for j in jobs}
    changes: dict[tuple[str, str], SceneChange] = {}
    for job in jobs:
        if not job.data_fingerprint or job.config_hash in recorded:
            continue
        candidates = {without_data_identity(job): ""}
        for old in {f for f in recorded.values() if f and f != job.data_fingerprint}:
            candidates[config_hash({**job.to_dict(), "data_fingerprint": old})] = old
        for old_hash, old_fingerprint in candidates.items():
            if old_hash in recorded and old_hash not in current:
                change = changes.setdefault((job.dataset, job.scene),
                                            SceneChange(job.dataset, job.scene, job.data_fingerprint))
                change.before.add(old_fingerprint)
                change.hashes.add(old_hash)
    return list(changes.values())


def supersede(folder: Path, records: pd.DataFrame, hashes: set[str]) -> pd.DataFrame:
    """Move every row of ``hashes`` from the records to ``records_superseded.parquet`` (appended,
    written atomically before the records shrink: a kill in between leaves the rows in both, never in
    neither); the records that stay."""
    moving = records[records["config_hash"].isin(hashes)]
    if moving.empty:
        return records
    path = Path(folder) / SUPERSEDED
    kept = pd.read_parquet(path) if path.exists() else pd.DataFrame()
    merged = pd.concat([kept, moving], ignore_index=True)
    tmp = path.with_suffix(".tmp")
    merged.to_parquet(tmp, index=False)
    os.replace(tmp, path)
    return records[~records["config_hash"].isin(hashes)].reset_index(drop=True)
