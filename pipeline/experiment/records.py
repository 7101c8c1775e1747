"""The sweep's records file (``<output_dir>/records.parquet``): one tidy table the reports read.

Rows, by ``kind``:
- ``round``: one per episode round (``num_views`` = views trained on; the PSNR-vs-views curve).
- ``final``: one per job: final metrics on every test view (``ssim`` is 3DGS's, ``ssim_skimage``
  scikit-image's, ``metrics_version`` and ``ssim_source`` as in ``pipeline.interchange.results``),
  status, selection cost, run id,
  ``degraded`` (the final model scored more than 3 dB below the last round on the same views),
  ``curve_psnr_drop`` (that difference) and ``nonfinite_steps`` (training steps skipped because
  their loss or gradient was not finite).
- ``sparsification``: one per (uncertainty method, fraction) of an uncertainty job.
- ``ause``: one per uncertainty method of an uncertainty job.
Identifying columns on every row: sweep, config_hash, run_id, status, dataset, scene, method,
strategy, protocol, seed, setting (the sweep-axis values as ``key=value, ...``), axes (JSON),
code_version (the code that computed the job, ``provenance.code_version``), data_fingerprint (the
scene's data identity, ``pipeline.data.fingerprint``; empty for a job recorded before it).
The file is rewritten atomically after every job, so a killed sweep loses no finished job.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.interchange.results import EpisodeResult, FinalMetrics, UncertaintyResult
from pipeline.experiment.outcome import JobOutcome
from pipeline.experiment.record_columns import (FINAL_METRICS, FINAL_TAGS, PICK_COLUMNS, ROUND_METRICS,
                                                final_values, mean_present, pick_means, round_values)
from pipeline.experiment.spec import Job
from pipeline.interchange.layout import RECORDS  # the one spelling of the records file


def identity(job: Job, outcome: JobOutcome, run_id: str | None) -> dict:
    return {"sweep": job.sweep, "job_index": job.index, "config_hash": job.config_hash,
            "run_id": run_id,
            "status": outcome.status, "job_kind": job.kind, "dataset": job.dataset,
            "scene": job.scene, "method": job.method, "strategy": job.strategy,
            "protocol": job.protocol["kind"], "seed": job.seed, "setting": job.setting,
            "axes": json.dumps(job.axes, sort_keys=True), "code_version": job.code_version,
            "data_fingerprint": job.data_identity,
            "world": job.world["kind"] if job.world else "dataset",  # where a view off the pool comes from
            **plugin_columns(job)}


def plugin_columns(job: Job) -> dict:
    """A plugin strategy's identity (plugin, plugin_distribution, plugin_version, plugin_sha256);
    none for a built-in strategy, so the records of built-in jobs keep their columns."""
    if job.plugin is None:
        return {}
    p = job.plugin
    return {"plugin": p["reference"], "plugin_distribution": p["distribution"],
            "plugin_version": p["version"], "plugin_sha256": p["source_sha256"]}


def episode_rows(base: dict, episode: EpisodeResult, seconds: float) -> list[dict]:
    """A round row per round, then the final row: the records' columns of the typed records
    (``record_columns``), the picks as JSON, a search's account off the pool."""
    rounds = episode.rounds
    rows = [{**base, "kind": "round", **round_values(r), "selected": json.dumps(r.selected),
             **({"poses": json.dumps(r.poses), **search_columns(r.search)} if r.search else {})}
            for r in rounds]
    rows.append({**base, "kind": "final", "num_views": rounds[-1].num_views if rounds else None,
                 **final_columns(episode.final), "wall_seconds": seconds, **pick_means(rounds),
                 "compile_seconds": float(sum(r.compile_seconds for r in rounds)),
                 "peak_rss_mb": max((r.peak_rss_mb for r in rounds), default=None),
                 "selected": json.dumps(episode.selected), "initial": json.dumps(episode.initial),
                 **({"poses": json.dumps(episode.acquired_poses)} if episode.acquired_poses else {})})
    return rows


def search_columns(search: dict) -> dict:
    """A round off the pool: which pick it took and the scores the search compared."""
    return {"search_taken": search["taken"], **{f"search_{k}": search[k] for k in SEARCH_SCORES}}


def final_columns(final: FinalMetrics) -> dict:
    """The final row's metric columns: the recorded fields, then the uncertainty and depth families."""
    return {**final_values(final), **uncertainty_columns(final.uncertainty), **depth_columns(final.depth)}


UNCERTAINTY_PREFIX = "unc_"  # the final model's pixel-level uncertainty metrics (eval.model_uncertainty)
DEPTH_PREFIX = "depth_"  # the final model's depth errors where the true depth is known (eval.depth)
# the final row's columns that MLflow carries as metrics of the same name (written by tracking, read back
# by records_from_mlflow): one list, so a family added to the records reaches the read-back too
TRACKED_METRIC_PREFIXES = (UNCERTAINTY_PREFIX, DEPTH_PREFIX)


