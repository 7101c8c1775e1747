"""Jobs the tracking store missed, replayed from what the sweep kept (``records.parquet`` and
``jobs/<hash>/``), without anyone asking:

- at the end of a sweep whose jobs could not be tracked (a server that went away), the driver tries
  again while the server does not answer, every ``RETRY_EVERY_S`` for up to ``tracking.replay_wait_s``
  seconds, saying so on the console;
- at every launch, the jobs this folder finished that the store does not have as FINISHED are
  replayed before any job runs;
- ``tracking_sync=true`` does only the replay (no job runs), as before.

A replayed run is the job's child run under the launch's parent run, with the records' worker
columns as its ``worker.*`` tags, its artifacts from ``jobs/<hash>/artifacts``, its round metrics
from ``result.json`` and its round images from ``jobs/<hash>/rounds/`` (``tracking.MlflowTracker``
takes the images a job saved there whenever MLflow did not receive them live).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pandas as pd

from pipeline.interchange.sweep_results import SweepResults
from pipeline.experiment.outcome import FINISHED, JobOutcome
from pipeline.experiment.records import RecordsFile
from pipeline.experiment.spec import Job
from pipeline.experiment.tracking import Tracker

RETRY_EVERY_S = 10.0  # between two tries while the tracking server does not answer
WORKER_COLUMNS = {"host": "host", "node": "node", "code_version": "worker_code_version", "packages": "packages",
                  "locked": "packages_locked", "cpu": "cpu", "starts": "starts"}  # worker key -> records column


@dataclass
class Replay:
    replayed: list[str] = field(default_factory=list)   # config hashes now FINISHED in the store
    unknown: list[str] = field(default_factory=list)    # not in this sweep's config, or no result.json
    failed: list[str] = field(default_factory=list)     # the store did not take them (still down)

    def line(self) -> str:
        out = f"{len(self.replayed)} run(s) replayed"
        if self.failed:
            out += f", {len(self.failed)} not (the tracking server did not take them)"
        if self.unknown:
            out += (f", {len(self.unknown)} not replayable (not in this sweep's config, or no "
                    f"jobs/<hash>/artifacts/result.json): {', '.join(self.unknown)}")
        return out


def finished_rows(records: RecordsFile) -> pd.DataFrame:
    frame = records.frame
    if frame.empty:
        return frame
    return frame.query("kind == 'final' and status == 'FINISHED'")


def finished_not_in(records: RecordsFile, have: set[str]) -> list[str]:
    """The config hashes the records have as finished that are not in ``have`` (the store's
    FINISHED runs), in records order."""
    finals = finished_rows(records)
    if finals.empty:
        return []
    return [h for h in dict.fromkeys(finals["config_hash"]) if h not in have]


def outcome_of(results: SweepResults, config_hash: str, row: pd.Series) -> JobOutcome:
    """A finished job's outcome as the worker returned it, from what the sweep kept."""
    job_folder = results.job(config_hash)
    folder = job_folder.artifacts
    artifacts = {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
                 if p.is_file() and p != job_folder.result_file}
    cells = {key: _plain(row.get(column)) for key, column in WORKER_COLUMNS.items()}
    worker = {key: value for key, value in cells.items() if value is not None}
    return JobOutcome(FINISHED, _count(row.get("attempts")), [], results.episode_data(config_hash),
                      artifacts, _number(row.get("wall_seconds")), worker=worker)


def replay(tracker: Tracker, jobs: dict[str, Job], output_dir: Path, records: RecordsFile,
           hashes: list[str]) -> Replay:
    """Log each of ``hashes`` as a finished run; a job the store refuses (a server still down) is
    counted as failed and the rest are still tried."""
    out = Replay()
    finals, results = finished_rows(records), SweepResults(output_dir)
    for config_hash in hashes:
        job = jobs.get(config_hash)
        if job is None or not results.job(config_hash).result_file.exists() or finals.empty:
            out.unknown.append(config_hash)
            continue
        row = finals[finals["config_hash"] == config_hash].iloc[-1]
        try:
            run_id = tracker.log_job(job, outcome_of(results, config_hash, row))
        except Exception:  # the server is still away: the records keep the job, the next try takes it
            out.failed.append(config_hash)
            continue
        records.add([{**r, "run_id": run_id} for r in
                     records.frame[records.frame["config_hash"] == config_hash].to_dict("records")])
        out.replayed.append(config_hash)
    return out


def replay_until_taken(tracker: Tracker, jobs: dict[str, Job], output_dir: Path, records: RecordsFile,
                       hashes: list[str], wait_s: float, say: Callable[[str], None],
                       sleep: Callable[[float], None] = time.sleep) -> Replay:
    """``replay``, tried again every ``RETRY_EVERY_S`` while some are refused, for up to ``wait_s``."""
    attempts = 1 + int(wait_s // RETRY_EVERY_S)  # the first try, then one every RETRY_EVERY_S within wait_s
    total = Replay()
    left = list(hashes)
    for attempt in range(attempts):
        if tracker.answers():  # no half-written run while the server is away
            tracker.close_orphans()  # the runs the outage left open end KILLED (the replay replaces them)
            done = replay(tracker, jobs, output_dir, records, left)
            total.replayed += done.replayed
            total.unknown += done.unknown
            left = done.failed
        if not left or attempt == attempts - 1:
            break
        if attempt == 0:
            say(f"tracking: the server does not take {len(left)} finished run(s) yet; trying again every "
                f"{RETRY_EVERY_S:.0f} s for up to {wait_s:.0f} s (tracking.replay_wait_s)")
        sleep(RETRY_EVERY_S)
    total.failed = left
    return total


def _plain(value):
    """A records cell as plain data (None when missing)."""
    if value is None or (isinstance(value, float) and value != value):
        return None
    return value.item() if hasattr(value, "item") else value


def _number(value) -> float | None:
    """A records cell as a float, None when missing (NaN or None)."""
    return None if value is None or value != value else float(value)


def _count(value) -> int:
    """A records cell holding an attempt count (1 when it was not recorded)."""
    number = _number(value)
    return 1 if number is None else int(number)
