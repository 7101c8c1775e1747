"""Which record rows a report reads: the finished jobs' rows of one kind."""

from __future__ import annotations

import pandas as pd


def finished(frame: pd.DataFrame, kind: str, job_kind: str = "episode") -> pd.DataFrame:
    """The rows of ``kind`` (final, round, ause, sparsification) of finished ``job_kind`` jobs."""
    ok = frame["status"] == "FINISHED"
    return frame[ok & (frame["kind"] == kind) & (frame["job_kind"] == job_kind)]