def uncertainty_columns(values: dict | None) -> dict:
    """``unc_<metric>`` columns of a final row (none when not measured)."""
    return {f"{UNCERTAINTY_PREFIX}{k}": v for k, v in (values or {}).items()}


def depth_columns(values: dict | None) -> dict:
    """``depth_<metric>`` columns of a final row (none when the scene's true depth is unknown)."""
    return {f"{DEPTH_PREFIX}{k}": v for k, v in (values or {}).items()}


def uncertainty_rows(base: dict, result: UncertaintyResult, seconds: float) -> list[dict]:
    rows = [{**base, "kind": "sparsification", "uncertainty_method": name, "fraction": f, "psnr": v}
            for name, curve in result.curves.items() for f, v in zip(result.fractions, curve)]
    rows += [{**base, "kind": "ause", "uncertainty_method": name, "ause": value}
             for name, value in result.ause.items()]
    rows.append({**base, "kind": "final", "psnr": float(np.mean(result.psnr)), "wall_seconds": seconds,
                 "test_views": len(result.psnr)})
    return rows


def worker_columns(outcome: JobOutcome) -> dict:
    """Where and under what the job ran (``executors.worker``): host, node, the worker's code
    version and packages, CPU model and the arithmetic's code paths, how many times it started (retries on another node,
    requeues, relaunches) and the seconds from its first start to its end."""
    w = outcome.worker
    if not w:
        return {}
    return {"host": w.get("host"), "node": w.get("node"), "worker_code_version": w.get("code_version"),
            "packages": w.get("packages"), "packages_locked": w.get("locked"), "cpu": w.get("cpu"),
            "numerics": w.get("numerics"),
            "starts": w.get("starts"),
            # numba's one-time compilation in this job (training and selection), seconds of wall_seconds
            "job_compile_seconds": w.get("compile_seconds"),
            "elapsed_seconds": round(w["ended"] - w["first_started"], 2) if "ended" in w else None}


def job_rows(job: Job, outcome: JobOutcome, run_id: str | None) -> list[dict]:
    base = {**identity(job, outcome, run_id), **worker_columns(outcome)}
    if not outcome.finished:
        return [{**base, "kind": "final", "error": outcome.traceback[-2000:],
                 "attempts": outcome.attempts}]
    if job.kind == "uncertainty":
        rows = uncertainty_rows(base, outcome.uncertainty, outcome.seconds)
    else:
        rows = episode_rows(base, outcome.episode, outcome.seconds)
    for row in rows:
        row["attempts"] = outcome.attempts
    return rows


