"""The records' scalar columns, derived once from the typed records' fields (``recorded`` metadata on
``RoundRecord`` and ``FinalMetrics``, ``pipeline.interchange.results``): the records file's rows
(``records.episode_rows``), what MLflow logs (``tracking``) and the read-back from MLflow
(``records.records_from_mlflow``) all take their lists from here, so a new recorded quantity is one
field of the record plus the code that measures it.

What is not a scalar of a record stays with its writer: the identity columns of every row, the picks
and poses as JSON, a search's account (``records.SEARCH_METRICS``), the uncertainty and depth families
(by prefix), the job's wall time.
"""

from __future__ import annotations

import typing
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from pipeline.interchange.results import FinalMetrics, RoundRecord


@dataclass(frozen=True)
class Column:
    """One recorded field: ``field`` of the record, ``column`` in the records, the MLflow ``metric``
    or ``tag`` carrying it ("" for neither: the records file only), ``picks_only`` (a round has it only when it
    picked), ``kind`` the field's Python type name (how a tag's text reads back)."""

    field: str
    column: str
    metric: str  # "": not logged as a metric
    tag: str     # "": not a tag
    picks_only: bool
    kind: str

    def encode_tag(self, value: Any) -> str:
        return str(bool(value)).lower() if self.kind == "bool" else str(value)[:5000]

    def decode_tag(self, text: str | None) -> Any:
        if self.kind == "bool":
            return text == "true"
        if text is None:
            return None
        return int(text) if self.kind == "int" else text


def columns_of(record: type) -> tuple[Column, ...]:
    hints = typing.get_type_hints(record)
    out = []
    for f in fields(record):
        meta = f.metadata.get("recorded")
        if meta is None:
            continue
        kind = hints[f.name]
        name = kind.__name__ if isinstance(kind, type) else "optional"
        out.append(Column(f.name, meta["column"] or f.name, meta["metric"] or "", meta["tag"] or "", meta["picks_only"],
                          name))
    return tuple(out)


ROUND_COLUMNS = columns_of(RoundRecord)
FINAL_COLUMNS = columns_of(FinalMetrics)
ROUND_METRICS = tuple(c for c in ROUND_COLUMNS if c.metric)
PICK_COLUMNS = tuple(c for c in ROUND_COLUMNS if c.picks_only)  # selection costs: the final row's means
FINAL_METRICS = tuple(c for c in FINAL_COLUMNS if c.metric)
FINAL_TAGS = tuple(c for c in FINAL_COLUMNS if c.tag)


def round_values(r: RoundRecord) -> dict:
    """A round row's recorded columns (a pick's cost is None on a round that picked nothing)."""
    picked = bool(r.selected)
    return {c.column: getattr(r, c.field) if picked or not c.picks_only else None for c in ROUND_COLUMNS}


def round_metrics(r: RoundRecord) -> list[tuple[str, Any, int]]:
    """The MLflow metrics of a round, at step = views trained on (a pick's cost only on a round that picked)."""
    picked = bool(r.selected)
    return [(c.metric, getattr(r, c.field), r.num_views) for c in ROUND_METRICS if picked or not c.picks_only]


def pick_means(rounds: list[RoundRecord]) -> dict:
    """The final row's selection costs: each one's mean over the rounds that picked and measured it."""
    picks = [r for r in rounds if r.selected]
    return {c.column: mean_present([getattr(r, c.field) for r in picks]) for c in PICK_COLUMNS}


def final_values(final: FinalMetrics) -> dict:
    return {c.column: getattr(final, c.field) for c in FINAL_COLUMNS}


def final_metrics(final: FinalMetrics) -> list[tuple[str, Any, int]]:
    return [(c.metric, getattr(final, c.field), 0) for c in FINAL_METRICS]


def final_tags(final: FinalMetrics) -> dict[str, str]:
    return {c.tag: c.encode_tag(getattr(final, c.field)) for c in FINAL_TAGS}


def mean_present(values: list) -> float | None:
    """The mean of the values that were measured (None: none was, e.g. a record older than the field)."""
    present = [v for v in values if v is not None]
    return float(np.mean(present)) if present else None
