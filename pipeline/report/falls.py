"""Round-to-round falls of the PSNR-vs-views curve: per episode, the largest drop of the curve's
PSNR from one round to the next. A pick adds a view, so the model after it should not be worse on
the same test views; a fall is what the training between the two evaluations took away (a reset,
a prune, a densification) or, rarely, a pick that hurt. Reported per method (and setting) with the
episodes whose worst fall is above ``FALL_DB``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from pipeline.report.rows import finished
from pipeline.report.stats import job_ids, job_keys

FALL_DB = 1.0  # a fall above this is counted apart (on bonsai's no-density-control runs every method stayed under 1 dB)
EPISODE_COLUMNS = ("method", "setting", "dataset", "scene", "seed")


@dataclass(frozen=True)
class WorstFall:
    """The largest PSNR drop between consecutive rounds: ``fall_db`` = psnr[from] - psnr[to]
    (0 with no views when the curve never goes down)."""

    fall_db: float
    from_views: int | None
    to_views: int | None


def worst_fall(num_views: np.ndarray, psnr: np.ndarray) -> WorstFall:
    """The worst fall of one episode's curve: ``num_views`` [R] and ``psnr`` [R], the rounds in
    the order they were evaluated (a curve of one round has no fall)."""
    views = np.asarray(num_views)
    values = np.asarray(psnr, dtype=float)
    if values.size < 2:
        return WorstFall(0.0, None, None)
    drops = values[:-1] - values[1:]
    k = int(np.argmax(drops))
    if drops[k] <= 0:
        return WorstFall(0.0, None, None)
    return WorstFall(float(drops[k]), int(views[k]), int(views[k + 1]))


def episode_falls(frame: pd.DataFrame) -> pd.DataFrame:
    """One row per finished episode with at least one round: its ``EPISODE_COLUMNS``, the worst
    fall (``worst_fall_db``, ``from_views``, ``to_views``) and its ``final_psnr``. Rounds are
    taken in training order (iteration, then view count)."""
    rounds = finished(frame, "round").dropna(subset=["psnr"])
    if rounds.empty:
        return pd.DataFrame(columns=[*EPISODE_COLUMNS, "worst_fall_db", "from_views", "to_views", "final_psnr"])
    rounds = rounds.assign(setting=rounds["setting"].fillna("") if "setting" in rounds else "")
    keys = job_keys(rounds)
    finals = finished(frame, "final")
    final = dict(zip(job_ids(finals, keys), finals["psnr"]))
    order = [c for c in ("iteration", "num_views") if c in rounds]
    rows = []
    for job, curve in rounds.groupby(keys, sort=False):
        curve = curve.sort_values(order, kind="stable")
        fall = worst_fall(curve["num_views"].to_numpy(), curve["psnr"].to_numpy())
        first = curve.iloc[0]
        rows.append({**{c: first[c] for c in EPISODE_COLUMNS}, "worst_fall_db": fall.fall_db,
                     "from_views": fall.from_views, "to_views": fall.to_views,
                     "final_psnr": float(final.get(job, np.nan))})
    return pd.DataFrame(rows)


def _worst_cell(part: pd.DataFrame) -> str:
    """'1.45 (seed 2, 5 → 6)': the largest worst fall among ``part``'s episodes, where it was."""
    top = part.loc[part["worst_fall_db"].idxmax()]
    if top["worst_fall_db"] <= 0:
        return "0.00 (never falls)"
    return (f"{top['worst_fall_db']:.2f} (seed {int(top['seed'])}, "
            f"{int(top['from_views'])} → {int(top['to_views'])})")


def falls_markdown(falls: pd.DataFrame, threshold: float = FALL_DB) -> str:
    """Rows method (and setting, when there are several: each method's settings together), a
    column pair per scene: the worst fall over its episodes, with seed and views, and how many
    episodes fall more than ``threshold``."""
    if falls.empty:
        return ""
    scenes = list(dict.fromkeys(zip(falls["dataset"], falls["scene"])))
    settings = list(dict.fromkeys(falls["setting"]))
    with_setting = settings != [""]
    header = ["method"] + (["setting"] if with_setting else [])
    for _, scene in scenes:
        header += [f"{scene}: worst fall (dB)", f"{scene}: > {threshold:g} dB"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for method in dict.fromkeys(falls["method"]):
        for setting in settings:
            part = falls[(falls["method"] == method) & (falls["setting"] == setting)]
            if not part.empty:
                cells = [method] + ([setting] if with_setting else [])
                lines.append("| " + " | ".join(cells + _scene_cells(part, scenes, threshold)) + " |")
    lines += ["", "Per episode the largest drop of the curve PSNR (the curve's test views) from one round to "
              "the next; per cell the largest of those over the seeds, the seed and the views where it was, "
              f"and how many episodes have a drop above {threshold:g} dB (every episode's: `falls.csv`)."]
    return "\n".join(lines) + "\n"


def _scene_cells(part: pd.DataFrame, scenes: list[tuple[str, str]], threshold: float) -> list[str]:
    """[worst fall, episodes above ``threshold``] per (dataset, scene), 'n/a' where none ran."""
    cells = []
    for dataset, scene in scenes:
        here = part[(part["dataset"] == dataset) & (part["scene"] == scene)]
        if here.empty:
            cells += ["n/a", "n/a"]
            continue
        over = int((here["worst_fall_db"] > threshold).sum())
        cells += [_worst_cell(here), f"{over} of {len(here)}"]
    return cells