class RecordsFile:
    def __init__(self, folder: str | Path):
        self.path = Path(folder) / RECORDS
        self.frame = pd.read_parquet(self.path) if self.path.exists() else pd.DataFrame()

    def finished_hashes(self) -> set[str]:
        return set(self.finished_versions())

    def finished_versions(self) -> dict[str, str | None]:
        """config hash -> code version of each finished job (None if not recorded)."""
        if self.frame.empty:
            return {}
        done = self.frame[(self.frame["kind"] == "final") & (self.frame["status"] == "FINISHED")]
        versions = done["code_version"] if "code_version" in done else [None] * len(done)
        return {h: (v if isinstance(v, str) else None) for h, v in zip(done["config_hash"], versions)}

    def add(self, rows: list[dict]) -> None:
        """Replace the rows of these jobs (by config hash) and rewrite the file atomically."""
        hashes = {r["config_hash"] for r in rows}
        kept = self.frame[~self.frame["config_hash"].isin(hashes)] if not self.frame.empty else self.frame
        self.frame = pd.concat([kept, pd.DataFrame(rows)], ignore_index=True)
        self.write()

    def supersede(self, hashes: set[str]) -> None:
        """Move the rows of these jobs to ``records_superseded.parquet`` (``data_changes``)."""
        from pipeline.experiment.data_changes import supersede
        self.frame = supersede(self.path.parent, self.frame, hashes)
        self.write()

    def write(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        self.frame.to_parquet(tmp, index=False)
        os.replace(tmp, self.path)


def records_from_mlflow(uri: str, experiment: str) -> pd.DataFrame:
    """Rebuild the records (final and round rows of episode jobs) from an MLflow experiment."""
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    found = client.get_experiment_by_name(experiment)
    if found is None:
        raise ValueError(f"{uri}: no MLflow experiment named {experiment!r}")
    runs, token = [], None
    while True:
        page = client.search_runs([found.experiment_id], "tags.config_hash != ''", max_results=1000,
                                  page_token=token)
        runs += list(page)
        token = page.token
        if not token:
            break
    rows = [row for run in current_runs(runs) for row in _rows_of_run(client, run, experiment)]
    if not rows:
        raise ValueError(f"{uri}: experiment {experiment!r} has no job runs")
    return pd.DataFrame(rows)


def current_runs(runs: list) -> list:
    """One run per job of each sweep folder (output_dir tag, config hash): its latest FINISHED
    run, else its latest run. A replay (tracking_sync) or a relaunch leaves the runs it supersedes
    (KILLED, FAILED, a partial child run of an outage) beside the one that counts; a report reads
    only that one. Two sweep folders that ran the same job keep one run each."""
    chosen: dict[tuple, object] = {}
    for run in runs:
        key = (run.data.tags.get("output_dir"), run.data.tags["config_hash"])
        best = chosen.get(key)
        rank = (run.info.status == "FINISHED", run.info.start_time or 0)
        if best is None or rank > (best.info.status == "FINISHED", best.info.start_time or 0):
            chosen[key] = run
    return list(chosen.values())


def _rows_of_run(client, run, experiment: str) -> list[dict]:
    tags, metrics, params = run.data.tags, run.data.metrics, run.data.params
    base = {"sweep": experiment, "config_hash": tags["config_hash"], "run_id": run.info.run_id,
            "status": run.info.status, "job_kind": tags.get("kind", "episode"), "dataset": tags.get("dataset"),
            "scene": tags.get("scene"), "method": tags.get("method"), "strategy": tags.get("strategy"),
            "protocol": tags.get("protocol"), "seed": int(tags.get("seed", 0)),
            "setting": tags.get("setting", ""), "axes": params.get("axes", "{}"),
            "code_version": tags.get("code_version"), "data_fingerprint": tags.get("data_fingerprint"),
            "world": params.get("world.kind", "dataset"),
            "job_index": int(tags["job_index"]) if "job_index" in tags else None}
    final = {**base, "kind": "final", **{c.column: metrics.get(c.metric) for c in FINAL_METRICS},
             **{c.column: c.decode_tag(tags.get(c.tag)) for c in FINAL_TAGS},
             "wall_seconds": metrics.get("wall_seconds"),
             **{k: v for k, v in metrics.items() if k.startswith(TRACKED_METRIC_PREFIXES)}}
    version = final["metrics_version"] = int(tags.get("metrics_version", 1))  # version 1: final_ssim was skimage's
    if version < 2:
        final["ssim"], final["ssim_skimage"] = None, metrics.get("final_ssim")
    logged = [c.metric for c in ROUND_METRICS] + list(SEARCH_METRICS)
    history = {key: {m.step: m.value for m in client.get_metric_history(run.info.run_id, key)} if key in metrics else {}
               for key in logged}  # run.data.metrics names every metric the run logged
    if version < 2:
        history["test_ssim_skimage"], history["test_ssim"] = history["test_ssim"], {}
    final.update({c.column: mean_present(list(history[c.metric].values())) for c in PICK_COLUMNS})  # over the picks
    rounds = [{**base, "kind": "round", "num_views": step,
               **{c.column: history[c.metric].get(step) for c in ROUND_METRICS}, **_search_columns(history, step)}
              for step in sorted(history["test_psnr"])]
    if "acquired_poses" in tags:  # a search round that took its pose took the next captured one
        poses = iter(json.loads(tags["acquired_poses"]))
        final["poses"] = tags["acquired_poses"]
        for row in rounds:  # as episode_rows writes them: null for a round whose pool pick stood
            if "search_taken" in row:
                row["poses"] = json.dumps([next(poses)] if row["search_taken"] != "pool" else None)
    return rounds + [final]


# the round metrics of a search off the pool (tracking.round_metrics logs them) and their record columns;
# search_taken as a metric: which pick a round took (a captured view has a pose: search, pool_captured)
SEARCH_SCORES = ("score", "best_start_score", "best_pool_score")
SEARCH_METRICS = (*(f"search_{k}" for k in SEARCH_SCORES), "search_taken")
SEARCH_TAKEN_CODES = {"pool": 0.0, "search": 1.0, "pool_captured": 2.0}
SEARCH_TAKEN_NAMES = {code: name for name, code in SEARCH_TAKEN_CODES.items()}


def _search_columns(history: dict, step: int) -> dict:
    if step not in history.get("search_taken", {}):
        return {}
    return {"search_taken": SEARCH_TAKEN_NAMES[history["search_taken"][step]],
            **{key: history[key].get(step) for key in SEARCH_METRICS if key != "search_taken"}}
