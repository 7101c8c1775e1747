"""The pixel-level sparsification curves of a sweep's episodes (Fig. 7 extended), read from each
finished job's ``result.json`` (``final.uncertainty_curves``: kept in the job folder, not in the
records), as one tidy frame: scene, method, seed, error (mae, rmse, dssim), fraction removed, the
curve ranked by the final model's Laplace variance, the oracle's (ranked by the true error) and
the random one (the error of all pixels)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from pipeline.interchange.sweep_results import SweepResults

COLUMNS = ["scene", "method", "seed", "error", "fraction", "by_uncertainty", "oracle", "random"]


def pixel_curves(sweep_dir: Path | None, finals: pd.DataFrame) -> pd.DataFrame:
    """The curves of the finished episodes ``finals`` (final rows) whose jobs measured them."""
    rows = []
    if sweep_dir is None or finals.empty:
        return pd.DataFrame(columns=COLUMNS)
    results = SweepResults(sweep_dir)
    for final in finals.itertuples():
        episode = results.episode_data(str(final.config_hash)) or {}  # plain: a job older than a field still reads
        curves = (episode.get("final") or {}).get("uncertainty_curves")
        if not curves:
            continue
        for error in ("mae", "rmse", "dssim"):
            part = curves[error]
            rows += [(final.scene, final.method, final.seed, error, f, by, oracle, rand)
                     for f, by, oracle, rand in zip(curves["fractions"], part["by_uncertainty"], part["oracle"],
                                                    part["random"])]
    return pd.DataFrame(rows, columns=COLUMNS)


def relative(curves: pd.DataFrame) -> pd.DataFrame:
    """Each job's curves over its error of all pixels (its random curve): 1 at fraction 0, the share
    of the error that the kept pixels still carry per pixel; comparable across methods whose models
    err by different amounts."""
    out = curves.copy()
    for column in ("by_uncertainty", "oracle", "random"):
        out[column] = curves[column] / curves["random"]
    return out
